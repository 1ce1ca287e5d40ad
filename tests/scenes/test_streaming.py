"""The scene generator streams its views to disk: the sparse points sampled in chunks and the surface
samples merged as they come equal the all-at-once results, and memory does not grow with the views."""

from __future__ import annotations

import tracemalloc

import numpy as np

from hico_plugin.scenes import generate as gen
from hico_plugin.scenes.generate import scene_config
from hico_plugin.scenes.render import render_view
from hico_plugin.scenes.sparse import FeatureSampler


def _sample(scene, images, depths, chunk_elements, max_track):
    sampler = FeatureSampler(scene.viewmats, scene.K, 200, 0.002, 0, max_track=max_track,
                             chunk_elements=chunk_elements)
    for view, (image, depth) in enumerate(zip(images, depths)):
        sampler.propose(view, image, depth)
    return sampler.finish(lambda views: depths[views], lambda view: images[view])


def test_sparse_points_do_not_depend_on_the_chunking():
    scene = scene_config("tiny").setup("tiny")
    cfg = scene.config
    views = [render_view(scene.caster, viewmat, scene.K, scene.width, scene.height, scene.sun, cfg.ambient,
                         cfg.shadows) for viewmat in scene.viewmats]
    images = np.stack([np.round(np.clip(view.rgb, 0, 1) * 255).astype(np.uint8) for view in views])
    depths = np.stack([view.depth.astype(np.float32) for view in views])
    for max_track in (3, 5):
        whole = _sample(scene, images, depths, 1 << 30, max_track)
        for chunk_elements in (1, 500):  # a view at a time; a few views, a few rows of draws at a time
            chunked = _sample(scene, images, depths, chunk_elements, max_track)
            for name in ("xyz", "rgb", "obs_point", "obs_image", "obs_pixel"):
                np.testing.assert_array_equal(getattr(chunked, name), getattr(whole, name))
        tracks = np.bincount(whole.obs_point)
        assert len(whole.xyz) == 200 and tracks.min() >= 2 and tracks.max() == max_track


def test_surface_samples_merged_as_they_come_keep_the_first_per_voxel():
    rng = np.random.default_rng(0)
    batches = [rng.uniform(0, 3, (int(rng.integers(1, 400)), 3)) for _ in range(40)]
    keys = gen._voxel_keys(np.concatenate(batches), 0.25)
    _, first = np.unique(keys, return_index=True)  # one point per voxel, the first seen
    expected = np.concatenate(batches)[first].astype(np.float32)
    for merge_at in (1, 1000, 1 << 30):
        samples = gen._SurfaceSamples(0.25, merge_at=merge_at)
        for batch in batches:
            samples.add(batch)
        np.testing.assert_array_equal(samples.points(), expected)


def _peak_bytes(tmp_path, num_views):
    scene = scene_config("tiny", num_views=num_views, width=128, height=96, sparse_points=50).setup("tiny")
    tracemalloc.start()
    try:
        gen.write_scene(scene, tmp_path / f"tiny-{num_views}")
        return tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()


def test_memory_does_not_grow_with_the_number_of_views(tmp_path, monkeypatch):
    # buffers small against the views' images, so that holding every view would show
    monkeypatch.setattr(gen, "SURFACE_BUFFER", 4096)
    monkeypatch.setattr(gen, "VISIBILITY_CHUNK", 1 << 14)
    few, many = _peak_bytes(tmp_path, 12), _peak_bytes(tmp_path, 192)
    every_view = 192 * 128 * 96 * (3 + 4)  # the images and depth maps of all views together
    assert many - few < 0.25 * every_view, (few, many, every_view)
