"""SPZ: the writer's quantisation read back by this package's decoder and by a real third-party reader,
PlayCanvas's splat-transform (npm @playcanvas/splat-transform 3.7.0, installed on first use; the test
needs Node.js and npm, and skips without them)."""

from __future__ import annotations

import shutil
import subprocess

import numpy as np
import pytest
import torch

from hico_plugin.errors import HicoError
from hico_plugin.export.gaussians import inria_vertices
from hico_plugin.export.ply import read_ply, write_ply
from hico_plugin.export.spz import fractional_bits, read_spz, write_spz

SPLAT_TRANSFORM = "@playcanvas/splat-transform@3.7.0"
# half a quantisation step of each attribute (positions at 12 fractional bits), and 8-bit rounding
TOLERANCE = {"x": 2**-13, "y": 2**-13, "z": 2**-13, "f_dc_0": 0.5 / (0.15 * 255) + 1e-4,
             "scale_0": 0.5 / 16 + 1e-4}


def _rows(count: int = 300, offset: float = 10.0) -> np.ndarray:
    gen = torch.Generator().manual_seed(0)
    rows, _ = inria_vertices(torch.randn(count, 3, generator=gen) * 3 + offset,
                             torch.randn(count, 4, generator=gen), torch.rand(count, 3, generator=gen) * 0.3 + 1e-3,
                             torch.rand(count, generator=gen) * 0.95 + 0.02, torch.rand(count, 3, generator=gen))
    return rows


def _assert_same(expected: np.ndarray, got: np.ndarray) -> None:
    assert len(got) == len(expected)
    for name, tolerance in TOLERANCE.items():
        assert np.abs(got[name] - expected[name]).max() <= tolerance, name
    opacity = lambda r: 1 / (1 + np.exp(-r["opacity"].astype(np.float64)))  # noqa: E731
    assert np.abs(opacity(got) - opacity(expected)).max() <= 0.5 / 255 + 1e-4
    quat = lambda r: np.stack([r[f"rot_{i}"] for i in range(4)], 1).astype(np.float64)  # noqa: E731
    assert np.abs((quat(got) * quat(expected)).sum(1)).min() > 0.9999  # q and -q are one rotation


def test_spz_round_trip_within_its_quantisation(tmp_path):
    rows = _rows()
    path = write_spz(tmp_path / "g.spz", rows)
    _assert_same(rows, read_spz(path))
    assert path.stat().st_mode & 0o777 == 0o644
    ply = write_ply(tmp_path / "g.ply", rows)
    assert path.stat().st_size < 0.3 * ply.stat().st_size  # 20 bytes a Gaussian before gzip, the PLY's 68


def test_large_coordinates_keep_fewer_fractional_bits_and_bad_files_are_refused(tmp_path):
    assert fractional_bits(np.array([[1000.0, 0, 0]])) == 12 and fractional_bits(np.array([[3000.0, 0, 0]])) == 11
    far = _rows(offset=5000.0)
    back = read_spz(write_spz(tmp_path / "far.spz", far))
    assert np.abs(back["x"] - far["x"]).max() <= 2**-10  # 9 fractional bits
    with pytest.raises(ValueError, match="does not fit"):
        fractional_bits(np.array([[1e7, 0, 0]]))
    (tmp_path / "bad.spz").write_bytes(b"not gzip")
    with pytest.raises(HicoError, match="not an SPZ file"):
        read_spz(tmp_path / "bad.spz")


@pytest.fixture(scope="session")
def splat_transform(tmp_path_factory):
    if shutil.which("node") is None or shutil.which("npm") is None:
        pytest.skip("Node.js / npm not installed (the third-party SPZ reader is an npm package)")
    prefix = tmp_path_factory.mktemp("npm")
    subprocess.run(["npm", "install", "--prefix", str(prefix), "--no-audit", "--no-fund", "--ignore-scripts",
                    SPLAT_TRANSFORM], check=True, capture_output=True, text=True, timeout=600)
    return prefix / "node_modules" / ".bin" / "splat-transform"


def test_playcanvas_splat_transform_reads_the_spz_as_the_export(splat_transform, tmp_path):
    rows = _rows()
    spz = write_spz(tmp_path / "g.spz", rows)
    converted = tmp_path / "from_spz.ply"
    done = subprocess.run([str(splat_transform), str(spz), str(converted)], capture_output=True, text=True,
                          timeout=300)
    assert done.returncode == 0, done.stdout + done.stderr
    _assert_same(rows, read_ply(converted))  # count, positions, colours, opacities, scales, rotations
