"""--matcher auto's rule: every pair for a small set, then a matcher whose pairs grow linearly with the photos."""

from __future__ import annotations

import dataclasses
import os

import pytest

from hico_plugin.process.ingest import PhotoInfo
from hico_plugin.process.matching import _stderr_without, _unique, choose_matcher
from hico_plugin.process.sfm import SfmOptions


def _photos(count: int, gps=lambda i: None) -> list[PhotoInfo]:
    return [PhotoInfo(640, 480, "", "", None, gps(i)) for i in range(count)]


def _spread(i: int) -> tuple[float, float, float]:
    return 47.0 + 1e-4 * i, 8.0, 400.0


def test_small_sets_match_every_pair_and_large_ones_a_bounded_number():
    options = SfmOptions()
    small = options.exhaustive_max
    assert choose_matcher(_photos(small, _spread), options, ordered=False)[0] == "exhaustive"
    assert choose_matcher(_photos(small), options, ordered=True)[0] == "exhaustive"
    name, why = choose_matcher(_photos(small + 1, _spread), options, ordered=False)
    assert name == "spatial" and "GPS" in why and f"the {options.neighbors} nearest" in why
    assert choose_matcher(_photos(small + 1), options, ordered=True)[0] == "sequential"
    name, why = choose_matcher(_photos(small + 1), options, ordered=False)
    assert name == "vocabtree" and "none with GPS in its EXIF" in why
    # The threshold is the one field: moved, the rule follows it.
    assert choose_matcher(_photos(8, _spread), dataclasses.replace(options, exhaustive_max=7), False)[0] == "spatial"


def test_spatial_needs_every_photo_located_at_distinct_places():
    options = SfmOptions(exhaustive_max=10)
    half = choose_matcher(_photos(20, lambda i: _spread(i) if i % 2 else None), options, ordered=False)
    assert half[0] == "vocabtree" and "GPS in the EXIF of only 10" in half[1]
    stale = choose_matcher(_photos(20, lambda i: _spread(i % 3)), options, ordered=False)
    assert stale[0] == "vocabtree" and "only 3 distinct positions" in stale[1]


@pytest.mark.parametrize("matcher", ["exhaustive", "sequential", "spatial", "vocabtree"])
def test_an_explicit_matcher_is_kept(matcher):
    name, why = choose_matcher(_photos(500, _spread), SfmOptions(matcher=matcher), ordered=True)
    assert (name, why) == (matcher, f"asked for (--matcher {matcher})")


def test_pairs_are_listed_once_each_way():
    assert _unique([(1, 2), (2, 1), (3, 3), (3, 1), (1, 3), (2, 4)]) == [(1, 2), (1, 3), (2, 4)]


def test_held_back_lines_are_dropped_and_the_others_kept(capfd):
    with _stderr_without("WARNING clustering"):
        os.write(2, b"WARNING clustering 64 points to 16 centroids\nsomething else\n")
    assert capfd.readouterr().err == "something else\n"
