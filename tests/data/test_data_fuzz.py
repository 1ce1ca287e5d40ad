"""Fuzzing the COLMAP parser with hypothesis: random byte flips in the sparse model and the images,
random image names. Every case either loads or fails with one HicoError line; nothing escapes as
another exception, and no path the dataset would read lies outside images/.

Case counts: ``pytest tests/data/test_data_fuzz.py --hypothesis-show-statistics``.
"""

from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hico_plugin.scenes.ring_dataset import write_ring_dataset

from hico_plugin.data import DataParserConfig
from hico_plugin.errors import HicoError

FUZZ = settings(max_examples=int(os.environ.get("HICO_FUZZ_EXAMPLES", "200")), deadline=None, derandomize=True,
                suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])


@pytest.fixture(scope="module")
def templates(tmp_path_factory):
    root = tmp_path_factory.mktemp("fuzz")
    write_ring_dataset(root / "bin", num_images=4, num_points=12)
    write_ring_dataset(root / "txt", num_images=4, num_points=12, text=True)
    return root


def _load_or_one_line(root: Path) -> None:
    """Parse ``root`` and decode every view; only a one-line HicoError may come out."""
    try:
        dataset = DataParserConfig(data=root, cache_dir=root / "cache").setup()
        images = (root / "images").resolve()
        assert all(Path(p).resolve().is_relative_to(images) for p in dataset.image_paths)
        dataset.verify_images()
    except HicoError as err:
        assert "\n" not in str(err), str(err)


def _flip(data: bytes, flips: list[tuple[int, int]]) -> bytes:
    data = bytearray(data)
    for position, value in flips:
        data[position % len(data)] = value
    return bytes(data)


_FLIPS = st.lists(st.tuples(st.integers(0, 2**20), st.integers(0, 255)), min_size=1, max_size=8)


@FUZZ
@given(kind=st.sampled_from(["bin", "txt"]), name=st.sampled_from(["cameras", "images", "points3D"]), flips=_FLIPS)
def test_byte_flips_in_the_sparse_model(templates, kind, name, flips):
    with tempfile.TemporaryDirectory() as folder:
        root = Path(folder) / "data"
        shutil.copytree(templates / kind, root)
        path = root / "sparse" / "0" / f"{name}.{kind}"
        path.write_bytes(_flip(path.read_bytes(), flips))
        _load_or_one_line(root)


@FUZZ
@given(flips=_FLIPS, truncate=st.integers(0, 4000), index=st.integers(0, 3))
def test_byte_flips_and_truncation_of_an_image(templates, flips, truncate, index):
    with tempfile.TemporaryDirectory() as folder:
        root = Path(folder) / "data"
        shutil.copytree(templates / "bin", root)
        path = sorted((root / "images").iterdir())[index]
        data = _flip(path.read_bytes(), flips)
        path.write_bytes(data[: max(0, len(data) - truncate)])
        _load_or_one_line(root)


_NAME_PARTS = st.sampled_from(["..", ".", "/", "\\", "view_001.png", "a", "C:", "~", " ", "%2e%2e", "\x00", "é"])


@FUZZ
@given(parts=st.lists(st.one_of(_NAME_PARTS, st.text(min_size=1, max_size=6)), min_size=1, max_size=6))
def test_random_image_names(templates, parts):
    name = "".join(parts)
    if any(c in name for c in "\n\r\t") or name != name.strip() or "#" in name:
        name = name.replace("\n", "").replace("\r", "").replace("\t", "").replace("#", "").strip() or "x"
    with tempfile.TemporaryDirectory() as folder:
        root = Path(folder) / "data"
        shutil.copytree(templates / "txt", root)
        images_txt = root / "sparse" / "0" / "images.txt"
        images_txt.write_text(images_txt.read_text().replace("view_002.png", name.replace(" ", "_")))
        _load_or_one_line(root)
