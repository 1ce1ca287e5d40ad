"""The district: a large grid of blocks with landmarks, seen by a drone's nadir and oblique grid and
from street level; exact depth, normals and surface points against the analytic geometry."""

from __future__ import annotations

import collections
import json

import numpy as np
import pytest

from hico_plugin.data.parser import DataParserConfig
from hico_plugin.errors import HicoError
from hico_plugin.scenes.generate import generate_scene, scene_config
from hico_plugin.scenes.raycast import ConvexPolyhedron, Ground, Revolution, Sphere
from helpers_datasets import SMALL_DISTRICT

SMALL = dict(SMALL_DISTRICT, width=64, height=48, pixel_samples=1)


@pytest.fixture(scope="module")
def district(tmp_path_factory):
    path = generate_scene("district", tmp_path_factory.mktemp("scenes") / "district", **SMALL)
    config = scene_config("district", **SMALL)
    return path, config, config.setup("district")


def _centres(viewmats):
    return -np.einsum("cji,cj->ci", viewmats[:, :3, :3], viewmats[:, :3, 3])


def _check_kinds(config):
    kinds, viewmats = config.capture()
    kinds = np.array(kinds)
    centres, forward = _centres(viewmats), viewmats[:, 2, :3]  # the camera's z axis in world coords
    down = np.degrees(np.arcsin(-forward[:, 2]))  # pitch below the horizon
    heading = np.degrees(np.arctan2(forward[:, 1], forward[:, 0]))
    aerial = kinds != "street"
    np.testing.assert_allclose(centres[aerial, 2], config.altitude, rtol=0.05)
    assert (down[kinds == "nadir"] > 85).all()
    oblique = kinds == "oblique"
    assert (np.abs(down[oblique] - config.oblique_pitch_deg) < 8).all()
    off_cardinal = np.abs((heading[oblique] + 45) % 90 - 45)
    assert (off_cardinal < 10).all()
    # each waypoint's rig: a nadir view, then obliques looking four ways
    rig = np.round(heading[:5] / 90) % 4
    assert kinds[0] == "nadir" and sorted(rig[1:]) == [0, 1, 2, 3]
    street = kinds == "street"
    low, high = config.street_heights
    assert ((centres[street, 2] >= low) & (centres[street, 2] <= high)).all()
    assert (np.abs(down[street]) < 20).all()
    # street cameras stand within a metre or so of a street's centre line, in x or in y
    pitch = config.block_pitch
    to_line = np.abs((centres[street, :2] - pitch / 2) / pitch - np.round((centres[street, :2] - pitch / 2) / pitch))
    assert (to_line.min(1) * pitch < 1.5).all()
    return collections.Counter(kinds)


def test_views_are_nadir_oblique_and_street():
    small = _check_kinds(scene_config("district", **SMALL))
    assert small == {"oblique": 19, "nadir": 5, "street": 6}
    config = scene_config("district")
    assert config.num_views >= 1000
    default = _check_kinds(config)
    assert sum(default.values()) == config.num_views
    assert default["street"] == round(config.street_share * config.num_views)
    assert default["oblique"] == 4 * default["nadir"]
    drone_only = _check_kinds(scene_config("district", **SMALL, effects={"multi_distance": False}))
    assert drone_only == {"oblique": 24, "nadir": 6}


def _built_area(config):
    """Area (m^2) of the xy bounding box of everything standing on the ground."""
    hulls = np.concatenate([p.hull_points() for p in config.build_primitives() if not isinstance(p, Ground)])
    return float(np.prod(np.ptp(hulls[:, :2], axis=0)))


def test_district_covers_eight_city_blocks_at_least():
    ratio = _built_area(scene_config("district")) / _built_area(scene_config("city-block"))
    assert ratio >= 8, ratio


def test_every_view_sees_surface_and_the_split_holds_every_kind(district):
    path, config, scene = district
    depths = np.stack([np.load(path / "ground_truth" / "depth" / f"view_{i:04d}.npy") for i in range(30)])
    assert ((depths > 0).mean((1, 2)) > 0.3).all()  # every camera sees surface, not just sky
    meta = json.loads((path / "scene.json").read_text())
    assert meta["declared_effects"] == ["exposure", "sky", "multi_distance"]
    assert sorted(meta["enabled_effects"]) == ["multi_distance", "sky"]
    dataset = DataParserConfig(data=path).parse(announce=False)
    kinds = np.array(config.view_kinds())
    assert set(kinds[np.asarray(dataset.test_indices)]) == {"nadir", "oblique", "street"}
    assert set(kinds[np.asarray(dataset.train_indices)]) == {"nadir", "oblique", "street"}


def _camera_rays(scene, viewmat):
    u, v = np.meshgrid(np.arange(scene.width) + 0.5, np.arange(scene.height) + 0.5)
    rays_cam = np.stack([u, v, np.ones_like(u)], -1).reshape(-1, 3) @ np.linalg.inv(scene.K).T  # z = 1
    return _centres(viewmat[None])[0], rays_cam @ viewmat[:3, :3]  # world, unnormalised: t is depth


def test_depth_and_normals_match_every_primitive_brute_force(district):
    """Nearest hits over all primitives, without the caster's culling, and their analytic normals."""
    path, _, scene = district
    checked = 0
    for i in range(0, 30, 3):
        viewmat = scene.viewmats[i]
        depth = np.load(path / "ground_truth" / "depth" / f"view_{i:04d}.npy").ravel()
        normal = np.load(path / "ground_truth" / "normal" / f"view_{i:04d}.npy").reshape(-1, 3)
        origin, rays = _camera_rays(scene, viewmat)
        length = np.linalg.norm(rays, axis=1)
        dirs = rays / length[:, None]
        best, part, prim = np.full(len(dirs), np.inf), np.zeros(len(dirs), np.int64), np.full(len(dirs), -1)
        for index, solid in enumerate(scene.primitives):
            t, face = solid.intersect(np.broadcast_to(origin, dirs.shape), dirs, scene.caster.eps)
            closer = t < best
            best[closer], part[closer], prim[closer] = t[closer], face[closer], index
        hit = np.isfinite(best)
        np.testing.assert_array_equal(depth > 0, hit)
        np.testing.assert_allclose(depth[hit], (best / length)[hit], rtol=1e-5)
        expected = np.zeros_like(dirs)
        for index in np.unique(prim[hit]):
            rays_here = np.flatnonzero(prim == index)
            points = origin + dirs[rays_here] * best[rays_here, None]
            expected[rays_here] = scene.primitives[index].surface(points, part[rays_here])[0]
        expected = expected @ viewmat[:3, :3].T
        expected *= -np.sign((expected * (dirs @ viewmat[:3, :3].T)).sum(1, keepdims=True))  # facing the camera
        np.testing.assert_allclose(normal[hit], expected[hit], atol=1e-5)
        checked += hit.sum()
    assert checked > 10 * 64 * 48 * 0.3


def _boundary_distance(solid, points):
    """Signed distance-like value [n]: 0 on the solid's surface, < 0 inside, > 0 outside."""
    if isinstance(solid, ConvexPolyhedron):
        return (points @ solid.normals.T - solid.offsets).max(1)
    if isinstance(solid, Sphere):
        return np.linalg.norm(points - np.asarray(solid.center), axis=1) - solid.radius
    if isinstance(solid, Revolution):
        p = points - np.asarray(solid.base)
        k = (solid.r1 - solid.r0) / solid.height
        side = (np.hypot(p[:, 0], p[:, 1]) - (solid.r0 + k * p[:, 2])) / np.sqrt(1 + k * k)
        return np.maximum(side, np.maximum(-p[:, 2], p[:, 2] - solid.height))
    assert isinstance(solid, Ground)
    return np.where((np.abs(points[:, :2]) <= solid.half_extent).all(1), np.abs(points[:, 2] - solid.z), np.inf)


def test_surface_points_lie_on_the_visible_geometry(district):
    path, _, scene = district
    points = np.load(path / "ground_truth" / "surface_points.npy").astype(np.float64)
    assert len(points) > 1000
    distance = np.stack([_boundary_distance(solid, points) for solid in scene.primitives])  # [P, n]
    tolerance = 2e-7 * np.abs(points).max()  # float32 storage
    assert (np.abs(distance).min(0) < tolerance).all()  # on some solid's surface
    assert (distance > -tolerance).all()  # and inside none (it would be hidden)
    on_ground = np.abs(distance[0]) < tolerance
    assert on_ground.sum() > 500 and (~on_ground).sum() > 500  # both the streets and the buildings


def test_bad_district_parameters_are_refused_before_rendering(tmp_path):
    with pytest.raises(HicoError, match="blocks must be odd and >= 3, got 4"):
        generate_scene("district", tmp_path / "a", **{**SMALL, "blocks": 4})
    with pytest.raises(HicoError, match="altitude 60 m does not clear the tallest landmark"):
        generate_scene("district", tmp_path / "b", **{**SMALL, "altitude": 60.0})
    with pytest.raises(HicoError, match="street_heights must be"):
        generate_scene("district", tmp_path / "c", **{**SMALL, "street_heights": (5.0, 2.0)})
    assert not any(tmp_path.iterdir())
