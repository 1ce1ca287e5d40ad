"""COLMAP data parser: camera models, formats, downscaling, normalisation, caches, ground truth."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from hico_plugin.data import DataParserConfig, SceneTransform
from hico_plugin.data.cache import ByteLRUCache
from hico_plugin.scenes.ring_dataset import HEIGHT, WIDTH, write_ring_dataset

def test_pinhole_binary_model_loads_normalised(tmp_path):
    written = write_ring_dataset(tmp_path, num_images=10)
    dataset = DataParserConfig(data=tmp_path).setup()

    assert dataset.image_names == written["names"]
    assert dataset.train_indices.dtype == torch.long
    assert dataset.test_indices.tolist() == [0, 8]
    assert dataset.train_indices.tolist() == [1, 2, 3, 4, 5, 6, 7, 9]
    assert dataset.points.dtype == torch.float32 and dataset.points.shape == (40, 3)
    assert torch.equal(dataset.point_colors, torch.from_numpy(written["colors"]))
    # normalised frame: camera centres around the origin, the farthest at distance 1
    centres = dataset.cameras.centers
    assert centres.mean(0).abs().max() < 1e-5
    assert centres.norm(dim=-1).max() == pytest.approx(1.0, abs=1e-5)
    # the recorded transform maps points and viewmats back to COLMAP's frame
    back = dataset.transform.points_to_colmap(dataset.points.double())
    assert np.allclose(back.numpy(), written["points"], atol=1e-5)
    viewmats = dataset.transform.viewmats_to_colmap(dataset.cameras.viewmats.double())
    assert np.allclose(viewmats[:, :3].numpy(), written["poses"], atol=1e-5)
    # the same point projects to the same pixel in both frames
    K = dataset.cameras.Ks[3].double()

    def project(viewmat, point):
        cam = viewmat[:3, :3] @ point + viewmat[:3, 3]
        return (K @ cam / cam[2])[:2]

    colmap_pixel = project(
        torch.from_numpy(np.vstack([written["poses"][3], [0, 0, 0, 1]])), torch.from_numpy(written["points"][0])
    )
    normalised_pixel = project(dataset.cameras.viewmats[3].double(), dataset.points[0].double())
    assert torch.allclose(colmap_pixel, normalised_pixel, atol=1e-3)
    # intrinsics and images at full resolution
    assert torch.allclose(dataset.cameras.Ks[0], torch.tensor([[32.0, 0, 20], [0, 32, 15], [0, 0, 1]]))
    image = dataset.image(2)
    assert image.dtype == torch.uint8 and image.shape == (HEIGHT, WIDTH, 3)
    assert np.array_equal(image.numpy(), written["images"][written["names"][2]])
    assert dataset.mask(0) is None and dataset.gt_depth(0) is None and dataset.gt_surface_points is None
    assert dataset.metadata == {}


def test_legacy_text_model_simple_pinhole(tmp_path):
    write_ring_dataset(tmp_path, model="SIMPLE_PINHOLE", text=True, num_images=4)
    for extra in ("rigs.txt", "frames.txt"):  # a COLMAP < 3.12 model has neither
        (tmp_path / "sparse" / "0" / extra).unlink()
    dataset = DataParserConfig(data=tmp_path, test_every=0, normalize=False).setup()
    assert len(dataset) == 4 and len(dataset.test_indices) == 0
    assert torch.allclose(dataset.cameras.Ks[0], torch.tensor([[32.0, 0, 20], [0, 32, 15], [0, 0, 1]]))
    assert dataset.transform.scale == 1.0


def test_explicit_test_names(tmp_path):
    written = write_ring_dataset(tmp_path)
    dataset = DataParserConfig(data=tmp_path, test_names=(written["names"][4], written["names"][1])).setup()
    assert dataset.test_indices.tolist() == [1, 4]
    assert dataset.train_indices.tolist() == [0, 2, 3, 5]


def test_downscale_resizes_on_load_or_reads_images_n(tmp_path):
    write_ring_dataset(tmp_path)
    full = DataParserConfig(data=tmp_path).setup()
    half = DataParserConfig(data=tmp_path, downscale=2).setup()
    assert half.image(1).shape == (HEIGHT // 2, WIDTH // 2, 3)
    assert torch.allclose(half.cameras.Ks[:, :2], full.cameras.Ks[:, :2] / 2)
    assert half.cameras.widths.tolist() == [WIDTH // 2] * 6

    (tmp_path / "images_2").mkdir()
    for name in full.image_names:
        cv2.imwrite(str(tmp_path / "images_2" / name), np.full((HEIGHT // 2, WIDTH // 2, 3), 7, np.uint8))
    from_folder = DataParserConfig(data=tmp_path, downscale=2).setup()
    assert (from_folder.image(0) == 7).all()


def test_image_stored_at_exact_downscale_is_accepted(tmp_path):
    written = write_ring_dataset(tmp_path)
    name = written["names"][0]
    cv2.imwrite(str(tmp_path / "images" / name), np.full((HEIGHT // 2, WIDTH // 2, 3), 50, np.uint8))
    dataset = DataParserConfig(data=tmp_path).setup()
    assert dataset.image(0).shape == (HEIGHT, WIDTH, 3) and (dataset.image(0) == 50).all()


def test_masks_ground_truth_and_metadata(tmp_path):
    written = write_ring_dataset(tmp_path)
    name = written["names"][1]
    (tmp_path / "masks").mkdir()
    mask = np.zeros((HEIGHT, WIDTH), np.uint8)
    mask[:, : WIDTH // 2] = 255
    cv2.imwrite(str(tmp_path / "masks" / f"{name}.png"), mask)
    depth = np.random.default_rng(1).uniform(1, 5, (HEIGHT, WIDTH)).astype(np.float32)
    normal = np.zeros((HEIGHT, WIDTH, 3), np.float32)
    normal[..., 2] = -1
    surface = np.random.default_rng(2).normal(size=(100, 3)).astype(np.float32)
    for kind, array in (("depth", depth), ("normal", normal)):
        (tmp_path / "ground_truth" / kind).mkdir(parents=True)
        np.save(tmp_path / "ground_truth" / kind / f"{Path(name).stem}.npy", array)
    np.save(tmp_path / "ground_truth" / "surface_points.npy", surface)
    (tmp_path / "scene.json").write_text('{"name": "tiny", "effects": ["exposure"]}')

    dataset = DataParserConfig(data=tmp_path).setup()
    loaded_mask = dataset.mask(1)
    assert loaded_mask.dtype == torch.bool and loaded_mask.shape == (HEIGHT, WIDTH, 1)
    assert loaded_mask[:, : WIDTH // 2].all() and not loaded_mask[:, WIDTH // 2 :].any()
    assert dataset.mask(0) is None
    assert dataset.gt_depth(1).shape == (HEIGHT, WIDTH, 1)
    assert torch.allclose(dataset.gt_depth(1)[..., 0], torch.from_numpy(depth) * dataset.transform.scale)
    assert torch.equal(dataset.gt_normal(1), torch.from_numpy(normal))
    assert dataset.gt_depth(0) is None
    assert torch.allclose(
        dataset.gt_surface_points, dataset.transform.points_from_colmap(torch.from_numpy(surface))
    )
    assert dataset.metadata["effects"] == ["exposure"]

    half = DataParserConfig(data=tmp_path, downscale=2).setup()
    assert half.gt_depth(1).shape == (HEIGHT // 2, WIDTH // 2, 1)
    assert set(np.unique(half.gt_depth(1).numpy())) <= set(np.unique(depth * np.float32(half.transform.scale)))
    assert half.mask(1).shape == (HEIGHT // 2, WIDTH // 2, 1)


# --------------------------------------------------------------------------- undistortion
DISTORTED = {
    "SIMPLE_RADIAL": ([60.0, 40.0, 30.0, -0.15], [-0.15, 0, 0, 0]),
    "RADIAL": ([60.0, 41.0, 29.0, -0.12, 0.03], [-0.12, 0.03, 0, 0]),
    "OPENCV": ([62.0, 58.0, 40.5, 29.5, -0.1, 0.02, 0.004, -0.003], [-0.1, 0.02, 0.004, -0.003]),
}


def pattern(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """A smooth colour image of normalised image coordinates: [..., 3] float in [0, 255]."""
    return np.stack(
        [127.5 + 100 * np.sin(3 * x) * np.cos(2 * y), 127.5 + 100 * np.cos(4 * y), 127.5 + 90 * np.sin(2 * x + y)],
        -1,
    )


@pytest.mark.parametrize("model", sorted(DISTORTED))
def test_distorted_models_are_undistorted_to_pinhole(tmp_path, model, monkeypatch):
    user_cache = tmp_path / "user_cache"
    monkeypatch.setenv("HICO_CACHE_DIR", str(user_cache))
    params, opencv_coefficients = DISTORTED[model]
    size = (80, 60)
    written = write_ring_dataset(tmp_path, model=model, params=params, size=size, num_images=2, write_images=False)
    # Render each distorted image independently of the parser: OpenCV's undistortPoints gives the
    # normalised ray of every distorted pixel (OpenCV's pixel centres are integers, COLMAP's +0.5).
    camera = written["camera"]
    fx, fy = (params[0], params[0]) if model != "OPENCV" else params[:2]
    cx, cy = params[1:3] if model != "OPENCV" else params[2:4]
    K_opencv = np.array([[fx, 0, cx - 0.5], [0, fy, cy - 0.5], [0, 0, 1]])
    u, v = np.meshgrid(np.arange(size[0], dtype=np.float64), np.arange(size[1], dtype=np.float64))
    pixels = np.stack([u.ravel(), v.ravel()], -1)[:, None]
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)
    rays = cv2.undistortPoints(
        pixels, K_opencv, np.array(opencv_coefficients), None, np.eye(3), np.eye(3), criteria
    )[:, 0]
    distorted = pattern(rays[:, 0], rays[:, 1]).reshape(size[1], size[0], 3).round().astype(np.uint8)
    for name in written["names"]:
        cv2.imwrite(str(tmp_path / "images" / name), distorted[..., ::-1])

    dataset = DataParserConfig(data=tmp_path, test_every=0).setup()
    assert camera.model.name == model
    image = dataset.image(0).numpy().astype(np.float64)
    K = dataset.cameras.Ks[0].double().numpy()
    height, width = image.shape[:2]
    assert (width, height) == (int(dataset.cameras.widths[0]), int(dataset.cameras.heights[0]))
    assert K[0, 1] == 0 and K[2].tolist() == [0, 0, 1]
    xs = (np.arange(width) + 0.5 - K[0, 2]) / K[0, 0]
    ys = (np.arange(height) + 0.5 - K[1, 2]) / K[1, 1]
    expected = pattern(*np.meshgrid(xs, ys))
    inner = (slice(3, -3), slice(3, -3))  # away from the border, where the distorted image ends
    error = np.abs(image[inner] - expected[inner])
    assert error.mean() < 1.5 and np.percentile(error, 99) < 6, (error.mean(), error.max())

    # undistorted once: the cache on disk serves later loads, even if the original changes
    assert not (tmp_path / ".hico_cache").exists()
    cached = list(user_cache.rglob(f"{written['names'][0]}.png"))
    assert len(cached) == 1
    cv2.imwrite(str(tmp_path / "images" / written["names"][0]), np.zeros_like(distorted))
    again = DataParserConfig(data=tmp_path, test_every=0).setup()
    assert np.array_equal(again.image(0).numpy(), image.astype(np.uint8))


def test_opencv_undistortion_matches_cv2_undistort_points(tmp_path):
    """A single bright pixel lands where cv2.undistortPoints sends it."""
    params, coefficients = DISTORTED["OPENCV"]
    written = write_ring_dataset(
        tmp_path, model="OPENCV", params=params, size=(80, 60), num_images=2, write_images=False
    )
    spot = np.zeros((60, 80, 3), np.uint8)
    spot[12:15, 60:63] = 255  # centre (61, 13) in OpenCV pixels
    for name in written["names"]:
        cv2.imwrite(str(tmp_path / "images" / name), spot)
    dataset = DataParserConfig(data=tmp_path, test_every=0, cache_dir=tmp_path / "elsewhere").setup()
    image = dataset.image(1).numpy()[..., 0].astype(np.float64)
    assert (tmp_path / "elsewhere").is_dir()
    K = dataset.cameras.Ks[1].double().numpy()
    K_opencv = np.array([[params[0], 0, params[2] - 0.5], [0, params[1], params[3] - 0.5], [0, 0, 1]])
    P = K.copy()
    P[:2, 2] -= 0.5
    expected = cv2.undistortPoints(np.array([[[61.0, 13.0]]]), K_opencv, np.array(coefficients), P=P)[0, 0]
    ys, xs = np.mgrid[: image.shape[0], : image.shape[1]]
    centroid = np.array([(xs * image).sum(), (ys * image).sum()]) / image.sum()
    assert np.abs(centroid - expected).max() < 0.35


# --------------------------------------------------------------------------- extents and caches
def test_camera_distance_range_matches_slow_reference(tmp_path):
    write_ring_dataset(tmp_path, num_images=9, num_points=300)
    dataset = DataParserConfig(data=tmp_path).setup()
    centres = dataset.cameras.centers.double().numpy()[dataset.train_indices.numpy()]
    points = dataset.points.double().numpy()
    per_camera = []
    for centre in centres:
        distances = np.linalg.norm(points - centre, axis=1)
        per_camera += [np.quantile(distances, 0.001), np.quantile(distances, 0.999)]
    dist_min, dist_max = dataset.camera_distance_range()
    assert dist_min == pytest.approx(np.quantile(per_camera, 0.001), rel=1e-6)
    assert dist_max == pytest.approx(np.quantile(per_camera, 0.999), rel=1e-6)
    radius = np.linalg.norm(centres - centres.mean(0), axis=1).max()
    assert dataset.cameras_extent() == pytest.approx(1.1 * radius, rel=1e-5)


def test_image_cache_is_bounded_by_bytes(tmp_path):
    write_ring_dataset(tmp_path)
    one_image = HEIGHT * WIDTH * 3
    dataset = DataParserConfig(data=tmp_path, cache_mb=1).setup()
    dataset.cache.max_bytes = 2 * one_image  # room for two decoded images
    for i in range(len(dataset)):
        dataset.image(i)
    assert len(dataset.cache) == 2 and dataset.cache.num_bytes == 2 * one_image
    assert ("image", 5) in dataset.cache and ("image", 0) not in dataset.cache


def test_byte_lru_cache_evicts_least_recently_used():
    cache = ByteLRUCache(max_bytes=300)
    make = lambda: np.zeros(100, np.uint8)
    for key in "abc":
        cache.get(key, make)
    cache.get("a", lambda: pytest.fail("'a' should be cached"))
    cache.get("d", make)
    assert "b" not in cache and all(k in cache for k in "acd")
    assert cache.get("big", lambda: np.zeros(1000, np.uint8)).nbytes == 1000 and "big" not in cache


def test_scene_transform_round_trip_and_dict():
    q, _ = torch.linalg.qr(torch.randn(3, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(1)))
    rotation = q * torch.sign(torch.linalg.det(q))
    transform = SceneTransform(torch.tensor([1.0, -2.0, 3.0], dtype=torch.float64), 0.25, rotation)
    points = torch.randn(5, 3, dtype=torch.float64)
    assert torch.allclose(transform.points_to_colmap(transform.points_from_colmap(points)), points)
    viewmat = torch.eye(4, dtype=torch.float64)
    viewmat[:3, :3] = torch.linalg.qr(torch.randn(3, 3, dtype=torch.float64))[0]
    viewmat[:3, 3] = torch.tensor([0.5, 0.1, 2.0])
    normalised = transform.viewmats_from_colmap(viewmat)
    assert torch.allclose(transform.viewmats_to_colmap(normalised), viewmat)
    # a point seen by the camera in either frame: same camera-space direction, depth times the scale
    camera_colmap = viewmat[:3, :3] @ points.T + viewmat[:3, 3:]
    camera_normalised = normalised[:3, :3] @ transform.points_from_colmap(points).T + normalised[:3, 3:]
    assert torch.allclose(camera_normalised, camera_colmap * transform.scale)
    again = SceneTransform.from_dict(transform.to_dict())
    assert torch.equal(again.centre, transform.centre) and again.scale == transform.scale
    assert torch.equal(again.rotation, transform.rotation)
    assert torch.equal(SceneTransform.from_dict({"centre": [0, 0, 0], "scale": 2.0}).rotation, torch.eye(3, dtype=torch.float64))


def test_builtin_tiny_scene_ground_truth_agrees_with_normalised_cameras(tmp_path):
    """The scene generator's output goes through this parser; its exact depth, normals and surface
    points land in the same normalised frame as the cameras."""
    from hico_plugin.scenes.generate import generate_scene

    root = generate_scene("tiny", tmp_path / "tiny")
    dataset = DataParserConfig(data=str(root)).setup()  # a plain string path works too
    assert dataset.metadata["scene"] == "tiny" and len(dataset.test_indices) > 0
    surface = dataset.gt_surface_points
    for i in (0, len(dataset) - 1):
        camera, depth = dataset.cameras[i], dataset.gt_depth(i)[..., 0]
        in_camera = surface @ camera.viewmat[:3, :3].T + camera.viewmat[:3, 3]
        pixels = in_camera @ camera.K.T
        pixels = pixels[:, :2] / pixels[:, 2:]
        inside = (
            (in_camera[:, 2] > 0)
            & (pixels >= 0).all(1)
            & (pixels[:, 0] < camera.width)
            & (pixels[:, 1] < camera.height)
        )
        z = in_camera[inside, 2]
        sampled = depth[pixels[inside, 1].long(), pixels[inside, 0].long()]
        visible = (sampled > 0) & ((z - sampled).abs() < 0.05 * sampled)
        assert visible.float().mean() > 0.5
        assert ((z - sampled).abs() / sampled)[visible].median() < 0.02
        normals = dataset.gt_normal(i)[depth > 0]
        assert torch.allclose(normals.norm(dim=-1), torch.ones(len(normals)), atol=1e-4)


def test_undistorted_images_are_cached_in_the_user_cache_not_the_dataset(tmp_path, monkeypatch):
    params, _ = DISTORTED["SIMPLE_RADIAL"]
    root = tmp_path / "dataset"
    write_ring_dataset(root, model="SIMPLE_RADIAL", params=params, size=(80, 60), num_images=2)
    monkeypatch.setenv("HICO_CACHE_DIR", str(tmp_path / "user_cache"))
    dataset = DataParserConfig(data=root, test_every=0).setup()
    dataset.image(0)
    assert not (root / ".hico_cache").exists()
    assert len(list((tmp_path / "user_cache").rglob("view_000.png.png"))) == 1


_LOAD_WITHOUT_PYCOLMAP = """
import sys
from pathlib import Path

import numpy as np

import hico_plugin.cli.train  # noqa: F401 -- the trainer's imports
from hico_plugin.data import DataParserConfig
from hico_plugin.data.formats.transforms import TransformsFormat
from hico_plugin.data.triangulate import _cache_key
from hico_plugin.storage import cache_dir

assert "pycolmap" not in sys.modules, "imported with the trainer"
pinhole, distorted, transforms = (Path(arg) for arg in sys.argv[1:])
for root in (pinhole, distorted):
    dataset = DataParserConfig(data=root, test_every=0).setup(announce=False)
    dataset.verify_images()
    dataset.tracks.observations()
# transforms.json whose triangulated seed points are cached (as a second run finds them)
record = TransformsFormat(triangulate=False).read(transforms)
long_side = max(max(camera.width, camera.height) for camera in record.cameras.values())  # loaded at full size
key = _cache_key(transforms, record.names, record.camera_ids, record.cameras, record.viewmats, long_side)
cache_dir("triangulation").mkdir(parents=True)
np.savez(cache_dir("triangulation") / f"{key}.npz", points=np.random.default_rng(0).normal(size=(200, 3)),
         colors=np.zeros((200, 3), np.uint8))
dataset = DataParserConfig(data=transforms, test_every=0).setup(announce=False)
assert "triangulated 200" in " ".join(dataset.notes), dataset.notes
dataset.verify_images()
assert "pycolmap" not in sys.modules, "imported while loading"
"""


def test_loading_pinhole_distorted_and_cached_transforms_never_imports_pycolmap(tmp_path):
    """pycolmap costs a training run 56 MiB: the trainer loads a pinhole COLMAP model, a distorted one
    (text) and a transforms.json with distortion and cached seed points without it."""
    import json
    import os
    import shutil
    import subprocess
    import sys

    params, _ = DISTORTED["OPENCV"]
    write_ring_dataset(tmp_path / "pinhole")
    written = write_ring_dataset(tmp_path / "distorted", model="OPENCV", params=params, size=(80, 60), text=True)
    shutil.copytree(tmp_path / "distorted" / "images", tmp_path / "transforms" / "images")
    frames = []
    for name, pose in zip(written["names"], written["poses"]):
        c2w = np.linalg.inv(np.concatenate([pose, [[0, 0, 0, 1]]]))
        c2w[:, 1:3] *= -1  # OpenCV -> OpenGL camera axes
        frames.append({"file_path": f"images/{name}", "transform_matrix": c2w.tolist()})
    (tmp_path / "transforms" / "transforms.json").write_text(json.dumps(
        {"fl_x": params[0], "fl_y": params[1], "cx": params[2], "cy": params[3], "w": 80, "h": 60,
         **dict(zip(("k1", "k2", "p1", "p2"), params[4:])), "frames": frames}))
    env = {**os.environ, "HICO_CACHE_DIR": str(tmp_path / "cache")}
    result = subprocess.run([sys.executable, "-c", _LOAD_WITHOUT_PYCOLMAP, *(str(tmp_path / name) for name in (
        "pinhole", "distorted", "transforms"))], capture_output=True, text=True, env=env)
    assert result.returncode == 0, result.stderr[-3000:]
