"""The scene's vertical (data.transform.scene_up): exact for level cameras that pitch down at a scene
from one side, close under hand-held roll, defined when every photo faces one way or there is one."""

from __future__ import annotations

import math

import numpy as np
import torch

from hico_plugin.data.transform import SceneTransform, frame_differences, rotation_about_z, rotation_to_z, scene_heading, scene_up
from hico_plugin.scenes.orbits import look_at


def _arc(degrees: float, count: int = 12, height: float = 2.0) -> np.ndarray:
    """Level cameras on an arc of ``degrees`` around the origin at ``height``, all looking down at it."""
    angles = np.radians(np.linspace(0.0, degrees, count))
    eyes = np.stack([4 * np.cos(angles), 4 * np.sin(angles), np.full(count, height)], axis=-1)
    return look_at(eyes, np.zeros_like(eyes))


def _turn(viewmats: np.ndarray, rotation: np.ndarray) -> torch.Tensor:
    """The same cameras in a world turned by ``rotation`` (world->camera: R' = R @ rotation.T)."""
    out = viewmats.copy()
    out[:, :3, :3] = viewmats[:, :3, :3] @ rotation.T
    return torch.from_numpy(out)


def _angle_deg(a: torch.Tensor, b: np.ndarray) -> float:
    return math.degrees(math.acos(min(1.0, abs(float(a @ torch.from_numpy(b))))))


def test_level_cameras_on_one_side_give_the_exact_vertical_where_their_mean_up_leans():
    viewmats = _arc(90.0)  # a quarter circle pitched ~27 degrees down: the mean up leans toward the scene
    q, _ = np.linalg.qr(np.random.default_rng(0).normal(size=(3, 3)))
    rotation = q * np.sign(np.linalg.det(q))
    turned = _turn(viewmats, rotation)
    mean_up = -turned[:, 1, :3].mean(dim=0)
    assert _angle_deg(mean_up / mean_up.norm(), rotation @ [0.0, 0.0, 1.0]) > 10.0
    up = scene_up(turned)
    assert _angle_deg(up, rotation @ [0.0, 0.0, 1.0]) < 1e-6
    assert float(up @ torch.from_numpy(rotation @ [0.0, 0.0, 1.0])) > 0  # up, not down
    # the oriented scene is z-up
    oriented = SceneTransform.from_cameras(turned).viewmats_from_colmap(turned)
    assert _angle_deg(scene_up(oriented), np.array([0.0, 0.0, 1.0])) < 1e-6


def test_hand_held_roll_moves_the_vertical_by_less_than_the_roll():
    viewmats = _arc(360.0, count=40)
    rolls = np.radians(np.random.default_rng(1).normal(0.0, 3.0, size=len(viewmats)))  # 3 degrees of roll
    rolled = viewmats.copy()
    for i, roll in enumerate(rolls):  # turn each camera about its own optical axis
        c, s = math.cos(roll), math.sin(roll)
        rolled[i, :3, :] = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]) @ viewmats[i, :3, :]
    assert _angle_deg(scene_up(torch.from_numpy(rolled)), np.array([0.0, 0.0, 1.0])) < 1.0


def test_one_heading_or_one_camera_falls_back_to_the_mean_up_made_level():
    forward = _arc(0.0, count=5)  # every camera faces the same way: the right axes fix only one direction
    up = scene_up(torch.from_numpy(forward))
    right = torch.from_numpy(forward[0, 0, :3])
    assert abs(float(up @ right)) < 1e-9 and float(up[2]) > 0.8
    single = scene_up(torch.from_numpy(forward[:1]))
    assert torch.allclose(single, up, atol=1e-9) and torch.isfinite(single).all()


def _walls(heading_deg: float, seed: int = 0) -> torch.Tensor:
    """Noisy points on the walls of a block of houses whose streets run at ``heading_deg`` about +z, a
    fifth of the houses turned off the grid by up to 20 degrees, and on the ground."""
    rng = np.random.default_rng(seed)
    points = []
    for i in range(5):
        for j in range(5):
            turn = math.radians(heading_deg + (rng.uniform(-20, 20) if rng.uniform() < 0.2 else 0.0))
            c, s = math.cos(turn), math.sin(turn)
            for side in range(4):
                t = rng.uniform(-1, 1, 60)
                z = rng.uniform(0, 2, 60)
                x, y = (t, np.full(60, 1.0 if side < 2 else -1.0)) if side % 2 == 0 else (np.full(60, 1.0 if side < 2 else -1.0), t)
                local = np.stack([x, y], axis=1)
                world = local @ np.array([[c, s], [-s, c]]) + np.array([5.0 * i, 5.0 * j]) @ np.array([[math.cos(math.radians(heading_deg)), math.sin(math.radians(heading_deg))], [-math.sin(math.radians(heading_deg)), math.cos(math.radians(heading_deg))]])
                points.append(np.concatenate([world, z[:, None]], axis=1))
    ground = np.concatenate([rng.uniform(-3, 23, (1500, 2)), np.zeros((1500, 1))], axis=1)
    cloud = np.concatenate(points + [ground]) + rng.normal(0.0, 0.01, (len(ground) + 60 * 100, 3))
    return torch.from_numpy(cloud)


def test_heading_turns_the_walls_onto_the_axes_whatever_the_source_heading():
    for heading in (0.0, 17.0, 30.0, -41.0):
        found = math.degrees(scene_heading(_walls(heading)))
        assert abs((found - heading + 45.0) % 90.0 - 45.0) < 0.5, (heading, found)
    # no walls, or walls at every heading: no turn
    blob = torch.from_numpy(np.random.default_rng(2).normal(size=(3000, 3)))
    assert scene_heading(blob) == 0.0
    ring = np.linspace(0, 2 * math.pi, 4000, endpoint=False)
    tower = torch.from_numpy(np.stack([np.cos(ring), np.sin(ring), np.random.default_rng(3).uniform(0, 5, 4000)], axis=1))
    assert scene_heading(tower) == 0.0


def test_a_recorded_frame_matches_one_with_another_heading_but_not_other_cameras():
    """The heading comes from the seed points, which a fresh triangulation reproduces only within its
    random sampling; the centre, scale and up axis come from the cameras and must agree."""
    viewmats = torch.from_numpy(_arc(120.0))
    points = _walls(17.0, seed=0)
    recorded = SceneTransform.from_cameras(viewmats, points=points).to_dict()
    today = SceneTransform.from_cameras(viewmats, points=_walls(17.0, seed=1)).to_dict()  # triangulated again
    assert today["rotation"] != recorded["rotation"]  # the points moved the heading
    assert frame_differences(recorded, today) == []
    turned = SceneTransform.from_dict(recorded)
    turned.rotation = rotation_about_z(0.3) @ turned.rotation
    assert frame_differences(recorded, turned.to_dict()) == []
    tilted = SceneTransform.from_dict(recorded)
    tilted.rotation = rotation_to_z(torch.tensor([0.01, 0.0, 1.0], dtype=torch.float64) / math.hypot(0.01, 1.0)) @ tilted.rotation
    assert frame_differences(recorded, tilted.to_dict()) == ["rotation"]
    moved = SceneTransform.from_cameras(viewmats[1:], points=points).to_dict()  # other cameras
    assert {"centre", "scale"} <= set(frame_differences(recorded, moved))
