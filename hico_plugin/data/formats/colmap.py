"""COLMAP layout: DIR/images + DIR/sparse/0 (binary or text; also hico-process output)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path


from hico_plugin.data.colmap import find_model_dir, read_colmap_model
from hico_plugin.data.formats import DATA_FORMATS, DataFormat, SceneRecord
from hico_plugin.data.paths import resolve_inside
from hico_plugin.errors import HicoError


@DATA_FORMATS.register("colmap")
@dataclass
class ColmapFormat(DataFormat):
    """COLMAP: DIR/<images-dir>/ and DIR/sparse/0/ (cameras, images, points3D as .bin or .txt)."""

    images_dir: str = "images"
    """Folder of the images inside the dataset directory."""

    def detect(self, data_dir: Path) -> bool:
        return (data_dir / "sparse" / "0").is_dir()

    def read(self, data_dir: Path) -> SceneRecord:
        model = read_colmap_model(find_model_dir(data_dir))
        image_dir = data_dir / self.images_dir
        if not image_dir.is_dir():
            raise HicoError(f"{image_dir}: image folder not found (set --images-dir to the folder of the images)")
        paths = [resolve_inside(image_dir, name, f"sparse/0/images: image {name!r}") for name in model.names]
        return SceneRecord(
            names=model.names, image_paths=paths, camera_ids=model.camera_ids, cameras=model.cameras,
            viewmats=model.viewmats, points=model.points, point_colors=model.point_colors, tracks=model.tracks,
            has_ground_truth=(data_dir / "ground_truth").is_dir(),
        )


__all__ = ["ColmapFormat"]
