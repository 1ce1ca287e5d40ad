"""Dataset formats: a transforms.json twin of a built-in scene reads and trains like its COLMAP twin."""

from __future__ import annotations

import json
import shutil

import cv2
import numpy as np
import pycolmap
import pytest
import torch

from hico_plugin.cli.train import parse as parse_train
from hico_plugin.cli.train import train
from hico_plugin.analysis.uncovered_cells import up_vector
from hico_plugin.data import DATA_FORMATS, DataParserConfig
from hico_plugin.data.transform import scene_up
from hico_plugin.errors import HicoError
from hico_plugin.scenes.generate import generate_scene

OPENCV = dict(k1=-0.12, k2=0.03, p1=0.001, p2=-0.0015)


def _distort(image: np.ndarray, pinhole: pycolmap.Camera, distorted: pycolmap.Camera) -> np.ndarray:
    """The view ``image`` (taken by ``pinhole``) as ``distorted`` would have taken it."""
    ys, xs = np.mgrid[: distorted.height, : distorted.width]
    pixels = np.stack([xs.ravel() + 0.5, ys.ravel() + 0.5], axis=-1).astype(np.float64)
    rays = distorted.cam_from_img(pixels)
    source = pinhole.img_from_cam(np.concatenate([rays, np.ones((len(rays), 1))], axis=1)) - 0.5
    maps = source.reshape(distorted.height, distorted.width, 2).astype(np.float32)
    return cv2.remap(image, maps[..., 0], maps[..., 1], cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT)


@pytest.fixture(scope="module")
def twins(tmp_path_factory):
    """(COLMAP twin, transforms.json twin) of the tiny scene, images distorted by an OPENCV camera."""
    root = tmp_path_factory.mktemp("twins")
    scene = generate_scene("tiny", root / "scene")
    model = pycolmap.Reconstruction(str(scene / "sparse" / "0"))
    pinhole = next(iter(model.cameras.values()))
    fx, fy, cx, cy = pinhole.params
    distorted = pycolmap.Camera(model="OPENCV", width=pinhole.width, height=pinhole.height,
                                params=[fx, fy, cx, cy, *OPENCV.values()], camera_id=pinhole.camera_id)
    colmap, transforms = root / "colmap", root / "transforms"
    for twin in (colmap, transforms):
        (twin / "images").mkdir(parents=True)
        for image in model.images.values():
            rgb = cv2.imread(str(scene / "images" / image.name))
            cv2.imwrite(str(twin / "images" / image.name), _distort(rgb, pinhole, distorted))
    model.cameras[pinhole.camera_id].model = distorted.model
    model.cameras[pinhole.camera_id].params = distorted.params
    (colmap / "sparse" / "0").mkdir(parents=True)
    model.write_binary(str(colmap / "sparse" / "0"))
    frames = []
    for image in sorted(model.images.values(), key=lambda im: im.name):
        c2w = np.eye(4)
        c2w[:3, :] = image.cam_from_world().inverse().matrix()
        c2w[:, 1:3] *= -1  # OpenCV -> OpenGL camera axes, as nerfstudio stores them
        # an applied_transform the loader must undo (a rotation about z and a shift)
        frames.append({"file_path": f"images/{image.name}", "transform_matrix": (APPLIED @ c2w).tolist()})
    points = np.array([p.xyz for p in model.points3D.values()]) @ APPLIED[:3, :3].T + APPLIED[:3, 3]
    colors = np.array([p.color for p in model.points3D.values()])
    cloud = pycolmap.Reconstruction()
    for xyz, color in zip(points, colors):
        cloud.add_point3D(xyz, pycolmap.Track(), color)
    cloud.export_PLY(str(transforms / "sparse_pc.ply"))
    meta = {"camera_model": "OPENCV", "fl_x": fx, "fl_y": fy, "cx": cx, "cy": cy, "w": pinhole.width,
            "h": pinhole.height, **OPENCV, "applied_transform": APPLIED[:3].tolist(),
            "ply_file_path": "sparse_pc.ply", "frames": frames}
    (transforms / "transforms.json").write_text(json.dumps(meta))
    return colmap, transforms


_angle = 0.4
APPLIED = np.array([[np.cos(_angle), -np.sin(_angle), 0, 0.5], [np.sin(_angle), np.cos(_angle), 0, -1.0],
                    [0, 0, 1, 0.25], [0, 0, 0, 1]])


def test_transforms_twin_reads_like_the_colmap_twin(twins):
    colmap, transforms = (DataParserConfig(data=twin).setup() for twin in twins)
    assert type(DataParserConfig(data=twins[1]).format) is type(None)  # detected, not named
    assert colmap.image_names == [name.removeprefix("images/") for name in transforms.image_names]
    assert torch.allclose(colmap.cameras.viewmats, transforms.cameras.viewmats, atol=1e-5)
    assert torch.allclose(colmap.cameras.Ks, transforms.cameras.Ks)
    def rows(points):  # the PLY holds the points in another order
        return points[np.lexsort(np.round(points.numpy(), 4).T)]

    assert np.allclose(rows(colmap.points), rows(transforms.points), atol=1e-5)
    assert torch.equal(colmap.image(3), transforms.image(3))
    assert colmap.sources[1].needs_undistortion


def test_transforms_twin_trains_to_the_colmap_twins_psnr(twins, tmp_path):
    psnr = {}
    for twin in twins:
        config = parse_train(["hico-gs-lite", "--data", str(twin), "--max-steps", "60", "--vis", "none",
                              "--progress", "none", "--output-dir", str(tmp_path / twin.name),
                              "--model.eval-lpips", "none", "--model.renderer.no-use-compile"])
        train(config)
        psnr[twin.name] = json.loads((tmp_path / twin.name / "eval.json").read_text())["results"]["psnr"]
    print(f"PSNR after 60 steps: COLMAP twin {psnr['colmap']:.3f} dB, transforms.json twin {psnr['transforms']:.3f} dB")
    assert psnr["transforms"] == pytest.approx(psnr["colmap"], abs=0.05)


def test_transforms_missing_frames_are_named_and_points_fall_back(twins, tmp_path, capsys):
    twin = tmp_path / "twin"
    shutil.copytree(twins[1], twin)
    meta = json.loads((twin / "transforms.json").read_text())
    del meta["ply_file_path"]
    meta["frames"].append({"file_path": "images/gone.png", "transform_matrix": meta["frames"][0]["transform_matrix"]})
    (twin / "transforms.json").write_text(json.dumps(meta))
    dataset = DataParserConfig(data=twin).setup()
    err = capsys.readouterr().err
    assert "1 of 13 frames skipped, image file missing: images/gone.png" in err
    assert "random points" in err and len(dataset.points) == 20_000
    meta["frames"][0]["file_path"] = "../outside.png"
    (twin / "transforms.json").write_text(json.dumps(meta))
    with pytest.raises(HicoError, match=r"frames\[0\].file_path: file name '../outside.png' climbs out"):
        DataParserConfig(data=twin).setup()


def test_formats_are_registered_components():
    assert {"colmap", "transforms"} <= set(DATA_FORMATS.names())


@pytest.mark.parametrize("factor", [0.001, 1000.0])
def test_scene_units_do_not_matter(tmp_path, factor):
    """The same scene in millimetres or kilometres loads to the same normalised cameras and points, so
    octree sizes, LOD distances and learning rates (all set in the normalised frame) mean the same and
    training is the same run."""
    scene = generate_scene("tiny", tmp_path / "scene")
    scaled = tmp_path / "scaled"
    shutil.copytree(scene / "images", scaled / "images")
    model = pycolmap.Reconstruction(str(scene / "sparse" / "0"))
    model.transform(pycolmap.Sim3d(factor, pycolmap.Rotation3d(), np.array([3.0, -7.0, 1.0]) * factor))
    (scaled / "sparse" / "0").mkdir(parents=True)
    model.write_binary(str(scaled / "sparse" / "0"))
    original, rescaled = DataParserConfig(data=scene).setup(), DataParserConfig(data=scaled).setup()
    assert rescaled.transform.scale == pytest.approx(original.transform.scale / factor, rel=1e-9)
    assert torch.allclose(original.cameras.viewmats, rescaled.cameras.viewmats, atol=1e-5)
    assert torch.allclose(original.points, rescaled.points, atol=1e-5)
    assert original.cameras_extent() == pytest.approx(rescaled.cameras_extent(), rel=1e-5)


def test_scene_is_oriented_up_from_the_cameras(tmp_path):
    """A built-in scene turned by a random rotation loads z-up like the original: the cameras' mean up
    is +z, and heights (z) of cameras and points match; only the heading about z may differ."""
    scene = generate_scene("tiny", tmp_path / "scene")
    turned = tmp_path / "turned"
    shutil.copytree(scene / "images", turned / "images")
    model = pycolmap.Reconstruction(str(scene / "sparse" / "0"))
    q, _ = np.linalg.qr(np.random.default_rng(7).normal(size=(3, 3)))
    rotation = q * np.sign(np.linalg.det(q))
    model.transform(pycolmap.Sim3d(1.0, pycolmap.Rotation3d(rotation), np.array([2.0, -1.0, 0.5])))
    (turned / "sparse" / "0").mkdir(parents=True)
    model.write_binary(str(turned / "sparse" / "0"))
    original, rotated = DataParserConfig(data=scene).setup(), DataParserConfig(data=turned).setup()
    up = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    for dataset in (original, rotated):
        assert torch.allclose(scene_up(dataset.cameras.viewmats), up, atol=1e-5)
        assert np.allclose(up_vector(dataset), up.numpy(), atol=1e-5)
    assert torch.allclose(original.cameras.centers[:, 2], rotated.cameras.centers[:, 2], atol=1e-5)
    assert torch.allclose(original.points[:, 2], rotated.points[:, 2], atol=1e-5)
    # without --orient the turned scene keeps its tilted up
    tilted = DataParserConfig(data=turned, orient=False).setup()
    assert float(scene_up(tilted.cameras.viewmats) @ up) < 0.99
