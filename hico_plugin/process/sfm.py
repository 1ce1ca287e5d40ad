"""Structure from motion on pycolmap 4: SIFT features, matching, mapping, undistortion, downscales.

Output (what ``--data OUT`` trains on, nerfstudio's folder names): ``OUT/images/`` (pinhole images of the
registered views, undistorted or as taken when no pixel moves by over half a pixel), ``OUT/images_{2,4,8}/``
(downscaled), ``OUT/sparse/0/`` (the pinhole COLMAP model), ``OUT/colmap/`` (input images, database.db, the
distorted models) and ``OUT/process.json`` (the summary printed at the end).
"""

from __future__ import annotations

import shutil
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal, Optional

import cv2
import numpy as np
import pycolmap

from hico_plugin.data import images as image_io
from hico_plugin.errors import HicoError
from hico_plugin.process.ingest import PhotoInfo, photo_info
from hico_plugin.process.matching import check_vocab_tree, choose_matcher, match
from hico_plugin.process.stages import Report, StageRunner, stage_key
from hico_plugin.process.undistort import KEEP_BELOW_PX, describe, undistort

Matcher = Literal["auto", "exhaustive", "sequential", "spatial", "vocabtree"]
Mapper = Literal["auto", "incremental", "global", "hierarchical"]
CameraMode = Literal["auto", "single", "per-folder", "per-image"]
IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".tif", ".tiff", ".bmp", ".webp")
EXTRACT_CHUNK = 32
"""Photos per feature extraction call: a progress step each."""


@dataclass
class SfmOptions:
    """Options of the SfM stages (shared by ``hico-process images`` and ``hico-process video``)."""

    matcher: Matcher = "auto"
    """Which photo pairs are matched. auto: exhaustive up to --exhaustive-max photos, above it sequential
    for video frames, spatial when every photo has GPS in its EXIF, else vocabtree (the choice is
    printed with its reason). exhaustive: every pair; sequential: the next frames in name order plus
    loop closures; spatial: the --neighbors nearest by GPS; vocabtree: the --neighbors most alike."""
    exhaustive_max: int = 100
    """Most photos --matcher auto matches exhaustively: about (n - 1) / 2 pairs a photo, as many as
    --neighbors gives the matchers above it, whose cost grows linearly with the photos."""
    neighbors: int = 50
    """Photos each photo is matched with by spatial (nearest GPS positions) and vocabtree (most alike)
    matching, and loop-closure candidates of sequential matching (COLMAP's spatial default)."""
    vocab_tree: Optional[Path] = None
    """A COLMAP vocabulary tree file for vocabtree and sequential matching (e.g. one of COLMAP's
    published trees); default: one built from the photos' own SIFT features, nothing downloaded."""
    mapper: Mapper = "auto"
    """auto: incremental up to --incremental-max photos, global above, the other one when the first
    registers too few. incremental (COLMAP): the most robust; global (GLOMAP): all poses at once, faster
    on large sets; hierarchical: partitions the scene and merges the parts."""
    incremental_max: int = 300
    """Most photos --mapper auto maps incrementally: above it, the global mapper solves every pose at
    once instead of a bundle adjustment for every few photos added, which makes incremental slow there."""
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
    max_image_size: int = image_io.MAX_LONG_SIDE
    """Long side training aims for (hico-train's --max-long-side, the same default): SIFT reads each
    photo at the size training loads it, the smallest power-of-two downscale of the set within this."""
    min_registered: float = 0.5
    """Fail when fewer than this fraction of the images register."""
    num_threads: int = -1
    """Threads for COLMAP (-1: all cores)."""
    seed: int = 0
    """Random seed of the mapper and of the vocabulary tree's sample (same inputs and seed -> same model)."""
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


def check_options(options: SfmOptions) -> None:
    """A HicoError for an option that is wrong whatever the photos are (checked before anything slow)."""
    if options.camera_model not in {model.name for model in pycolmap.CameraModelId.__members__.values()}:
        known = ", ".join(sorted(pycolmap.CameraModelId.__members__))
        raise HicoError(f"--camera-model: unknown COLMAP model {options.camera_model!r}; expected one of {known}")
    if not options.keep_below_px >= 0:  # NaN too
        raise HicoError(f"--keep-below-px: expected a distance in pixels >= 0, got {options.keep_below_px}")
    for flag, value in (("--exhaustive-max", options.exhaustive_max), ("--incremental-max", options.incremental_max),
                        ("--neighbors", options.neighbors), ("--max-image-size", options.max_image_size)):
        if value < 1:
            raise HicoError(f"{flag}: expected a whole number >= 1, got {value}")
    if options.vocab_tree is not None and not options.vocab_tree.expanduser().is_file():
        raise HicoError(f"--vocab-tree {options.vocab_tree}: file not found (expected a COLMAP vocabulary tree file)")


def choose_mapper(count: int, options: SfmOptions) -> tuple[str, str]:
    """The mapper for ``count`` photos and why: ``options.mapper`` unless it is ``auto``; then
    incremental, COLMAP's most robust, up to ``options.incremental_max`` photos, and global above,
    where incremental's repeated bundle adjustments make it slow (COLMAP's FAQ on the three mappers)."""
    if options.mapper != "auto":
        return options.mapper, f"asked for (--mapper {options.mapper})"
    if count <= options.incremental_max:
        return "incremental", f"{count} photos, at most --incremental-max {options.incremental_max}: the most robust"
    return "global", (f"{count} photos, over --incremental-max {options.incremental_max}: every pose at once "
                      "(rotation averaging, global positioning), no bundle adjustment per photo added")


def map_with_fallback(map_one: Callable[[str], dict[str, Any]], mapper: str, auto: bool,
                      say: Callable[[str], None]) -> dict[str, Any]:
    """``map_one(mapper)``; under --mapper auto, a mapper that registers too few hands the set to the other
    (incremental <-> global): either can stop early on a set the other maps (COLMAP's FAQ on the mappers)."""
    try:
        return map_one(mapper)
    except HicoError as err:
        other = {"incremental": "global", "global": "incremental"}.get(mapper)
        if not auto or other is None:
            raise
        say(f"{'mapping':<12} the {mapper} mapper fell short ({err}); mapping with the {other} mapper instead")
        return map_one(other)


def feature_sizes(infos: dict[str, PhotoInfo], groups: list[list[str]], max_long_side: int) -> list[int]:
    """Per camera group, the long side SIFT reads its photos at: the size training loads them (the
    whole set's power-of-two downscale within ``max_long_side``, ``image_io.downscale_factor``)."""
    factor = image_io.downscale_factor(max(max(info.width, info.height) for info in infos.values()), max_long_side)
    return [max(1, round(max(max(infos[n].width, infos[n].height) for n in group) / factor)) for group in groups]


def run_sfm(input_dir: Path, names: list[str], out: Path, options: SfmOptions, runner: StageRunner,
            input_key: Any, ordered: bool = False) -> dict[str, Any]:
    """Features -> matches -> model -> undistorted dataset in ``out``; returns the summary.
    ``input_key`` identifies the input images (a stage is reused only for the same inputs); ``ordered``:
    the images are the frames of one video, in time order."""
    check_options(options)
    work = out / "colmap"
    database = work / "database.db"
    masks = input_dir.parent / "masks"  # where ingest_photos put the photos' transparency, if any
    infos = {name: photo_info(input_dir / name) for name in names}
    cameras = camera_groups(infos, names, options.camera_mode)
    matcher, matcher_reason = choose_matcher([infos[name] for name in names], options, ordered)
    tree_words = check_vocab_tree(options) if matcher in ("sequential", "vocabtree") else 0
    mapper, mapper_reason = choose_mapper(len(names), options)
    runner.say(f"{'matcher':<12} {matcher}: {matcher_reason}")
    runner.say(f"{'mapper':<12} {mapper}: {mapper_reason}")
    sizes = feature_sizes(infos, cameras, options.max_image_size)
    pycolmap.logging.minloglevel = 2  # COLMAP's INFO/WARNING lines would drown the progress lines
    features_key = stage_key(input_key, options.camera_model, options.camera_params, options.camera_mode,
                             options.max_features, sizes)
    features = runner.run("features", features_key, lambda report: _extract(database, input_dir, cameras, sizes,
                                                                            masks, options, report),
                          unit="photos", describe=_describe_features)
    vocab = None if options.vocab_tree is None else (str(options.vocab_tree.expanduser().resolve()), tree_words)
    matching_key = stage_key(features_key, matcher, options.neighbors if matcher != "exhaustive" else None, vocab,
                             options.seed)
    matched = runner.run("matching", matching_key, lambda report: match(database, matcher, options, work, matching_key,
                                                                        report, runner.say),
                         unit="pairs", describe=lambda done: _describe_matching(done, len(names)))
    key = stage_key(matching_key, mapper, options.seed)

    def mapping(report: Report) -> dict[str, Any]:
        return map_with_fallback(lambda chosen: _map(database, input_dir, work, chosen, options, report), mapper,
                                 options.mapper == "auto", runner.say)

    mapped = runner.run("mapping", key, mapping, unit="photos", describe=_describe_mapping)
    model_dir = work / "sparse" / str(mapped["model"])
    key = stage_key(key, options.keep_below_px)
    undistorted = runner.run("undistort", key, lambda report: undistort(model_dir, input_dir, masks, out, report,
                                                                        options.keep_below_px), unit="photos")
    key = stage_key(key, list(options.downscales))
    runner.run("downscale", key, lambda report: _downscale(out, options.downscales, report), unit="photos")
    summary = _summary(database, names, pycolmap.Reconstruction(str(model_dir)), options)
    summary.update(matcher=matcher, matcher_reason=matcher_reason, mapper=mapped["mapper"],
                   mapper_reason=mapper_reason, feature_long_sides=features["long_sides"], pairs=matched["pairs"],
                   verified_pairs=matched["verified"], undistortion=undistorted["cameras"])
    return summary


def _describe_features(summary: dict[str, Any]) -> str:
    sides = sorted(set(summary["long_sides"]))
    return (f"{summary['photos']} photos read at a {'/'.join(map(str, sides))} px long side, "
            f"{summary['cameras']} camera(s), {summary['keypoints']:,} keypoints")


def _describe_matching(summary: dict[str, Any], photos: int) -> str:
    return (f"{summary['matcher']}: {summary['pairs']:,} pairs ({summary['pairs'] / max(1, photos):.1f} a photo), "
            f"{summary['verified']:,} with verified matches")


def _describe_mapping(summary: dict[str, Any]) -> str:
    return (f"{summary['mapper']}: {summary['registered']} of {summary['images']} photos registered "
            f"({summary['models']} model(s))")


def camera_groups(infos: dict[str, PhotoInfo], names: list[str], mode: CameraMode) -> list[list[str]]:
    """The photos each COLMAP camera holds: one group per distinct (size, EXIF make, model, focal
    length) for ``auto``, else as ``mode`` says. A forced mode whose camera would hold photos of
    different sizes is refused here, before any feature is extracted (a camera has one size)."""
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


def _extract(database: Path, input_dir: Path, cameras: list[list[str]], sizes: list[int], masks: Path,
             options: SfmOptions, report: Report) -> dict[str, Any]:
    database.parent.mkdir(parents=True, exist_ok=True)
    database.unlink(missing_ok=True)  # a half-written database from a crash is not resumable
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = options.camera_model
    reader.camera_params = options.camera_params
    if masks.is_dir():
        reader.mask_path = str(masks)  # no features where a photo was transparent
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.num_threads = options.num_threads
    extraction.sift.max_num_features = options.max_features
    total = sum(len(group) for group in cameras)
    done = 0
    report(done, total)
    for group, size in zip(cameras, sizes):
        extraction.max_image_size = size
        # Each group's first call adds one camera for its photos; the calls after it add theirs to it.
        reader.existing_camera_id = -1
        for start in range(0, len(group), EXTRACT_CHUNK):
            chunk = group[start:start + EXTRACT_CHUNK]
            pycolmap.extract_features(database, input_dir, image_names=chunk, camera_mode=pycolmap.CameraMode.SINGLE,
                                      reader_options=reader, extraction_options=extraction, device=pycolmap.Device.cpu)
            if reader.existing_camera_id == -1:
                with pycolmap.Database.open(database) as db:
                    reader.existing_camera_id = db.read_image_with_name(chunk[0]).camera_id
            done += len(chunk)
            report(done, total)
    with pycolmap.Database.open(database) as db:
        keypoints = db.num_keypoints()
    return {"photos": total, "cameras": len(cameras), "long_sides": sizes, "keypoints": keypoints}


def _map(database: Path, input_dir: Path, work: Path, mapper: str, options: SfmOptions,
         report: Report) -> dict[str, Any]:
    sparse, calibrated = work / "sparse", work / "calibrated.db"
    if sparse.exists():
        shutil.rmtree(sparse)
    sparse.mkdir(parents=True)
    calibrated.unlink(missing_ok=True)
    with pycolmap.Database.open(database) as db:
        total = db.num_images()
        guessed_focal = not all(camera.has_prior_focal_length for camera in db.read_all_cameras())
    report(0, total)
    if mapper == "incremental":
        pipeline = pycolmap.IncrementalPipelineOptions()
        pipeline.num_threads = options.num_threads
        pipeline.random_seed = options.seed
        registered = [0]

        def next_image() -> None:
            registered[0] += 1
            report(min(registered[0], total), total)

        models = pycolmap.incremental_mapping(database, input_dir, sparse, pipeline, next_image_callback=next_image)
    elif mapper == "global":
        pipeline = pycolmap.GlobalPipelineOptions()
        pipeline.num_threads = options.num_threads
        pipeline.random_seed = options.seed
        if guessed_focal:
            # The global mapper needs good focal lengths (COLMAP's FAQ): without EXIF ones, they are first
            # estimated from the verified pairs' fundamental matrices, on a copy (it rewrites the database).
            shutil.copyfile(database, calibrated)
            calibration = pycolmap.ViewGraphCalibrationOptions()
            calibration.random_seed = options.seed
            pycolmap.calibrate_view_graph(calibrated, calibration)
            database = calibrated
        models = pycolmap.global_mapping(database, input_dir, sparse, pipeline)
        calibrated.unlink(missing_ok=True)
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
    report(registered, total)
    if registered < max(3, options.min_registered * total):
        raise HicoError(
            f"{input_dir}: only {registered} of {total} images registered (expected at least "
            f"{max(3, int(np.ceil(options.min_registered * total)))}, --min-registered {options.min_registered}); "
            "the photos need more overlap and texture, or try --matcher exhaustive / another --mapper"
        )
    # every model is written under sparse/<i> by the pipelines; make sure the chosen one is on disk
    models[best].write_binary(str(sparse / str(best)))
    return {"model": int(best), "models": len(models), "mapper": mapper, "registered": registered, "images": total}


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
        "camera_model": options.camera_model,
    }


def print_summary(summary: dict[str, Any], out: Path, timings: dict[str, float], reused: list[str],
                  echo: Callable[[str], None] = print) -> None:
    echo(f"registered {summary['registered']} of {summary['images']} images "
         f"({summary['cameras']} camera(s), {summary['camera_model']}, {summary['matcher']} matching of "
         f"{summary['pairs']:,} pairs, "
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
