"""Fixtures shared by several test modules."""

from __future__ import annotations

from pathlib import Path

import pytest


@pytest.fixture(scope="session")
def tiny_run(tmp_path_factory) -> Path:
    """The directory of a tiny trained run: hico-gs-lite, built-in `tiny` scene, 2 steps, no viewer,
    octree levels forced on (tiny's views stand at one distance, so auto would train one level, and the
    export, viewer and evaluation tests read levels).

    Trained once per session (about half the time of the CLI tests). Tests may add files to it and
    rewrite eval.json (hico-eval does), but must not remove what training wrote."""
    from hico_plugin.cli.train import parse, train

    out = tmp_path_factory.mktemp("tiny-run")
    train(parse(["hico-gs-lite", "--scene", "tiny", "--max-steps", "2", "--vis", "none", "--progress", "none",
                 "--output-dir", str(out), "--model.eval-lpips", "none", "--model.renderer.no-use-compile",
                 "--model.effects", "auto,lod=on"]))
    return out


@pytest.fixture(scope="session")
def large_colmap_dataset(tmp_path_factory) -> Path:
    """A COLMAP dataset of 300 photos of 1600x1200 px (one JPEG hard-linked 300 times): decoding and
    analysing it takes seconds, so a check that runs after that is plain to see."""
    from helpers_datasets import write_large_colmap_dataset

    return write_large_colmap_dataset(tmp_path_factory.mktemp("large-colmap"))
