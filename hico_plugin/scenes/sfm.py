"""Optional real SfM on the rendered images (pycolmap: SIFT, exhaustive matching, incremental
mapping), aligned to the generator's frame so the ground truth stays valid."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pycolmap

from hico_plugin.errors import HicoError


def run_sfm(dataset: Path, reference: pycolmap.Reconstruction, K: np.ndarray, seed: int, num_threads: int = 2) -> dict:
    """Replace ``dataset/sparse/0`` by an SfM reconstruction of ``dataset/images``.

    Intrinsics are given (a calibrated camera), poses and points come from SfM. The largest model is
    aligned to ``reference`` (the known poses) by a similarity on the camera centres, so depth,
    normals and surface points remain ground truth for it. Returns statistics for scene.json."""
    work = dataset / ".sfm"
    work.mkdir()
    pycolmap.logging.minloglevel = 1  # COLMAP's per-step INFO lines would drown the summary
    database, images = work / "database.db", dataset / "images"
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = "PINHOLE"
    reader.camera_params = ",".join(f"{v:.10g}" for v in (K[0, 0], K[1, 1], K[0, 2], K[1, 2]))
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.num_threads = num_threads
    extraction.sift.max_num_features = 4096
    pycolmap.extract_features(
        database, images, camera_mode=pycolmap.CameraMode.SINGLE, reader_options=reader,
        extraction_options=extraction, device=pycolmap.Device.cpu,
    )
    pycolmap.match_exhaustive(database, device=pycolmap.Device.cpu)
    options = pycolmap.IncrementalPipelineOptions()
    options.num_threads = num_threads
    options.random_seed = seed
    options.ba_refine_focal_length = False
    options.ba_refine_principal_point = False
    options.ba_refine_extra_params = False
    models = pycolmap.incremental_mapping(database, images, work / "models", options)
    if not models:
        raise HicoError(f"--sfm: COLMAP registered no images in {images}; use the known poses (no --sfm)")
    model = max(models.values(), key=lambda m: m.num_reg_images())
    if model.num_reg_images() < 3:
        raise HicoError(
            f"--sfm: COLMAP registered only {model.num_reg_images()} of {len(reference.images)} images in {images} "
            "(too few views or overlap for SfM); add views (--num-views) or use the known poses (no --sfm)"
        )
    extent = np.ptp([img.projection_center() for img in reference.images.values()], axis=0).max()
    sim = pycolmap.align_reconstructions_via_proj_centers(model, reference, max_proj_center_error=0.05 * extent)
    if sim is None:
        raise HicoError(
            f"--sfm: could not align the SfM model ({model.num_reg_images()} images) to the known cameras"
        )
    model.transform(sim)
    by_name = {img.name: img for img in reference.images.values()}
    errors = [
        np.linalg.norm(img.projection_center() - by_name[img.name].projection_center())
        for img in model.images.values()
        if img.has_pose
    ]
    sparse = dataset / "sparse" / "0"
    shutil.rmtree(sparse)
    sparse.mkdir(parents=True)
    model.write_binary(str(sparse))
    shutil.rmtree(work)
    return {
        "registered_images": model.num_reg_images(),
        "num_points3D": model.num_points3D(),
        "mean_track_length": model.compute_mean_track_length(),
        "mean_reprojection_error_px": model.compute_mean_reprojection_error(),
        "camera_center_error_mean": float(np.mean(errors)),
        "camera_center_error_max": float(np.max(errors)),
    }
