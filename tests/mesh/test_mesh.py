"""Mesh extraction and surface metrics: TSDF fusion of the tiny scene's exact depth maps recovers its
surface, bad depth gives a clear error, cleaning drops floaters, the depth filter rejects wrong depth."""

from __future__ import annotations

import importlib.util
import shutil
from types import SimpleNamespace

import numpy as np
import pycolmap
import pytest
import torch

from hico_plugin.data import DataParserConfig
from hico_plugin.errors import HicoError
from hico_plugin.mesh import (
    MeshExportConfig,
    TriangleMesh,
    clean_mesh,
    evaluate_surface,
    extract_mesh,
    fuse_tsdf,
    multiview_depth_filter,
    read_ply,
    sample_surface,
    surface_results,
    write_ply,
)
from hico_plugin.mesh.extract import scene_extent
from hico_plugin.mesh.mesh import face_components
from hico_plugin.metrics.geometry import gt_spacing_threshold
from hico_plugin.rasterizer.base import RenderOutputs
from hico_plugin.scenes.generate import generate_scene

needs_open3d = pytest.mark.skipif(importlib.util.find_spec("open3d") is None,
                                  reason="open3d not installed (pip install 'hico_plugin[mesh]')")


@pytest.fixture(autouse=True)
def one_thread():
    """Small tensors: on the shared 2-core machine torch's second thread only adds spin-waiting."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    # 160 x 120 views: at the default 64 x 48 the ground seen at grazing angles is too coarsely sampled
    # for a surface within tau = 1.5 x the ground-truth spacing.
    root = generate_scene("tiny", tmp_path_factory.mktemp("scene") / "tiny", width=160, height=120)
    return DataParserConfig(data=root, test_every=0).setup()


@pytest.fixture(scope="module")
def tiny_turned(tiny, tmp_path_factory):
    """The tiny scene in another COLMAP frame: turned by a random rotation, moved and scaled x1000
    (cameras, sparse points, ground-truth surface and depths alike; camera-space normals unchanged)."""
    source, turned = tiny.data_dir, tmp_path_factory.mktemp("turned") / "tiny"
    shutil.copytree(source / "images", turned / "images")
    shutil.copytree(source / "ground_truth" / "normal", turned / "ground_truth" / "normal")
    q, _ = np.linalg.qr(np.random.default_rng(3).normal(size=(3, 3)))
    rotation, shift, scale = q * np.sign(np.linalg.det(q)), np.array([40.0, -25.0, 7.0]), 1000.0
    model = pycolmap.Reconstruction(str(source / "sparse" / "0"))
    model.transform(pycolmap.Sim3d(scale, pycolmap.Rotation3d(rotation), shift))
    (turned / "sparse" / "0").mkdir(parents=True)
    model.write_binary(str(turned / "sparse" / "0"))
    surface = np.load(source / "ground_truth" / "surface_points.npy")
    np.save(turned / "ground_truth" / "surface_points.npy", scale * surface @ rotation.T + shift)
    (turned / "ground_truth" / "depth").mkdir()
    for depth in (source / "ground_truth" / "depth").glob("*.npy"):
        np.save(turned / "ground_truth" / "depth" / depth.name, scale * np.load(depth))
    return DataParserConfig(data=turned, test_every=0).setup()


def _gt_maps(dataset):
    views = range(len(dataset))
    return [dataset.gt_depth(i)[..., 0] for i in views], [dataset.image(i) for i in views]


def _grid_mesh(n: int, offset=(0.0, 0.0, 0.0), size: float = 1.0) -> TriangleMesh:
    """An n x n quad grid in the z = 0 plane (2 n^2 triangles), shifted by ``offset``."""
    ticks = np.linspace(0, size, n + 1)
    xs, ys = np.meshgrid(ticks, ticks, indexing="ij")
    vertices = np.stack([xs.ravel(), ys.ravel(), np.zeros(xs.size)], 1) + np.asarray(offset)
    ids = np.arange((n + 1) ** 2).reshape(n + 1, n + 1)
    a, b, c, d = ids[:-1, :-1].ravel(), ids[1:, :-1].ravel(), ids[1:, 1:].ravel(), ids[:-1, 1:].ravel()
    return TriangleMesh(vertices, np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)]))


@needs_open3d
def test_fusing_exact_depth_recovers_the_surface(tiny):
    depths, colors = _gt_maps(tiny)
    voxel = scene_extent(tiny) / 256
    mesh = clean_mesh(fuse_tsdf(depths, colors, tiny.cameras, voxel, 4 * voxel, 10.0), 100)
    assert len(mesh.faces) > 1000 and mesh.vertex_colors is not None
    metrics = evaluate_surface(mesh, tiny.gt_surface_points)
    assert metrics.f1 > 0.9 and metrics.precision > 0.9 and metrics.recall > 0.9, metrics
    # Coloured from the images: the mesh is not one flat colour.
    assert mesh.vertex_colors.astype(float).std(axis=0).min() > 5


@needs_open3d
def test_empty_or_far_depth_is_a_clear_error(tiny):
    depths, colors = _gt_maps(tiny)
    for bad in ([torch.zeros_like(d) for d in depths], [torch.full_like(d, float("nan")) for d in depths],
                [d + 100.0 for d in depths]):
        with pytest.raises(HicoError, match="no pixel in any of the 12 depth maps .*max_depth"):
            fuse_tsdf(bad, colors, tiny.cameras, 0.02, 0.08, max_depth=10.0)
    with pytest.raises(HicoError, match="voxel_size must be a positive"):
        fuse_tsdf(depths, colors, tiny.cameras, 0.0, 0.08, 10.0)
    with pytest.raises(HicoError, match="view 0: expected depth"):
        fuse_tsdf([d[:-1] for d in depths], colors, tiny.cameras, 0.02, 0.08, 10.0)


class _ExactDepthModel:
    """Stands in for a trained model: renders the scene's exact depth and images."""

    def __init__(self, dataset):
        self.dataset = dataset

    def render(self, camera, outputs, step=None):
        assert step is None  # full LOD
        depth = self.dataset.gt_depth(camera.index)
        rgb = self.dataset.image(camera.index).float() / 255
        return RenderOutputs(rgb=rgb, alpha=torch.ones_like(depth), depth=depth, plane_depth=depth), None


@needs_open3d
def test_extract_mesh_writes_a_colmap_frame_ply(tiny, tmp_path):
    config = MeshExportConfig(voxel_size=scene_extent(tiny) / 256 / tiny.transform.scale, depth_filter=True,
                              min_component_triangles=100)
    mesh = extract_mesh(_ExactDepthModel(tiny), tiny, config)
    path = write_ply(tmp_path / "out" / "mesh.ply", mesh)
    again = read_ply(path)
    assert again.faces.shape == mesh.faces.shape and np.allclose(again.vertices, mesh.vertices, atol=1e-5)
    assert np.array_equal(again.vertex_colors, mesh.vertex_colors)
    # Ground truth as stored on disk is in the COLMAP frame, like the mesh.
    gt_colmap = tiny.transform.points_to_colmap(tiny.gt_surface_points.double())
    metrics = evaluate_surface(again, gt_colmap)
    assert metrics.f1 > 0.9, metrics
    assert not list(path.parent.glob(".*tmp"))  # atomic write left no temporary file
    # hico-eval's entries: the same protocol on the file.
    results = surface_results(tiny, path)
    assert set(results) == {"surface_precision", "surface_recall", "surface_f1", "surface_chamfer", "surface_tau"}
    assert results["surface_tau"] == pytest.approx(gt_spacing_threshold(tiny.transform.points_to_colmap(
        tiny.gt_surface_points.double())))
    assert results["surface_f1"] == pytest.approx(metrics.f1)
    assert surface_results(tiny, tmp_path / "missing.ply") == {}


@needs_open3d
def test_extract_mesh_with_nothing_drawn_is_a_clear_error(tiny):
    class Empty(_ExactDepthModel):
        def render(self, camera, outputs, step=None):
            out, _ = super().render(camera, outputs, step)
            out.alpha = torch.zeros_like(out.alpha)  # nothing opaque: every depth is discarded
            return out, None

    with pytest.raises(HicoError, match="no pixel of the 10 training views reaches opacity --min-alpha 0.5"):
        extract_mesh(Empty(tiny), DataParserConfig(data=tiny.data_dir).setup(), MeshExportConfig())
    with pytest.raises(HicoError, match=r"has a plane depth in \(0, --max-depth 0.001\] \(COLMAP units\)"):
        extract_mesh(_ExactDepthModel(tiny), tiny, MeshExportConfig(max_depth=1e-3))


def test_clean_mesh_drops_a_small_floating_blob():
    surface = _grid_mesh(20)  # 800 triangles
    blob = _grid_mesh(2, offset=(5.0, 5.0, 5.0), size=0.1)  # 8 triangles, disconnected
    degenerate = np.array([[0, 0, 1]])  # repeated vertex
    mesh = TriangleMesh(np.concatenate([surface.vertices, blob.vertices]),
                        np.concatenate([surface.faces, blob.faces + len(surface.vertices), degenerate]))
    cleaned = clean_mesh(mesh, min_component_triangles=100)
    assert len(cleaned.faces) == 800 and len(cleaned.vertices) == len(surface.vertices)
    assert cleaned.vertices[:, 0].max() <= 1.0 + 1e-12
    assert len(clean_mesh(mesh, 1).faces) == 808  # only the degenerate triangle goes


def test_face_components_match_scipy_connected_components():
    """Random triangles over few vertices (components of every size) and a shuffled 2,000-triangle strip
    (one component, 1,000 hops long): the same partition as scipy's, numbered by lowest vertex id."""
    csgraph = pytest.importorskip("scipy.sparse.csgraph")
    sparse = pytest.importorskip("scipy.sparse")
    rng = np.random.default_rng(0)
    strip = 3000 + np.arange(2000)[:, None] + np.arange(3)
    faces = np.concatenate([rng.integers(0, 3000, (1200, 3)), strip[rng.permutation(2000)]])
    mesh = TriangleMesh(np.zeros((5002, 3)), faces)
    labels = face_components(mesh)
    size = len(faces) + len(mesh.vertices)
    graph = sparse.coo_matrix((np.ones(3 * len(faces)), (np.repeat(np.arange(len(faces)), 3),
                                                         len(faces) + faces.reshape(-1))), shape=(size, size))
    expected = csgraph.connected_components(graph, directed=False)[1][:len(faces)]
    count = len(np.unique(expected))
    assert labels.max() + 1 == count and len(np.unique(np.stack([labels, expected]), axis=1).T) == count
    assert len(np.unique(labels[1200:])) == 1
    lowest = [faces[labels == label].min() for label in range(count)]
    assert (np.diff(lowest) > 0).all()


def test_sampling_is_area_weighted_and_a_perfect_mesh_scores_one():
    big, small = [[0, 0, 0], [3, 0, 0], [0, 1, 0]], [[10, 0, 0], [11, 0, 0], [10, 1, 0]]
    mesh = TriangleMesh(np.array(big + small, dtype=float), np.array([[0, 1, 2], [3, 4, 5]]))
    samples = sample_surface(mesh, 40_000, seed=1)
    assert abs((samples[:, 0] >= 10).mean() - 0.25) < 0.01
    inside_big = samples[samples[:, 0] < 10]
    assert (inside_big[:, 0] / 3 + inside_big[:, 1] <= 1 + 1e-9).all()  # inside the triangle
    plane = _grid_mesh(10)
    ticks = np.linspace(0, 1, 201)
    gt = np.stack(np.meshgrid(ticks, ticks, [0.0], indexing="ij"), -1).reshape(-1, 3)
    # Enough samples that they are denser than tau (the default N_vertices + N_faces assumes a fine mesh).
    metrics = evaluate_surface(plane, gt, num_samples=100_000)
    assert metrics.f1 == pytest.approx(1.0, abs=1e-3) and metrics.threshold == pytest.approx(1.5 * 0.005)
    shifted = evaluate_surface(TriangleMesh(plane.vertices + [0, 0, 0.05], plane.faces), gt, num_samples=10_000)
    assert shifted.f1 == 0.0 and shifted.chamfer == pytest.approx(0.05, rel=0.05)
    with pytest.raises(HicoError, match="no area"):
        evaluate_surface(TriangleMesh(np.zeros((3, 3)), np.array([[0, 1, 2]])), gt)


def test_depth_filter_keeps_consistent_depth_and_rejects_wrong_depth(tiny):
    depths = torch.stack(_gt_maps(tiny)[0])
    keep = multiview_depth_filter(depths, tiny.cameras, num_neighbours=6, min_consistent=2)
    valid = depths > 0
    assert not bool((keep & ~valid).any())
    assert keep.sum() > 0.7 * valid.sum()
    corrupted = depths.clone()
    corrupted[0] *= 1.1  # view 0 is 10% too far everywhere: no neighbour confirms it
    keep_bad = multiview_depth_filter(corrupted, tiny.cameras, num_neighbours=6, min_consistent=2)
    assert keep_bad[0].sum() < 0.05 * valid[0].sum()
    assert keep_bad[1:].sum() > 0.6 * valid[1:].sum()
    with pytest.raises(HicoError, match="at least 2 views"):
        multiview_depth_filter(depths[:1], _one_camera(tiny.cameras))


def _one_camera(cameras):
    return type(cameras)(cameras.viewmats[:1], cameras.Ks[:1], cameras.widths[:1], cameras.heights[:1])


def test_ply_round_trip_and_unreadable_file(tmp_path):
    mesh = _grid_mesh(3)
    mesh.vertex_colors = np.arange(len(mesh.vertices) * 3).reshape(-1, 3).astype(np.uint8)
    again = read_ply(write_ply(tmp_path / "m.ply", mesh))
    assert np.array_equal(again.faces, mesh.faces) and np.array_equal(again.vertex_colors, mesh.vertex_colors)
    (tmp_path / "bad.ply").write_bytes(b"not a mesh")
    with pytest.raises(HicoError, match="bad.ply"):
        read_ply(tmp_path / "bad.ply")
    with pytest.raises(HicoError, match="not found"):
        read_ply(tmp_path / "missing.ply")


def test_voxel_size_follows_the_scene_not_the_axes(tiny, tiny_turned):
    """The default voxel (scene extent / 512) and tau are the same in normalised units whatever the
    COLMAP frame: in COLMAP units both scale with the scene (x1000) and ignore its rotation and shift."""
    assert scene_extent(tiny_turned) == pytest.approx(scene_extent(tiny), rel=1e-6)
    points = tiny.points.to(torch.float64)
    # the extent is a diameter of the points, not of one box: turning them about +z changes nothing
    turn = torch.tensor([[0.6, -0.8, 0.0], [0.8, 0.6, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    spun = SimpleNamespace(points=(points @ turn.T).float(), cameras=tiny.cameras)
    assert scene_extent(spun) == pytest.approx(scene_extent(tiny), rel=1e-6)
    tau = gt_spacing_threshold(tiny.transform.points_to_colmap(tiny.gt_surface_points.double()))
    tau_turned = gt_spacing_threshold(tiny_turned.transform.points_to_colmap(tiny_turned.gt_surface_points.double()))
    assert tau_turned == pytest.approx(1000 * tau, rel=1e-4)


@needs_open3d
def test_mesh_f1_is_the_same_in_a_turned_moved_and_scaled_frame(tiny, tiny_turned, tmp_path):
    """Meshing the same depth maps in two COLMAP frames related by a similarity (random rotation, shift,
    x1000) scores the same against each frame's ground truth: fusion, voxel size and tau follow the scene.
    (The normalised frames differ by a turn about +z, so the TSDF grids cut the surface differently;
    what is left is that sampling difference.)"""
    config = MeshExportConfig(min_component_triangles=100)
    scores = []
    for dataset, name in ((tiny, "a"), (tiny_turned, "b")):
        path = write_ply(tmp_path / name / "mesh.ply", extract_mesh(_ExactDepthModel(dataset), dataset, config))
        scores.append(surface_results(dataset, path))
    original, turned = scores
    # exact depths: precision ~1.0; recall 0.79 since tiny loads upright with its faces along the
    # voxel grid (it was 0.9+ while tiny loaded tilted half a degree; an open question of the fusion)
    assert original["surface_f1"] > 0.85 and original["surface_precision"] > 0.99, original
    assert turned["surface_tau"] == pytest.approx(1000 * original["surface_tau"], rel=1e-4)
    assert turned["surface_chamfer"] == pytest.approx(1000 * original["surface_chamfer"], rel=0.05)
    for key in ("surface_f1", "surface_precision", "surface_recall"):
        assert turned[key] == pytest.approx(original[key], abs=0.01), (key, original, turned)
