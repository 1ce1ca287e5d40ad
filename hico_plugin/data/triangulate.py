"""Seed points triangulated from known poses (COLMAP's point triangulator, through pycolmap 4).

For posed image sets without a point cloud (transforms.json without ``ply_file_path``, Mega-NeRF): SIFT on the
CPU, matching of the pairs the poses say overlap (``pose_pairs``), then ``pycolmap.triangulate_points`` with the
given cameras and poses fixed. Cached in ``storage.cache_dir("triangulation")``, keyed by every input, never in the
dataset folder; pycolmap is imported only on a cache miss.
"""

from __future__ import annotations

import hashlib
import json
import shutil
import sys
import tempfile
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from hico_plugin.data.camera_model import Camera, camera_centres
from hico_plugin.data.checks import image_header_size
from hico_plugin.data.images import MAX_LONG_SIDE
from hico_plugin.storage import atomic_path, cache_dir

if TYPE_CHECKING:
    import pycolmap

MIN_POINTS = 100
"""Fewer triangulated points than this and the caller falls back to random points."""
POSE_NEIGHBOURS = 20
"""Cameras each image is matched with: the nearest by centre among those looking its way. Every pair
of instant-ngp's fox (50 photos, 1,225 pairs) took 56 s to match and gave 13,466 points; each
photo's 20 nearest within 90 degrees about 33 s and 13,344 points (the whole triangulation 69 s
against 93). A set of 150 photos has 11,175 pairs, about 8 minutes of matching on two cores; with 20
neighbours at most 3,000. (COLMAP's spatial matcher chooses by centre alone, 50 by default.)"""
POSE_MAX_ANGLE = 90.0
"""Degrees between two optical axes beyond which a pair is not matched: cameras facing apart rarely
share a surface, and a camera turning in place would otherwise pair with the views behind it. Aerial
orbits share their ground at wide angles: a 12-view city-block twin triangulated 52 points from the
pairs within 45 degrees, 139 within 90 and 147 from every pair."""
PAIR_BLOCK = 256
"""Images whose distances to every other are held at once while choosing pairs."""
MAX_FEATURES = 4096
MAX_IMAGE_SIZE = MAX_LONG_SIDE
"""Longest side, in pixels, SIFT reads a photo at. Below it, photos are read at the size training loads
them: features finer than a training pixel do not place a seed point better for that training, and
SIFT's time grows with the pixels (instant-ngp's fox, 50 photos of 1920x1080 trained at 960x540: 30 s
instead of 74 to extract, 56 s instead of 74 to match every pair)."""
CACHE_VERSION = 2  # bump when the output for the same inputs changes


def triangulate_known_poses(data_dir: Path, names: list[str], camera_ids: list[int],
                            cameras: dict[int, Camera], viewmats: np.ndarray, long_side: int = MAX_IMAGE_SIZE,
                            num_threads: int = -1) -> tuple[np.ndarray, np.ndarray]:
    """Points seen by the images ``data_dir/names[i]`` from the known cameras.

    names: [N] image paths relative to ``data_dir``; camera_ids: [N] keys of ``cameras`` (any COLMAP
    model, distortion included); viewmats: [N, 4, 4] world->camera, OpenCV axes; long_side: the
    longest image side, in pixels, features are extracted at (at most ``MAX_IMAGE_SIZE``).
    Returns points [P, 3] float64 in the world frame of ``viewmats`` and colours [P, 3] uint8 (P may
    be 0 when nothing matches)."""
    long_side = min(long_side, MAX_IMAGE_SIZE)
    key = _cache_key(data_dir, names, camera_ids, cameras, viewmats, long_side)
    cached = cache_dir("triangulation") / f"{key}.npz"
    if cached.is_file():
        try:
            with np.load(cached, allow_pickle=False) as data:
                return data["points"], data["colors"]
        except (OSError, ValueError, KeyError):
            pass  # a damaged cache entry is recomputed
    print(f"triangulating seed points from the {len(names)} known poses (SIFT + matching on the CPU; "
          f"cached in {cached.parent})", file=sys.stderr)
    cached.parent.mkdir(parents=True, exist_ok=True)
    work = Path(tempfile.mkdtemp(prefix=f".{key}-", dir=cached.parent))
    try:
        points, colors = _triangulate(data_dir, names, camera_ids, cameras, viewmats, work, long_side, num_threads)
        with atomic_path(cached) as partial:  # a crash never leaves a half-written entry
            np.savez(partial, points=points, colors=colors)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    return points, colors


def _triangulate(data_dir: Path, names: list[str], camera_ids: list[int], cameras: dict[int, Camera],
                 viewmats: np.ndarray, work: Path, long_side: int, num_threads: int) -> tuple[np.ndarray, np.ndarray]:
    import pycolmap

    database = work / "database.db"
    pycolmap.logging.minloglevel = 2  # COLMAP's INFO lines would drown the training log
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.num_threads = num_threads
    extraction.max_image_size = long_side
    extraction.sift.max_num_features = MAX_FEATURES
    # COLMAP's pair list splits a line at spaces and skips lines starting with '#'; names it cannot
    # hold are paired by COLMAP's spatial matcher on the camera centres instead (no angle limit).
    listable = not any(name.startswith("#") or any(c.isspace() for c in name) for name in names)
    centres = camera_centres(viewmats)
    reconstruction = pycolmap.Reconstruction()
    # Each image enters the database with its known camera (at its file's size, where keypoints live)
    # before any feature is extracted, in the order of ``names``: the extractor would number images in
    # the order its threads finish them, and these numbers decide the order the triangulator visits
    # images in and which image of a pair RANSAC verifies from, so the same photos gave other points
    # each run.
    with pycolmap.Database.open(database) as db:
        for i, (name, camera_id) in enumerate(zip(names, camera_ids)):
            camera, image, frame_id = _register_image(db, name, _file_camera(cameras[camera_id], data_dir / name))
            reconstruction.add_camera_with_trivial_rig(camera)
            reconstruction.add_image_with_trivial_frame(image, pycolmap.Rigid3d(viewmats[i, :3, :4]))
            if not listable:
                prior = pycolmap.PosePrior(position=centres[i],
                                           coordinate_system=pycolmap.PosePriorCoordinateSystem.CARTESIAN)
                prior.corr_data_id = pycolmap.data_t(pycolmap.sensor_t(pycolmap.SensorType.CAMERA, camera.camera_id),
                                                     frame_id)
                db.write_pose_prior(prior)
    pycolmap.extract_features(database, data_dir, image_names=names, camera_mode=pycolmap.CameraMode.PER_IMAGE,
                              extraction_options=extraction, device=pycolmap.Device.cpu)
    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = num_threads
    verification = pycolmap.TwoViewGeometryOptions()
    verification.ransac.random_seed = 0  # RANSAC seeded per pair: a pair's inliers do not depend on its thread
    if listable:
        pair_list = work / "pairs.txt"
        pair_list.write_text("".join(f"{names[i]} {names[j]}\n" for i, j in pose_pairs(viewmats)))
        pairing = pycolmap.ImportedPairingOptions()
        pairing.match_list_path = pair_list
        pycolmap.match_image_pairs(database, matching_options=matching, pairing_options=pairing,
                                   verification_options=verification, device=pycolmap.Device.cpu)
    else:
        pairing = pycolmap.SpatialPairingOptions()
        pairing.ignore_z = False
        pairing.max_num_neighbors = POSE_NEIGHBOURS
        pairing.max_distance = float("inf")  # the scene's units are unknown; the neighbour count bounds it
        pycolmap.match_spatial(database, matching_options=matching, pairing_options=pairing,
                               verification_options=verification, device=pycolmap.Device.cpu)
    options = pycolmap.IncrementalPipelineOptions()
    # One thread and a seeded RANSAC: same matches, same points. With two threads, fresh runs on
    # instant-ngp's fox (50 photos) gave 13,373 or 13,380 points even with bundle adjustment on one
    # thread; on one thread the step takes about 2 s more of the 36 the whole triangulation takes.
    options.num_threads = 1
    options.random_seed = 0
    result = pycolmap.triangulate_points(reconstruction, database, data_dir, work / "model", options=options)
    ordered = [result.points3D[i] for i in sorted(result.points3D)]
    if not ordered:
        return np.zeros((0, 3)), np.zeros((0, 3), dtype=np.uint8)
    return (np.array([p.xyz for p in ordered], dtype=np.float64),
            np.array([p.color for p in ordered], dtype=np.uint8))


def _file_camera(camera: Camera, path: Path) -> Camera:
    """``camera`` rescaled to the size of the image file at ``path`` (an exact downscale of it)."""
    scaled = replace(camera)
    scaled.rescale(*image_header_size(path, "image"))
    return scaled


def _register_image(db: pycolmap.Database, name: str, camera: Camera) -> tuple[pycolmap.Camera, pycolmap.Image, int]:
    """Writes ``camera``, its one-camera rig, the image ``name`` and its frame into ``db``, as COLMAP's
    feature extractor writes a photo it has not seen (camera mode PER_IMAGE). Returns the camera and
    image with their database ids, and the frame's id."""
    import pycolmap

    written = camera.to_pycolmap()
    written.camera_id = db.write_camera(written)
    sensor = pycolmap.sensor_t(pycolmap.SensorType.CAMERA, written.camera_id)
    rig = pycolmap.Rig()
    rig.add_ref_sensor(sensor)
    image = pycolmap.Image(name=name, camera_id=written.camera_id)
    image.image_id = db.write_image(image)
    frame = pycolmap.Frame()
    frame.rig_id = db.write_rig(rig)
    frame.add_data_id(pycolmap.data_t(sensor, image.image_id))
    return written, image, db.write_frame(frame)


def pose_pairs(viewmats: np.ndarray, neighbours: int = POSE_NEIGHBOURS,
               max_angle: float = POSE_MAX_ANGLE) -> list[tuple[int, int]]:
    """Image pairs (i < j) worth matching, from the poses alone: each image with its ``neighbours``
    nearest cameras by centre among those whose optical axis is within ``max_angle`` degrees of its
    own, as hloc's ``pairs_from_poses`` chooses them. viewmats: [N, 4, 4] world->camera, OpenCV axes."""
    centres = camera_centres(viewmats)
    axes = viewmats[:, 2, :3] / np.linalg.norm(viewmats[:, 2, :3], axis=1, keepdims=True)  # viewing directions
    pairs = set()
    for start in range(0, len(viewmats), PAIR_BLOCK):  # [block, N] at a time: thousands of photos fit
        rows = slice(start, start + PAIR_BLOCK)
        distances = np.linalg.norm(centres[rows, None] - centres[None], axis=-1)
        distances[axes[rows] @ axes.T < np.cos(np.radians(max_angle))] = np.inf
        distances[np.arange(distances.shape[0]), np.arange(start, start + distances.shape[0])] = np.inf
        for i, row in enumerate(distances, start):
            for j in np.argsort(row, kind="stable")[:neighbours]:
                if np.isfinite(row[j]):
                    pairs.add((min(i, int(j)), max(i, int(j))))
    return sorted(pairs)


def _cache_key(data_dir: Path, names: list[str], camera_ids: list[int], cameras: dict[int, Camera],
               viewmats: np.ndarray, long_side: int) -> str:
    files = []
    for name in names:
        stat = (data_dir / name).stat()
        files.append([name, stat.st_size, stat.st_mtime_ns])
    source = json.dumps([
        CACHE_VERSION, MAX_FEATURES, long_side, POSE_NEIGHBOURS, POSE_MAX_ANGLE,
        str(data_dir.resolve()), files, camera_ids,
        [[cid, c.model, c.width, c.height, [round(float(v), 9) for v in c.params]] for cid, c in sorted(cameras.items())],
        np.round(viewmats, 9).tolist(),
    ])
    return hashlib.sha1(source.encode()).hexdigest()[:16]
