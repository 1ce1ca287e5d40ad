"""Structure from motion on pycolmap 4: SIFT features, matching, mapping, undistortion, downscales.

Output layout (what ``--data OUT`` trains on, nerfstudio's folder names)::

    OUT/images/            pinhole images of the registered views (undistorted, or as taken when
                           their camera's distortion moves no pixel by more than half a pixel)
    OUT/images_{2,4,8}/    the same, downscaled by 2, 4, 8
    OUT/sparse/0/          the pinhole COLMAP model
    OUT/colmap/            work files: input images, database.db, the distorted models
    OUT/process.json       the summary printed at the end
"""

from __future__ import annotations

import shutil
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import cv2
import numpy as np
import pycolmap

from hico_plugin.data import images as image_io
from hico_plugin.errors import HicoError
from hico_plugin.process.ingest import photo_info
from hico_plugin.process.stages import Report, StageRunner, stage_key
from hico_plugin.process.undistort import KEEP_BELOW_PX, describe, undistort

Matcher = Literal["exhaustive", "sequential", "spatial"]
Mapper = Literal["incremental", "global", "hierarchical"]
CameraMode = Literal["auto", "single", "per-folder", "per-image"]
IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".tif", ".tiff", ".bmp", ".webp")


@dataclass
class SfmOptions:
    """Options of the SfM stages (shared by ``hico-process images`` and ``hico-process video``)."""

    matcher: Matcher = "exhaustive"
    """exhaustive: every pair (up to a few hundred images); sequential: neighbours in name order plus
    loop detection pairs (video); spatial: neighbours by GPS position from EXIF."""
    mapper: Mapper = "incremental"
    """incremental (COLMAP), global (GLOMAP: faster on large sets), hierarchical (partitions the scene
    and merges: for city-scale sets)."""
    camera_model: str = "OPENCV"
    """COLMAP camera model estimated for the photos (SIMPLE_PINHOLE, PINHOLE, SIMPLE_RADIAL, RADIAL,
    OPENCV, OPENCV_FISHEYE, ...); images are undistorted to PINHOLE at the end (kept as taken for a
    camera whose distortion moves no pixel by more than --keep-below-px)."""
    camera_params: str = ""
    """Known intrinsics as COLMAP lists them for --camera-model (e.g. PINHOLE: "fx,fy,cx,cy"); empty =
    estimated, starting from the EXIF focal length (or 1.2 x the image size without EXIF)."""
    camera_mode: CameraMode = "auto"
    """auto: one camera per distinct camera the photos' sizes and EXIF (make, model, focal length) name;
    single: one camera for all photos; per-folder: one per sub-folder; per-image: one each."""
    max_features: int = 8192
    """SIFT features per image."""
    max_image_size: int = 3200
    """Longest side features are extracted at (larger photos are downscaled for SIFT only)."""
    min_registered: float = 0.5
    """Fail when fewer than this fraction of the images register."""
    num_threads: int = -1
    """Threads for COLMAP (-1: all cores)."""
    seed: int = 0
    """Random seed of the mapper (same inputs and seed -> same model)."""
    keep_below_px: float = KEEP_BELOW_PX
    """A camera whose fitted distortion moves no pixel by more than this many pixels keeps its photos as
    taken (written as PINHOLE without the distortion); the others' photos are resampled to PINHOLE,
    which blurs them a little. 0: resample every camera with any distortion."""
    downscales: tuple[int, ...] = (2, 4, 8)
    """Write images_N copies for these factors (nerfstudio's layout; --downscale N loads them)."""


def list_images(folder: Path) -> list[str]:
    """Relative names of the image files under ``folder`` (recursively, sorted)."""
    return sorted(
        str(path.relative_to(folder)) for path in folder.rglob("*")
        if path.is_file() and path.suffix.lower() in IMAGE_SUFFIXES and not path.name.startswith(".")
    )


def run_sfm(input_dir: Path, names: list[str], out: Path, options: SfmOptions, runner: StageRunner,
            input_key: Any) -> dict[str, Any]:
    """Features -> matches -> model -> undistorted dataset in ``out``; returns the summary.
    ``input_key`` identifies the input images (a stage is reused only for the same inputs)."""
    if options.camera_model not in {model.name for model in pycolmap.CameraModelId.__members__.values()}:
        known = ", ".join(sorted(pycolmap.CameraModelId.__members__))
        raise HicoError(f"--camera-model: unknown COLMAP model {options.camera_model!r}; expected one of {known}")
    if not options.keep_below_px >= 0:  # NaN too
        raise HicoError(f"--keep-below-px: expected a distance in pixels >= 0, got {options.keep_below_px}")
    work = out / "colmap"
    database = work / "database.db"
    masks = input_dir.parent / "masks"  # where ingest_photos put the photos' transparency, if any
    cameras = camera_groups(input_dir, names, options.camera_mode)
    pycolmap.logging.minloglevel = 2  # COLMAP's INFO/WARNING lines would drown the progress bars
    key = stage_key(input_key, options.camera_model, options.camera_params, options.camera_mode, options.max_features,
                    options.max_image_size)
    runner.run("features", key, lambda report: _extract(database, input_dir, cameras, masks, options, report))
    key = stage_key(key, options.matcher)
    runner.run("matching", key, lambda report: _match(database, options))
    key = stage_key(key, options.mapper, options.seed)
    mapped = runner.run("mapping", key, lambda report: _map(database, input_dir, work / "sparse", options, report))
    model_dir = work / "sparse" / str(mapped["model"])
    key = stage_key(key, options.keep_below_px)
    undistorted = runner.run("undistort", key, lambda report: undistort(model_dir, input_dir, masks, out, report,
                                                                        options.keep_below_px))
    key = stage_key(key, list(options.downscales))
    runner.run("downscale", key, lambda report: _downscale(out, options.downscales, report))
    summary = _summary(database, names, pycolmap.Reconstruction(str(model_dir)), options)
    summary["undistortion"] = undistorted["cameras"]
    return summary


def camera_groups(input_dir: Path, names: list[str], mode: CameraMode) -> list[list[str]]:
    """The photos each COLMAP camera holds: one group per distinct (size, EXIF make, model, focal
    length) for ``auto``, else as ``mode`` says. A forced mode whose camera would hold photos of
    different sizes is refused here, before any feature is extracted (a camera has one size)."""
    infos = {name: photo_info(input_dir / name) for name in names}
    if mode == "per-image":
        return [[name] for name in names]
    groups: dict[Any, list[str]] = {}
    for name in names:
        key = {"auto": infos[name].camera_key(), "single": None, "per-folder": str(Path(name).parent)}[mode]
        groups.setdefault(key, []).append(name)
    if mode != "auto":
        for group in groups.values():
            sizes: dict[tuple[int, int], list[str]] = {}
            for name in group:
                sizes.setdefault((infos[name].width, infos[name].height), []).append(name)
            if len(sizes) > 1:
                listed = "; ".join(f"{w}x{h}: {len(n)} photo(s), e.g. {n[0]}" for (w, h), n in sorted(sizes.items()))
                raise HicoError(f"--camera-mode {mode}: one camera has one image size, but its photos have "
                                f"{len(sizes)} ({listed}); use --camera-mode auto (one camera per size and EXIF "
                                "camera) or per-image")
    return list(groups.values())


def _extract(database: Path, input_dir: Path, cameras: list[list[str]], masks: Path, options: SfmOptions,
             report: Report) -> dict[str, Any]:
    database.parent.mkdir(parents=True, exist_ok=True)
    database.unlink(missing_ok=True)  # a half-written database from a crash is not resumable
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = options.camera_model
    reader.camera_params = options.camera_params
    if masks.is_dir():
        reader.mask_path = str(masks)  # no features where a photo was transparent
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.num_threads = options.num_threads
    extraction.max_image_size = options.max_image_size
    extraction.sift.max_num_features = options.max_features
    total = sum(len(group) for group in cameras)
    done = 0
    # pycolmap reports no per-image progress; the bar advances by camera. Each call adds one camera
    # that holds its group's photos.
    report(done, total)
    for group in cameras:
        pycolmap.extract_features(database, input_dir, image_names=group, camera_mode=pycolmap.CameraMode.SINGLE,
                                  reader_options=reader, extraction_options=extraction, device=pycolmap.Device.cpu)
        done += len(group)
        report(done, total)
    return {"cameras": len(cameras)}


def _match(database: Path, options: SfmOptions) -> None:
    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = options.num_threads
    device = pycolmap.Device.cpu
    if options.matcher == "exhaustive":
        pycolmap.match_exhaustive(database, matching_options=matching, device=device)
    elif options.matcher == "sequential":
        pairing = pycolmap.SequentialPairingOptions()
        pairing.overlap = 10
        pairing.quadratic_overlap = True
        pycolmap.match_sequential(database, matching_options=matching, pairing_options=pairing, device=device)
    else:
        with pycolmap.Database.open(database) as db:
            has_gps = db.num_pose_priors() > 0
        if not has_gps:
            raise HicoError("--matcher spatial: no image has a GPS position in its EXIF; use exhaustive or sequential")
        pycolmap.match_spatial(database, matching_options=matching, device=device)


def _map(database: Path, input_dir: Path, sparse: Path, options: SfmOptions, report: Report) -> dict[str, Any]:
    if sparse.exists():
        shutil.rmtree(sparse)
    sparse.mkdir(parents=True)
    with pycolmap.Database.open(database) as db:
        total = db.num_images()
    if options.mapper == "incremental":
        pipeline = pycolmap.IncrementalPipelineOptions()
        pipeline.num_threads = options.num_threads
        pipeline.random_seed = options.seed
        registered = [0]

        def next_image() -> None:
            registered[0] += 1
            report(min(registered[0], total), total)

        models = pycolmap.incremental_mapping(database, input_dir, sparse, pipeline, next_image_callback=next_image)
    elif options.mapper == "global":
        pipeline = pycolmap.GlobalPipelineOptions()
        pipeline.num_threads = options.num_threads
        pipeline.random_seed = options.seed
        models = pycolmap.global_mapping(database, input_dir, sparse, pipeline)
    else:
        pipeline = pycolmap.HierarchicalPipelineOptions()
        pipeline.num_threads = options.num_threads
        models = pycolmap.hierarchical_mapping(database, input_dir, sparse, pipeline)
    if not models:
        raise HicoError(
            f"{input_dir}: COLMAP registered no images ({total} given); the photos need more overlap "
            "(each spot seen from 3+ photos, ~60% overlap between neighbours) and texture"
        )
    best = max(models, key=lambda index: models[index].num_reg_images())
    registered = models[best].num_reg_images()
    if registered < max(3, options.min_registered * total):
        raise HicoError(
            f"{input_dir}: only {registered} of {total} images registered (expected at least "
            f"{max(3, int(np.ceil(options.min_registered * total)))}, --min-registered {options.min_registered}); "
            "the photos need more overlap and texture, or try --matcher exhaustive / --mapper incremental"
        )
    # every model is written under sparse/<i> by the pipelines; make sure the chosen one is on disk
    models[best].write_binary(str(sparse / str(best)))
    return {"model": int(best), "models": len(models)}


def _downscale(out: Path, factors: tuple[int, ...], report: Report) -> None:
    names = list_images(out / "images")
    for factor in factors:
        if (out / f"images_{factor}").exists():
            shutil.rmtree(out / f"images_{factor}")
    for done, name in enumerate(names, start=1):
        image = image_io.read_rgb(out / "images" / name)
        height, width = image.shape[:2]
        for factor in factors:
            small = image_io.resize(image, -(-width // factor), -(-height // factor))
            target = out / f"images_{factor}" / name
            target.parent.mkdir(parents=True, exist_ok=True)
            if not cv2.imwrite(str(target), cv2.cvtColor(small, cv2.COLOR_RGB2BGR)):
                raise HicoError(f"{target}: cannot be written")
        report(done, len(names))


def _summary(database: Path, names: list[str], model: pycolmap.Reconstruction, options: SfmOptions) -> dict[str, Any]:
    registered = {image.name for image in model.images.values() if image.has_pose}
    dropped: dict[str, str] = {}
    with pycolmap.Database.open(database) as db:
        by_name = {image.name: image.image_id for image in db.read_all_images()}
        inlier_pairs: dict[int, int] = {}
        for pair_id, geometry in zip(*db.read_two_view_geometries()):
            if len(geometry.inlier_matches) == 0:
                continue
            for image_id in pycolmap.pair_id_to_image_pair(pair_id):
                inlier_pairs[image_id] = inlier_pairs.get(image_id, 0) + 1
        for name in names:
            if name in registered:
                continue
            image_id = by_name.get(name)
            if image_id is None:
                dropped[name] = "unreadable image"
            elif db.num_keypoints_for_image(image_id) < 50:
                dropped[name] = f"too few features ({db.num_keypoints_for_image(image_id)})"
            elif inlier_pairs.get(image_id, 0) == 0:
                dropped[name] = "no verified matches to any other image"
            else:
                dropped[name] = f"matched {inlier_pairs[image_id]} images but not registered by the mapper"
    return {
        "images": len(names),
        "registered": len(registered),
        "dropped": dropped,
        "cameras": model.num_cameras(),
        "points3D": model.num_points3D(),
        "mean_track_length": model.compute_mean_track_length(),
        "mean_reprojection_error_px": model.compute_mean_reprojection_error(),
        "matcher": options.matcher,
        "mapper": options.mapper,
        "camera_model": options.camera_model,
    }


def print_summary(summary: dict[str, Any], out: Path, timings: dict[str, float], reused: list[str],
                  echo: Callable[[str], None] = print) -> None:
    echo(f"registered {summary['registered']} of {summary['images']} images "
         f"({summary['cameras']} camera(s), {summary['camera_model']}, {summary['matcher']} matching, "
         f"{summary['mapper']} mapping)")
    for name, reason in sorted(summary["dropped"].items()):
        echo(f"  dropped  {name}: {reason}")
    if summary.get("rewritten"):
        echo(f"normalised {len(summary['rewritten'])} photo(s) on the way in (upright, 8-bit RGB; "
             f"{len(summary.get('masked', []))} with a transparency mask in masks/)")
    for choice in summary["undistortion"]:
        echo(describe(choice))
    echo(f"points3D   {summary['points3D']} (mean track length {summary['mean_track_length']:.2f}, "
         f"mean reprojection error {summary['mean_reprojection_error_px']:.3f} px)")
    stages = ", ".join(f"{name} {seconds:.1f} s" for name, seconds in timings.items())
    echo(f"time       {sum(timings.values()):.1f} s ({stages})" + (f"; reused: {', '.join(reused)}" if reused else ""))
    echo(f"dataset    {out}   (train: hico-train hico-gs-lite --data {out})")
