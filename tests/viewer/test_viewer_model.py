"""The viewer on the real HiCoModel (built-in `tiny` scene): every output draws, and the server renders
a browser camera placed at a training view through the model."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
from helpers_viewer import ProtocolClient, wait_for

from hico_plugin.data.sources import DataSourceConfig
from hico_plugin.model import HiCoModelConfig
from hico_plugin.rasterizer.renderer import RendererConfig
from hico_plugin.viewer import RunViewerState, ViewableModel, ViewerConfig, camera_to_viser, model_render_fn
from hico_plugin.visualization import OUTPUT_NAMES, REQUIRED_OUTPUTS, RenderOptions, visualize


@pytest.fixture(scope="module")
def tiny_model():
    dataset = DataSourceConfig(scene="tiny").setup()
    model = HiCoModelConfig(renderer=RendererConfig(use_compile=False), eval_lpips="none").setup(dataset=dataset)
    return model.eval(), dataset


def test_every_output_of_the_real_model_draws(tiny_model):
    model, dataset = tiny_model
    assert isinstance(model, ViewableModel)
    camera = dataset.cameras[int(dataset.train_indices[0])].scaled(0.25)
    num_levels = int(model.viewer_anchors()[1].max()) + 1
    # One render with every output any view needs (the model reads only these four fields).
    everything = SimpleNamespace(required_outputs=tuple(sorted(set().union(*REQUIRED_OUTPUTS.values()))),
                                 clca_enabled=True, level_range=None, distance_scale=1.0)
    outputs = model.render_for_display(camera, everything)
    for name in OUTPUT_NAMES:
        image = visualize(outputs, RenderOptions(output=name, num_levels=num_levels))
        assert image.dtype == np.uint8 and image.shape == (camera.height, camera.width, 3), name
    without_clca = model_render_fn(model)(camera, RenderOptions(clca_enabled=False))
    assert without_clca.shape == (camera.height, camera.width, 3)


def test_server_renders_a_training_view_through_the_model(tiny_model):
    model, dataset = tiny_model
    viewer = ViewerConfig(port=0, max_resolution=96, settle_seconds=0.05).setup(
        render_fn=model_render_fn(model), state=RunViewerState(model, dataset)
    )
    client = ProtocolClient(viewer.port)
    try:
        camera = dataset.cameras[int(dataset.train_indices[0])]
        wxyz, position, fov_y, aspect = camera_to_viser(camera)
        client.send_camera(wxyz, position, fov=fov_y, width=round(300 * aspect), height=300)
        assert wait_for(lambda: viewer.render_count >= 1 and viewer.last_image.shape[1] == 96 or viewer.last_error is not None, 60)
        assert viewer.last_error is None
        assert viewer.last_image.std() > 1.0  # the scene, not a flat background
        assert viewer.scene.num_levels == int(model.viewer_anchors()[1].max()) + 1
    finally:
        client.close()
        viewer.stop()
