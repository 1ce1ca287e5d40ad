"""SfM's choices made from the photos before anything slow: SIFT's size (the size training loads the
photos at), the mapper by count, and options refused with one line."""

from __future__ import annotations

import dataclasses
from types import SimpleNamespace

import pytest

from hico_plugin.data.images import MAX_LONG_SIDE
from hico_plugin.data.parser import DataParserConfig
from hico_plugin.errors import HicoError
from hico_plugin.process.ingest import PhotoInfo
from hico_plugin.process.sfm import SfmOptions, check_options, choose_mapper, feature_sizes, map_with_fallback


def _loaded_long_side(sizes: list[tuple[int, int]], max_long_side: int) -> list[int]:
    """The long side hico-train loads photos of ``sizes`` at (its automatic downscale of the whole set)."""
    record = SimpleNamespace(cameras={i: SimpleNamespace(width=w, height=h) for i, (w, h) in enumerate(sizes)})
    factor = DataParserConfig(max_long_side=max_long_side)._auto_downscale(record, [])
    return [round(max(w, h) / factor) for w, h in sizes]


@pytest.mark.parametrize("sizes", [[(1600, 1200)], [(4000, 3000)], [(3200, 2400)], [(1000, 750)],
                                   [(4032, 3024), (1920, 1080)], [(1080, 1920), (640, 480)]])
def test_features_are_extracted_at_the_size_training_loads(sizes):
    infos = {f"{i}.jpg": PhotoInfo(w, h, "", "", None) for i, (w, h) in enumerate(sizes)}
    groups = [[name] for name in infos]
    assert SfmOptions().max_image_size == DataParserConfig().max_long_side == MAX_LONG_SIDE
    for max_long_side in (MAX_LONG_SIDE, 1000):
        assert feature_sizes(infos, groups, max_long_side) == _loaded_long_side(sizes, max_long_side)
    assert max(feature_sizes(infos, groups, MAX_LONG_SIDE)) <= MAX_LONG_SIDE


def test_the_mapper_follows_the_count():
    options = SfmOptions()
    assert choose_mapper(options.incremental_max, options)[0] == "incremental"
    assert choose_mapper(options.incremental_max + 1, options)[0] == "global"
    assert choose_mapper(5, dataclasses.replace(options, incremental_max=4))[0] == "global"
    assert choose_mapper(5000, SfmOptions(mapper="incremental")) == ("incremental", "asked for (--mapper incremental)")


@pytest.mark.parametrize("field, value, message", [
    ("exhaustive_max", 0, "--exhaustive-max: expected a whole number >= 1, got 0"),
    ("neighbors", -3, "--neighbors: expected a whole number >= 1, got -3"),
    ("max_image_size", 0, "--max-image-size: expected a whole number >= 1, got 0"),
    ("camera_model", "PINHOL", "--camera-model: unknown COLMAP model 'PINHOL'"),
])
def test_bad_options_are_one_line(field, value, message):
    with pytest.raises(HicoError, match=message.replace("(", r"\(")):
        check_options(dataclasses.replace(SfmOptions(), **{field: value}))


def test_a_missing_vocabulary_tree_is_refused(tmp_path):
    with pytest.raises(HicoError, match=r"--vocab-tree .*none.bin: file not found"):
        check_options(SfmOptions(vocab_tree=tmp_path / "none.bin"))


def _mapper_that_fails(*failing: str):
    tried = []

    def map_one(mapper: str) -> dict:
        tried.append(mapper)
        if mapper in failing:
            raise HicoError(f"{mapper}: only 2 of 100 images registered")
        return {"mapper": mapper}

    return map_one, tried


@pytest.mark.parametrize("first,other", [("incremental", "global"), ("global", "incremental")])
def test_auto_mapping_hands_a_set_the_first_mapper_fails_to_the_other(first, other):
    map_one, tried = _mapper_that_fails(first)
    said = []
    assert map_with_fallback(map_one, first, True, said.append) == {"mapper": other}
    assert tried == [first, other] and f"the {first} mapper fell short" in said[0]


def test_a_named_mapper_or_two_failures_end_in_the_error():
    map_one, tried = _mapper_that_fails("incremental")
    with pytest.raises(HicoError, match="incremental: only 2"):
        map_with_fallback(map_one, "incremental", False, print)  # --mapper incremental: no other
    assert tried == ["incremental"]
    map_one, tried = _mapper_that_fails("incremental", "global")
    with pytest.raises(HicoError, match="global: only 2"):
        map_with_fallback(map_one, "incremental", True, lambda line: None)
    assert tried == ["incremental", "global"]
