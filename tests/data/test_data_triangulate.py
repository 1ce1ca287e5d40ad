"""Seed points triangulated from known poses: a transforms.json twin of a built-in scene without a
point cloud loads with points on the scene's ground-truth surface, cached outside the dataset."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pycolmap
import pytest
from scipy.spatial import cKDTree

from hico_plugin.data import DataParserConfig
from hico_plugin.data.formats.transforms import TransformsFormat
from hico_plugin.data.triangulate import MIN_POINTS
from hico_plugin.scenes.generate import generate_scene

# city-block, not tiny: tiny's repeating checkers give SIFT matches that slide along epipolar lines
# (see hico-process's test); 12 views at 320x240 triangulate in a few seconds.
SCENE = dict(width=320, height=240, num_views=12)
SPACING = 0.4  # city-block's surface_spacing (metres) between ground-truth surface samples


@pytest.fixture(scope="module")
def twin(tmp_path_factory):
    """(scene, transforms.json twin without ply_file_path)."""
    root = tmp_path_factory.mktemp("triangulate")
    scene = generate_scene("city-block", root / "scene", **SCENE)
    model = pycolmap.Reconstruction(str(scene / "sparse" / "0"))
    camera = next(iter(model.cameras.values()))
    fx, fy, cx, cy = camera.params
    out = root / "twin"
    shutil.copytree(scene / "images", out / "images")
    frames = []
    for image in model.images.values():
        c2w = np.eye(4)
        c2w[:3] = image.cam_from_world().inverse().matrix()
        c2w[:, 1:3] *= -1  # OpenCV -> OpenGL camera axes
        frames.append({"file_path": f"images/{image.name}", "transform_matrix": c2w.tolist()})
    meta = {"fl_x": fx, "fl_y": fy, "cx": cx, "cy": cy, "w": camera.width, "h": camera.height, "frames": frames}
    (out / "transforms.json").write_text(json.dumps(meta))
    return scene, out


def _surface_distances(scene, points: np.ndarray) -> np.ndarray:
    surface = np.load(scene / "ground_truth" / "surface_points.npy")
    return cKDTree(surface).query(points)[0]


def _assert_triangulated_onto_the_surface(scene, data, capsys) -> None:
    """The dataset at ``data`` loads with triangulated seed points (no random fallback) on ``scene``'s
    ground-truth surface."""
    dataset = DataParserConfig(data=data, normalize=False).setup()
    assert "random" not in capsys.readouterr().err
    distance = _surface_distances(scene, dataset.points.double().numpy())
    assert len(distance) >= MIN_POINTS
    assert np.median(distance) < SPACING and np.mean(distance < 2 * SPACING) > 0.75


def test_points_triangulated_from_known_poses_lie_on_the_surface(twin, tmp_path, monkeypatch, capsys):
    scene, out = twin
    monkeypatch.setenv("HICO_CACHE_DIR", str(tmp_path / "cache"))
    before = sorted(p.name for p in out.rglob("*"))
    dataset = DataParserConfig(data=out, normalize=False).setup()
    err = capsys.readouterr().err
    points = dataset.points.double().numpy()
    distance = _surface_distances(scene, points)
    with capsys.disabled():
        print(f"triangulated {len(points)} points; distance to the surface: median {np.median(distance):.3f} m, "
              f"80th percentile {np.percentile(distance, 80):.3f} m (surface samples every {SPACING} m)")
    assert "triangulated" in err and "random" not in err
    assert len(points) >= MIN_POINTS
    assert np.median(distance) < SPACING and np.mean(distance < 2 * SPACING) > 0.75
    # random seeding (the fallback) is far off the surface: the bounds above can fail
    fallback = DataParserConfig(data=out, normalize=False, format=TransformsFormat(triangulate=False)).setup()
    assert np.median(_surface_distances(scene, fallback.points.double().numpy())) > 3 * SPACING
    # cached in the user cache directory, nothing written into the dataset; the second load reuses it
    assert sorted(p.name for p in out.rglob("*")) == before
    cached = list((tmp_path / "cache" / "triangulation").glob("*.npz"))
    assert len(cached) == 1
    again = DataParserConfig(data=out, normalize=False).setup()
    assert "triangulating" not in capsys.readouterr().err
    assert np.array_equal(again.points.numpy(), dataset.points.numpy())


def test_a_fresh_triangulation_gives_the_same_points_every_run(twin, tmp_path, monkeypatch):
    """Nothing in the result depends on which thread finished first: the same photos and poses give the
    same points, bit for bit, with nothing cached."""
    _, out = twin
    runs = []
    for run in range(3):
        monkeypatch.setenv("HICO_CACHE_DIR", str(tmp_path / f"cache{run}"))
        runs.append(DataParserConfig(data=out, normalize=False).setup(announce=False).points.numpy())
    assert len(runs[0]) >= MIN_POINTS
    assert all(np.array_equal(points, runs[0]) for points in runs[1:])


def test_photos_stored_at_a_downscale_of_their_camera_triangulate_onto_the_surface(twin, tmp_path, monkeypatch,
                                                                                  capsys):
    """transforms.json may state the camera at twice the size of the files (an exact downscale, as
    ``images_2`` folders hold): keypoints are in the file's pixels, so the camera is met at that size."""
    scene, out = twin
    monkeypatch.setenv("HICO_CACHE_DIR", str(tmp_path / "cache"))
    meta = json.loads((out / "transforms.json").read_text())
    for key in ("fl_x", "fl_y", "cx", "cy", "w", "h"):
        meta[key] *= 2
    twice = tmp_path / "twice"
    shutil.copytree(out / "images", twice / "images")
    (twice / "transforms.json").write_text(json.dumps(meta))
    _assert_triangulated_onto_the_surface(scene, twice, capsys)


def test_meganerf_layout_is_triangulated_in_the_source_frame(twin, tmp_path, monkeypatch, capsys):
    """Mega-NeRF carries no points: they are triangulated from its (DRB, shifted, scaled) poses and
    come out in the source frame, on the scene's surface."""
    from helpers_datasets import write_meganerf

    scene, _ = twin
    monkeypatch.setenv("HICO_CACHE_DIR", str(tmp_path / "cache"))
    write_meganerf(scene, tmp_path / "mega")
    _assert_triangulated_onto_the_surface(scene, tmp_path / "mega", capsys)


def test_cache_key_is_the_one_pycolmap_cameras_gave(tmp_path):
    """A user's triangulation cache keeps hitting: the key from plain cameras is the key the loader made
    when cameras were pycolmap's (model by name, parameters as pycolmap stores them)."""
    import hashlib
    import json

    from hico_plugin.data import triangulate
    from hico_plugin.data.camera_model import Camera

    (tmp_path / "a.jpg").write_bytes(b"jpeg")
    camera = Camera(camera_id=1, model="OPENCV", width=1080, height=1920,
                    params=[1375.52, 1374.49, 554.558, 965.268, 0.0578421, -0.0805099, -0.000980296, 0.00015575])
    viewmats = np.eye(4)[None] + 1e-3
    theirs = pycolmap.Camera(model="OPENCV", width=1080, height=1920, params=list(camera.params))
    stat = (tmp_path / "a.jpg").stat()
    source = json.dumps([
        triangulate.CACHE_VERSION, triangulate.MAX_FEATURES, triangulate.MAX_IMAGE_SIZE, triangulate.POSE_NEIGHBOURS,
        triangulate.POSE_MAX_ANGLE, str(tmp_path.resolve()), [["a.jpg", stat.st_size, stat.st_mtime_ns]], [1],
        [[1, theirs.model.name, theirs.width, theirs.height, [round(float(v), 9) for v in theirs.params]]],
        np.round(viewmats, 9).tolist(),
    ])
    assert triangulate._cache_key(tmp_path, ["a.jpg"], [1], {1: camera}, viewmats, triangulate.MAX_IMAGE_SIZE) == (
        hashlib.sha1(source.encode()).hexdigest()[:16])


def test_features_are_extracted_at_the_size_the_photos_are_trained_at(twin, tmp_path, monkeypatch):
    """SIFT reads the photos at the size --downscale / --max-long-side loads them (finer features would
    not seed that training better, and cost time with the pixels), never above MAX_IMAGE_SIZE."""
    from hico_plugin.data import triangulate

    _, out = twin
    monkeypatch.setenv("HICO_CACHE_DIR", str(tmp_path / "cache"))
    sizes = []

    def record(*args):
        sizes.append(args[-2])  # (..., work, long_side, num_threads)
        return np.random.default_rng(0).normal(size=(MIN_POINTS, 3)), np.zeros((MIN_POINTS, 3), np.uint8)

    monkeypatch.setattr(triangulate, "_triangulate", record)
    DataParserConfig(data=out, normalize=False, max_long_side=200).setup(announce=False)  # 320x240 -> 1/2
    DataParserConfig(data=out, normalize=False, downscale=4).setup(announce=False)
    monkeypatch.setattr(triangulate, "MAX_IMAGE_SIZE", 100)
    DataParserConfig(data=out, normalize=False, downscale=1).setup(announce=False)
    assert sizes == [160, 80, 100]


def _look(centre: np.ndarray, yaw_degrees: float) -> np.ndarray:
    """World->camera viewmat (OpenCV axes) of a level camera at ``centre`` looking along +x turned by yaw."""
    yaw = np.radians(yaw_degrees)
    forward = np.array([np.cos(yaw), np.sin(yaw), 0.0])
    down = np.array([0.0, 0.0, -1.0])
    rotation = np.stack([np.cross(down, forward), down, forward])  # rows: camera x, y, z in the world
    viewmat = np.eye(4)
    viewmat[:3, :3], viewmat[:3, 3] = rotation, -rotation @ centre
    return viewmat


def test_pose_pairs_match_only_cameras_near_and_looking_the_same_way():
    from hico_plugin.data.triangulate import pose_pairs

    # a camera turning in place every 30 degrees: equal centres, so only the axes choose
    turning = np.stack([_look(np.zeros(3), 30 * k) for k in range(12)])
    assert pose_pairs(turning, neighbours=5, max_angle=45) == sorted(
        (min(k, (k + 1) % 12), max(k, (k + 1) % 12)) for k in range(12))
    # a line of cameras all looking one way: each with its two nearest along the line
    line = np.stack([_look(np.array([0.0, float(k), 0.0]), 0) for k in range(8)])
    assert pose_pairs(line, neighbours=2) == sorted({(min(i, j), max(i, j)) for i in range(8)
                                                     for j in (i - 1, i + 1) if 0 <= j < 8} | {(0, 2), (5, 7)})
    # fewer cameras than neighbours: every pair within the angle, none twice
    assert pose_pairs(line[:4], neighbours=20) == [(i, j) for i in range(4) for j in range(i + 1, 4)]


def test_photos_named_with_spaces_are_paired_by_their_centres(twin, tmp_path, monkeypatch, capsys):
    """COLMAP's pair list cannot hold a name with a space: such a set is matched by COLMAP's spatial
    matcher on the camera centres instead, and still triangulates onto the surface."""
    scene, out = twin
    monkeypatch.setenv("HICO_CACHE_DIR", str(tmp_path / "cache"))
    spaced = tmp_path / "spaced"
    (spaced / "my photos").mkdir(parents=True)
    meta = json.loads((out / "transforms.json").read_text())
    for frame in meta["frames"]:
        name = "my photos/" + frame["file_path"].split("/")[-1].replace("_", " ")
        shutil.copy(out / frame["file_path"], spaced / name)
        frame["file_path"] = name
    (spaced / "transforms.json").write_text(json.dumps(meta))
    _assert_triangulated_onto_the_surface(scene, spaced, capsys)
