"""The viewer on a real Trainer run (the engine's toy model made viewable): live stats and plot,
pause / resume and checkpoint from the viewer, renders under the trainer's lock."""

from __future__ import annotations

import threading
import time

import numpy as np
import torch
from helpers_toy_model import ToyDataset, ToyModel, render_blobs
from helpers_viewer import ProtocolClient, wait_for

from hico_plugin.engine import TrainerConfig
from hico_plugin.viewer import ViewerConfig, attach_viewer
from hico_plugin.visualization import RenderOptions


class ViewableToy(ToyModel):
    """The engine's toy with the two ViewableModel methods."""

    def render_for_display(self, camera, options: RenderOptions):
        self.lock_held_during_render.append(self.trainer_lock._is_owned())
        return {"rgb": render_blobs(self.features, self.centers, self.mlp, camera, self.sigma)}

    def viewer_anchors(self):
        positions = torch.cat([self.centers.detach(), torch.zeros(len(self.centers), 1)], dim=-1)
        return positions, torch.arange(len(self.centers)) % 2


def test_viewer_follows_and_controls_a_training_run(tmp_path):
    dataset = ToyDataset(num_views=12, size=8, seed=0)
    model = ViewableToy(num_blobs=6, size=8, seed=3, densify_every=10**9, densify_until=0)
    config = TrainerConfig(output_dir=tmp_path / "run", max_steps=10**6, save_every=0, eval_every=0,
                           progress="none", vis="none", device="cpu")
    trainer = config.setup(model=model, dataset=dataset)
    model.trainer_lock, model.lock_held_during_render = trainer.lock, []
    viewer = attach_viewer(trainer, ViewerConfig(port=0, refresh_seconds=0.1, settle_seconds=0.05, max_resolution=64))
    result: list = []
    training = threading.Thread(target=lambda: result.append(trainer.train()))
    client = ProtocolClient(viewer.port)
    try:
        training.start()
        client.send_camera((0.0, 1.0, 0.0, 0.0), (0.0, 0.0, 2.0))
        assert wait_for(lambda: viewer.render_count >= 2 and trainer.step > 20)
        assert all(model.lock_held_during_render)  # every render ran under the trainer's lock
        assert wait_for(lambda: "| step |" in viewer.gui.stats_text.content and viewer.stats.plot is not None)
        assert "loss" in viewer.stats.plot_names and not viewer.gui.pause.disabled

        viewer.toggle_pause()
        assert trainer.is_paused and viewer.gui.pause.label == "Resume training"
        time.sleep(0.2)  # a step in flight may still finish
        paused_at = trainer.step
        time.sleep(0.3)
        assert trainer.step == paused_at
        viewer.toggle_pause()
        assert not trainer.is_paused
        assert wait_for(lambda: trainer.step > paused_at)

        viewer.request_checkpoint(None)
        assert wait_for(lambda: any((tmp_path / "run" / "checkpoints").glob("*.ckpt")))
    finally:
        trainer.request_stop()
        training.join(timeout=60)
        client.close()
        viewer.stop()
    assert result and result[0].interrupted
    assert not viewer.state.is_training
    assert np.isfinite(viewer.state.history()["loss"]).all()
