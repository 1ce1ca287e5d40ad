"""hico_plugin.export: PLY round trips, the Inria row layout with bad rows dropped and counted, the
COLMAP-frame mapping, camera paths (quaternions, slerp, orbit, interpolate) and frame writers."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
import torch

from hico_plugin.cameras import Cameras
from hico_plugin.data.transform import SceneTransform
from hico_plugin.errors import HicoError
from hico_plugin.export import (
    anchor_vertices,
    gaussians_to_colmap,
    inria_vertices,
    interpolate_path,
    orbit_path,
    read_ply,
    write_ply,
)
from hico_plugin.export.camera_paths import keyframe_path, quat_slerp, quat_to_rotmat, rotmat_to_quat
from hico_plugin.export.frames import Mp4Writer, write_png
from hico_plugin.export.gaussians import INRIA_FIELDS, SH_C0
from hico_plugin.scenes.orbits import intrinsics, look_at


def test_ply_round_trip_keeps_every_type_and_value(tmp_path):
    rng = np.random.default_rng(0)
    rows = np.empty(7, dtype=[("x", "<f4"), ("d", "<f8"), ("level", "<i4"), ("n", "<u2"), ("red", "u1"), ("s", "i1")])
    for name in rows.dtype.names:
        rows[name] = rng.integers(-100 if name in ("x", "d", "level", "s") else 0, 100, size=7)
    rows["x"] += 0.25
    path = write_ply(tmp_path / "sub" / "a.ply", rows)
    header = path.read_bytes().split(b"end_header\n")[0].decode()
    assert "format binary_little_endian 1.0" in header and "element vertex 7" in header
    assert "property uchar red" in header and "property double d" in header
    back = read_ply(path)
    assert back.dtype.names == rows.dtype.names
    for name in rows.dtype.names:
        np.testing.assert_array_equal(back[name], rows[name])
    assert [p.name for p in path.parent.iterdir()] == ["a.ply"]  # no temp file left behind


def test_ply_empty_and_bad_files(tmp_path):
    empty = np.empty(0, dtype=[(name, "<f4") for name in INRIA_FIELDS])
    assert len(read_ply(write_ply(tmp_path / "empty.ply", empty))) == 0
    ascii_ply = b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nend_header\n1.0\n"
    (tmp_path / "ascii.ply").write_bytes(ascii_ply)
    with pytest.raises(HicoError, match="binary_little_endian"):
        read_ply(tmp_path / "ascii.ply")
    data = (tmp_path / "empty.ply").read_bytes().replace(b"vertex 0", b"vertex 2")
    (tmp_path / "short.ply").write_bytes(data)
    with pytest.raises(HicoError, match="bytes of vertex data"):
        read_ply(tmp_path / "short.ply")
    with pytest.raises(HicoError, match="not found"):
        read_ply(tmp_path / "missing.ply")


def _gaussians(n: int, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    means = torch.randn(n, 3, generator=g)
    quats = torch.randn(n, 4, generator=g)
    scales = torch.rand(n, 3, generator=g) * 0.1 + 0.01
    opacities = torch.rand(n, generator=g) * 0.9 + 0.05
    colors = torch.rand(n, 3, generator=g)
    return means, quats, scales, opacities, colors


def test_inria_rows_drop_and_count_bad_rows_and_round_trip(tmp_path):
    means, quats, scales, opacities, colors = _gaussians(12)
    means[0, 1] = float("nan")
    scales[1, 2] = float("inf")
    scales[2, 0] = 0.0  # log scale -inf
    colors[3, 0] = float("nan")
    quats[4] = 0.0
    opacities[5] = 0.5 / 255
    opacities[6] = 0.0
    quats[7] = 0.0
    opacities[7] = 0.0  # zero quaternion and transparent: counted once, as zero quaternion
    opacities[8] = 1.0  # logit stays finite
    rows, dropped = inria_vertices(means, quats, scales, opacities, colors)
    assert (dropped.non_finite, dropped.zero_quaternion, dropped.transparent, dropped.kept) == (4, 2, 2, 4)
    assert dropped.dropped == 8 and len(rows) == 4 and rows.dtype.names == INRIA_FIELDS
    keep = torch.tensor([8, 9, 10, 11])
    back = read_ply(write_ply(tmp_path / "g.ply", rows))
    xyz = np.stack([back["x"], back["y"], back["z"]], -1)
    np.testing.assert_allclose(xyz, means[keep].numpy(), rtol=1e-6)
    f_dc = np.stack([back[f"f_dc_{i}"] for i in range(3)], -1)
    np.testing.assert_allclose(f_dc * SH_C0 + 0.5, colors[keep].numpy(), atol=1e-6)
    np.testing.assert_allclose(1 / (1 + np.exp(-back["opacity"])), opacities[keep].numpy(), atol=1e-6)
    assert np.isfinite(back["opacity"]).all() and back["opacity"][0] > 10
    log_scales = np.stack([back[f"scale_{i}"] for i in range(3)], -1)
    np.testing.assert_allclose(np.exp(log_scales), scales[keep].numpy(), rtol=1e-5)
    rot = np.stack([back[f"rot_{i}"] for i in range(4)], -1)
    expected = torch.nn.functional.normalize(quats[keep], dim=-1).numpy()
    np.testing.assert_allclose(rot, expected, atol=1e-6)
    np.testing.assert_array_equal(np.stack([back["nx"], back["ny"], back["nz"]], -1), 0.0)


def test_colmap_frame_undoes_the_normalisation():
    colmap_means = torch.tensor([[10.0, -4.0, 2.0], [3.0, 3.0, 3.0], [0.0, 1.0, 0.0]], dtype=torch.float64)
    centre = torch.tensor([1.0, 2.0, 3.0], dtype=torch.float64)
    transform = SceneTransform(centre, 0.25, _random_rotations(1, seed=3)[0])
    normalised = transform.points_from_colmap(colmap_means)
    scales = torch.tensor([[0.1, 0.2, 0.3], [1.0, 1.0, 1.0], [1.0, 2.0, 3.0]], dtype=torch.float64)
    colmap_axes = _random_rotations(3, seed=4)
    quats = rotmat_to_quat(transform.rotation @ colmap_axes) * torch.tensor([[2.0], [0.5], [0.0]], dtype=torch.float64)
    means, colmap_quats, colmap_scales = gaussians_to_colmap(normalised, quats, scales, transform)
    torch.testing.assert_close(means, colmap_means)
    torch.testing.assert_close(colmap_scales, scales * 4)
    assert colmap_quats[2].abs().max() == 0  # a zero quaternion stays zero (the exporter drops it)
    unit = torch.nn.functional.normalize(colmap_quats[:2], dim=-1)
    torch.testing.assert_close(quat_to_rotmat(unit), colmap_axes[:2], atol=1e-12, rtol=0)


def test_anchor_rows_hold_positions_levels_features_colours():
    positions, features = torch.randn(5, 3), torch.randn(5, 4)
    levels = torch.tensor([0, 1, 2, 1, 0])
    colors = np.arange(15, dtype=np.uint8).reshape(5, 3)
    rows = anchor_vertices(positions, levels, features, colors)
    assert rows.dtype.names[:4] == ("x", "y", "z", "level") and rows.dtype.names[-3:] == ("red", "green", "blue")
    np.testing.assert_array_equal(rows["level"], levels.numpy())
    np.testing.assert_allclose(np.stack([rows[f"f_anchor_{i}"] for i in range(4)], -1), features.numpy())
    np.testing.assert_array_equal(rows["blue"], colors[:, 2])


def _random_rotations(n: int, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    q = torch.nn.functional.normalize(torch.randn(n, 4, generator=g, dtype=torch.float64), dim=-1)
    return quat_to_rotmat(q)


def test_rotmat_quat_round_trip_including_half_turns():
    rot = _random_rotations(200)
    half_turns = quat_to_rotmat(torch.tensor([[0.0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1], [0, 0.6, 0.8, 0],
                                              [1e-9, 0, 0, 1]], dtype=torch.float64))
    rot = torch.cat([rot, half_turns, torch.eye(3, dtype=torch.float64)[None]])
    quats = rotmat_to_quat(rot)
    assert (quats[:, 0] >= 0).all()
    torch.testing.assert_close(quats.norm(dim=-1), torch.ones(len(rot), dtype=torch.float64))
    torch.testing.assert_close(quat_to_rotmat(quats), rot, atol=1e-12, rtol=0)


def test_slerp_moves_at_constant_angular_speed_along_the_short_arc():
    q0 = torch.tensor([1.0, 0, 0, 0], dtype=torch.float64)
    angle = 2.0  # radians about z
    q1 = -torch.tensor([math.cos(angle / 2), 0, 0, math.sin(angle / 2)], dtype=torch.float64)  # same rotation, far sign
    t = torch.linspace(0, 1, 5, dtype=torch.float64)
    out = quat_slerp(q0.expand(5, 4), q1.expand(5, 4), t)
    rot = quat_to_rotmat(out)
    angles = torch.atan2(rot[:, 1, 0], rot[:, 0, 0])
    torch.testing.assert_close(angles, t * angle)
    same = quat_slerp(q0[None], q0[None] * (1 + 1e-12), torch.tensor([0.3], dtype=torch.float64))
    torch.testing.assert_close(same[0], q0)


def _ring(num: int, radius: float, height: float, centre: np.ndarray, width: int = 40, height_px: int = 30) -> Cameras:
    angles = np.linspace(0, 2 * np.pi, num, endpoint=False) + 0.3
    eyes = centre + np.stack([radius * np.cos(angles), radius * np.sin(angles), np.full(num, height)], -1)
    viewmats = torch.tensor(look_at(eyes, np.repeat(centre[None], num, 0)), dtype=torch.float32)
    K = torch.tensor(intrinsics(width, height_px, 60.0), dtype=torch.float32)
    return Cameras(viewmats, K.expand(num, 3, 3).clone(), torch.full((num,), width), torch.full((num,), height_px))


def test_orbit_circles_the_scene_centre_at_the_cameras_height_and_radius():
    centre = np.array([1.0, -2.0, 0.5])
    ring = _ring(9, radius=3.0, height=1.5, centre=centre)
    orbit = orbit_path(ring, 16)
    assert len(orbit) == 16 and orbit.viewmats.dtype == torch.float32
    eyes = orbit.centers.double() - torch.tensor(centre)
    torch.testing.assert_close(eyes[:, 2], torch.full((16,), 1.5, dtype=torch.float64), atol=1e-4, rtol=0)
    torch.testing.assert_close(eyes[:, :2].norm(dim=-1), torch.full((16,), 3.0, dtype=torch.float64), atol=1e-4, rtol=0)
    # The centre projects to the principal point, and image-up is world-up (z).
    target_cam = orbit.viewmats[:, :3, :3].double() @ torch.tensor(centre) + orbit.viewmats[:, :3, 3].double()
    torch.testing.assert_close(target_cam[:, :2], torch.zeros(16, 2, dtype=torch.float64), atol=1e-4, rtol=0)
    assert (orbit.viewmats[:, 1, 2] < 0).all()  # camera y (down) points against world z
    bearings = torch.atan2(eyes[:, 1], eyes[:, 0])
    steps = torch.remainder(bearings.diff(), 2 * math.pi)
    torch.testing.assert_close(steps, torch.full((15,), 2 * math.pi / 16, dtype=torch.float64), atol=1e-4, rtol=0)


def test_orbit_rejects_cameras_without_a_common_up():
    ring = _ring(4, 3.0, 0.0, np.zeros(3))
    flipped = ring.viewmats.clone()
    flipped[2:, :2] *= -1  # half the cameras upside down: the up directions cancel
    with pytest.raises(HicoError, match="up direction"):
        orbit_path(Cameras(flipped, ring.Ks, ring.widths, ring.heights), 4)


def test_interpolate_passes_through_the_cameras():
    ring = _ring(4, radius=2.0, height=0.5, centre=np.zeros(3))
    path = interpolate_path(ring, 7)  # keys at frames 0, 2, 4, 6
    torch.testing.assert_close(path.viewmats[::2], ring.viewmats, atol=1e-5, rtol=0)
    mid = path.centers[1]
    torch.testing.assert_close(mid, (ring.centers[0] + ring.centers[1]) / 2, atol=1e-5, rtol=0)
    rot = path.viewmats[:, :3, :3].double()
    identity = torch.eye(3, dtype=torch.float64).expand(7, 3, 3)
    torch.testing.assert_close(rot @ rot.transpose(1, 2), identity, atol=1e-6, rtol=0)
    single = Cameras(ring.viewmats[:1], ring.Ks[:1], ring.widths[:1], ring.heights[:1])
    torch.testing.assert_close(interpolate_path(single, 3).viewmats, ring.viewmats[:1].expand(3, 4, 4))
    with pytest.raises(HicoError, match="frames"):
        interpolate_path(ring, 0)


def test_interpolate_rescales_intrinsics_to_the_first_size():
    ring = _ring(2, radius=2.0, height=0.5, centre=np.zeros(3))
    Ks = ring.Ks.clone()
    Ks[1, :2] *= 2  # the second camera at twice the resolution
    cams = Cameras(ring.viewmats, Ks, torch.tensor([40, 80]), torch.tensor([30, 60]))
    path = interpolate_path(cams, 3)
    assert path.widths.tolist() == [40] * 3
    torch.testing.assert_close(path.Ks[2], ring.Ks[1])


def test_keyframe_path_reaches_each_keyframe_at_its_time_smoothly():
    keys = _ring(4, radius=2.0, height=0.5, centre=np.zeros(3))
    seconds = torch.tensor([1.0, 0.5, 1.5, 2.0])  # the last counts only for a loop
    path = keyframe_path(keys, seconds, fps=10)
    assert len(path) == 31 and path.widths.tolist() == [40] * 31  # 3 s at 10 fps, both ends included
    torch.testing.assert_close(path.viewmats[[0, 10, 15, 30]], keys.viewmats, atol=1e-5, rtol=0)
    rot = path.viewmats[:, :3, :3].double()
    torch.testing.assert_close(rot @ rot.transpose(1, 2), torch.eye(3, dtype=torch.float64).expand(31, 3, 3),
                               atol=1e-6, rtol=0)
    # the velocity (m/s) has no jump where the 1 s transition meets the 0.5 s one (keyframe 1, t = 1 s)
    fine = keyframe_path(keys, seconds, fps=1000).centers.double()
    velocity = (fine[1:] - fine[:-1]) * 1000
    assert (velocity[1000] - velocity[999]).norm() < 0.01 * velocity[999].norm()
    loop = keyframe_path(keys, seconds, fps=10, loop=True)
    assert len(loop) == 50  # 5 s, the return to the first keyframe is the next frame after the last
    torch.testing.assert_close(loop.viewmats[[0, 10, 15, 30]], keys.viewmats, atol=1e-5, rtol=0)
    assert (loop.centers[-1] - keys.centers[0]).norm() < 0.45
    single = keyframe_path(Cameras(keys.viewmats[:1], keys.Ks[:1], keys.widths[:1], keys.heights[:1]), seconds[:1], 10)
    assert len(single) == 1
    with pytest.raises(HicoError, match="transition"):
        keyframe_path(keys, torch.tensor([1.0, 0.0, 1.0, 1.0]), fps=10)


def test_png_and_mp4_writers(tmp_path):
    image = np.zeros((30, 40, 3), np.uint8)
    image[..., 0] = 200  # red
    path = write_png(tmp_path / "f" / "00000.png", image)
    np.testing.assert_array_equal(cv2.imread(str(path))[..., ::-1], image)
    video = Mp4Writer(tmp_path / "v.mp4", 10, 40, 30)
    if not video.available:
        pytest.skip("no video writer in this OpenCV build")
    for _ in range(5):
        video.write(image)
    with pytest.raises(ValueError, match="frame of"):
        video.write(np.zeros((10, 10, 3), np.uint8))
    assert video.close()
    capture = cv2.VideoCapture(str(tmp_path / "v.mp4"))
    assert int(capture.get(cv2.CAP_PROP_FRAME_COUNT)) == 5
    capture.release()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["f", "v.mp4"]
    odd = Mp4Writer(tmp_path / "odd.mp4", 10, 21, 15)
    odd.write(np.full((15, 21, 3), 100, np.uint8))
    assert odd.close()
    capture = cv2.VideoCapture(str(tmp_path / "odd.mp4"))
    ok, frame = capture.read()
    capture.release()
    assert ok and frame.shape == (16, 22, 3)  # padded to even, nothing cut off


def test_hico_export_offers_every_registered_exporter_and_skips_one_without_defaults(monkeypatch):
    from dataclasses import dataclass

    from hico_plugin.cli.export import parse
    from hico_plugin.export.exporters import EXPORTERS, Exporter

    @dataclass
    class NeedsAPath(Exporter):
        """A plug-in's mistake: an option without a default."""

        path: str

    monkeypatch.setitem(EXPORTERS._entries, "needs-a-path", NeedsAPath)  # registered for this test only
    with pytest.warns(UserWarning, match="exporter 'needs-a-path' .* left out: every option needs a default"):
        defaults = EXPORTERS.defaults()
        args = parse(["--load-config", "RUN/config.yml", "anchors", "--output", "a.ply"])
    assert {"gaussians", "anchors", "mesh"} <= set(defaults) and "needs-a-path" not in defaults
    assert type(args.target).__name__ == "ExportAnchors" and str(args.target.output) == "a.ply"
