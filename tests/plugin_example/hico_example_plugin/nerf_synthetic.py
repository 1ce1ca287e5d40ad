"""A dataset format from outside: ``nerf-synthetic`` reads the NeRF-synthetic (Blender) layout,
``DIR/transforms_train.json`` and ``DIR/transforms_test.json``, whose test file holds the held-out views.

Registering the config is all it takes: ``hico-train hico-gs-lite --data DIR nerf-synthetic`` names it
(auto-detection finds it too), and ``hico-inspect`` and ``hico-bench --data`` offer it alike. Each file
is read by the built-in transforms.json reader; seed points are random, as 3D Gaussian Splatting does
on these object scenes (they carry no point cloud).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from hico_plugin.data.formats import DATA_FORMATS, DataFormat, SceneRecord
from hico_plugin.data.formats.transforms import TransformsFormat


@DATA_FORMATS.register("nerf-synthetic")
@dataclass
class NerfSyntheticFormat(DataFormat):
    """NeRF-synthetic (Blender): DIR/transforms_train.json and DIR/transforms_test.json (the test split)."""

    random_points: int = 20_000
    """Seed points drawn at random inside the cameras' bounds (the layout has no point cloud)."""

    def detect(self, data_dir: Path) -> bool:
        return (data_dir / "transforms_train.json").is_file()

    def read(self, data_dir: Path) -> SceneRecord:
        train = self._split(data_dir, "train")
        if not (data_dir / "transforms_test.json").is_file():
            return train
        test = self._split(data_dir, "test")
        # The test file numbers its cameras from 1 as well: shift them past the training file's.
        offset = max(train.cameras)
        for camera_id, camera in test.cameras.items():
            camera.camera_id = camera_id + offset
        views = sorted(range(len(train.names) + len(test.names)), key=lambda i: (train.names + test.names)[i])
        pick = lambda values: [values[i] for i in views]  # noqa: E731 -- views sorted by name, as a record holds them
        return SceneRecord(
            names=pick(train.names + test.names), image_paths=pick(train.image_paths + test.image_paths),
            camera_ids=pick(train.camera_ids + [camera_id + offset for camera_id in test.camera_ids]),
            cameras={**train.cameras, **{camera.camera_id: camera for camera in test.cameras.values()}},
            viewmats=np.concatenate([train.viewmats, test.viewmats])[views],
            # the training split's seed points (transforms.json has none: made once the loading size is known)
            points=train.points, point_colors=train.point_colors, seed_points_at=train.seed_points_at,
            test_names=list(test.names),
            notes=train.notes + test.notes,
        )

    def _split(self, data_dir: Path, split: str) -> SceneRecord:
        return TransformsFormat(file=f"transforms_{split}.json", triangulate=False,
                                random_points=self.random_points).read(data_dir)
