"""The Mega-NeRF layout: a twin of a built-in scene, written with Mega-NeRF's conventions, loads to the
same cameras and split; bad metadata fails with one line naming the file and field."""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import numpy as np
import pycolmap
import pytest
import torch

from hico_plugin.data import DataParserConfig
from hico_plugin.data.formats.meganerf import MegaNerfFormat
from hico_plugin.data.parser import detect_format
from hico_plugin.errors import HicoError
from hico_plugin.scenes.generate import generate_scene
from helpers_datasets import ORIGIN_DRB, RDF_TO_DRB, SCALE, write_meganerf



@pytest.fixture(scope="module")
def twin(tmp_path_factory):
    root = tmp_path_factory.mktemp("meganerf")
    scene = generate_scene("tiny", root / "scene")
    return scene, root / "mega", write_meganerf(scene, root / "mega")


def test_the_writer_follows_meganerfs_ray_convention(twin):
    """Independent of our reader: Mega-NeRF's ray for the pixel where COLMAP projects a point passes
    through that point once it is moved into Mega-NeRF's frame."""
    scene, mega, names = twin
    model = pycolmap.Reconstruction(str(scene / "sparse" / "0"))
    by_name = {image.name: image for image in model.images.values()}
    points = np.array([p.xyz for p in model.points3D.values()])[:20]
    for mega_name, name in list(names.items())[:3]:
        meta = torch.load(mega / mega_name.replace("rgbs", "metadata").replace(".png", ".pt"), weights_only=True)
        c2w, (fx, fy, cx, cy) = meta["c2w"].double().numpy(), meta["intrinsics"].double().numpy()
        image = by_name[name]
        pixels = model.cameras[image.camera_id].img_from_cam(image.cam_from_world() * points)
        directions = np.stack([(pixels[:, 0] - cx) / fx, -(pixels[:, 1] - cy) / fy, -np.ones(len(pixels))], -1)
        rays = directions @ c2w[:, :3].T
        targets = (points @ RDF_TO_DRB.T - ORIGIN_DRB) / SCALE - c2w[:, 3]
        off_ray = np.linalg.norm(np.cross(rays, targets), axis=1) / np.linalg.norm(rays, axis=1)
        assert off_ray.max() < 1e-5 * np.linalg.norm(targets, axis=1).max()
        assert (np.einsum("ij,ij->i", rays, targets) > 0).all()  # in front of the camera


@pytest.mark.parametrize("normalize", [False, True])
def test_meganerf_twin_loads_the_known_cameras(twin, normalize):
    scene, mega, names = twin
    assert isinstance(detect_format(mega), MegaNerfFormat)
    colmap = DataParserConfig(data=scene, normalize=normalize).setup()
    loaded = DataParserConfig(data=mega, normalize=normalize).setup()
    assert sorted(loaded.image_names) == sorted(names)
    order = [colmap.image_names.index(names[name]) for name in loaded.image_names]
    # float32 storage of c2w in Mega-NeRF's [-1, 1] frame: ~1e-7 relative, times the scale back
    assert torch.allclose(loaded.cameras.viewmats, colmap.cameras.viewmats[order], atol=2e-5)
    assert torch.allclose(loaded.cameras.Ks, colmap.cameras.Ks[order], atol=1e-4)
    assert torch.equal(loaded.cameras.widths, colmap.cameras.widths[order])
    assert torch.equal(loaded.cameras.heights, colmap.cameras.heights[order])
    assert [loaded.image_names[i] for i in loaded.test_indices] == [n for n in loaded.image_names if n.startswith("val/")]
    assert len(loaded.train_indices) + len(loaded.test_indices) == len(names)
    assert torch.equal(loaded.image(1), colmap.image(order[1]))


def test_meganerf_is_selectable_by_name_and_test_names_still_override(twin):
    _, mega, names = twin
    first = sorted(names)[0]
    dataset = DataParserConfig(data=mega, format=MegaNerfFormat(random_points=500), test_names=(first,)).setup()
    assert [dataset.image_names[i] for i in dataset.test_indices] == [first]


def _broken_copy(twin, tmp_path: Path) -> tuple[Path, Path]:
    copy = tmp_path / "mega"
    shutil.copytree(twin[1], copy)
    return copy, copy / "train" / "metadata" / "000001.pt"


@pytest.mark.parametrize(
    "change, message",
    [
        (lambda m: m.pop("intrinsics"), r"000001\.pt: field 'intrinsics' missing"),
        (lambda m: m.update(c2w=torch.eye(3)), r"000001\.pt: field 'c2w' is \(3, 3\); expected finite \[3, 4\]"),
        (lambda m: m.update(W=-4), r"000001\.pt: field 'W' is -4; expected a positive whole number"),
        (lambda m: m.update(intrinsics=torch.tensor([float("nan"), 1.0, 2.0, 3.0])), r"field 'intrinsics' is \(4,\); expected finite"),
        (lambda m: m["c2w"].mul_(2.0), r"000001\.pt: field 'c2w' has a rotation part that is not orthonormal"),
    ],
)
def test_bad_metadata_names_the_file_and_field(twin, tmp_path, change, message):
    copy, path = _broken_copy(twin, tmp_path)
    meta = torch.load(path, weights_only=True)
    change(meta)
    torch.save(meta, path)
    with pytest.raises(HicoError, match=message):
        DataParserConfig(data=copy).setup()


class _RunsCode:
    """Pickles to a call of os.makedirs: what a crafted metadata file could make a plain torch.load run."""

    def __init__(self, marker: Path):
        self.marker = marker

    def __reduce__(self):
        return os.makedirs, (str(self.marker),)


def test_a_pickle_that_would_run_code_is_refused(twin, tmp_path):
    copy, path = _broken_copy(twin, tmp_path)
    marker = tmp_path / "code-ran"
    torch.save({"H": _RunsCode(marker)}, path)
    with pytest.raises(HicoError, match=r"000001\.pt: refused or unreadable .*weights_only=True") as info:
        DataParserConfig(data=copy).setup()
    assert not marker.exists() and "\n" not in str(info.value)
    path.write_bytes(path.read_bytes()[:100])  # truncated
    with pytest.raises(HicoError, match=r"000001\.pt: refused or unreadable") as info:
        DataParserConfig(data=copy).setup()
    assert "\n" not in str(info.value)
    (copy / "coordinates.pt").unlink()
    with pytest.raises(HicoError, match=r"coordinates\.pt: not found"):
        DataParserConfig(data=copy).setup()


def test_metadata_without_its_image_is_named(twin, tmp_path):
    copy, path = _broken_copy(twin, tmp_path)
    (copy / "train" / "rgbs" / "000001.png").unlink()
    with pytest.raises(HicoError, match=r"000001\.pt: no image train/rgbs/000001\.jpg or \.png"):
        DataParserConfig(data=copy).setup()
