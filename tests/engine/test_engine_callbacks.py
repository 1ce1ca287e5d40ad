"""Progress bar, metrics summary and optional TensorBoard."""

import importlib.util
import io

import pytest

from hico_plugin.engine import TrainerConfig
from hico_plugin.engine.callbacks import ProgressBar, format_bar_metrics
from hico_plugin.engine.evaluation import summarize
from hico_plugin.errors import HicoError
from helpers_toy_model import ToyDataConfig, ToyModelConfig


def test_bar_summary_shows_loss_terms_psnr_and_counts():
    text = format_bar_metrics({"loss": 0.0123, "psnr": 24.56, "num_anchors": 12345.0,
                               "num_gaussians": 98765.0, "loss/rgb": 0.01, "lr/mlp": 0.1})
    assert text == "loss 0.0123 | psnr 24.56 | anchors 12,345 | gaussians 98,765 | rgb 0.01"


def test_progress_bar_renders_step_speed_and_metrics():
    stream = io.StringIO()
    bar = ProgressBar(max_steps=10, stream=stream)
    bar.on_train_start(trainer=None, step=0)
    bar.on_step_end(4, {"loss": 0.5, "psnr": 20.0, "it_per_s": 3.0, "num_anchors": 7.0})
    bar.on_eval(4, {"psnr": 21.5})
    bar.on_train_end(4)
    output = stream.getvalue()
    for expected in ("5/10", "3.00 it/s", "psnr 20", "anchors 7", "test PSNR 21.50 dB"):
        assert expected in output, expected


def test_summarize_mean_std_and_unavailable():
    results = summarize([{"psnr": 20.0, "lpips": None, "rgb": [1, 2]}, {"psnr": 22.0, "lpips": None}])
    assert results == {"psnr": 21.0, "psnr_std": 1.0, "lpips": None, "lpips_std": None}


@pytest.mark.skipif(importlib.util.find_spec("tensorboard") is not None, reason="tensorboard is installed")
def test_tensorboard_without_the_package_is_a_clear_error(tmp_path):
    config = TrainerConfig(output_dir=tmp_path / "run", data=ToyDataConfig(), model=ToyModelConfig(),
                           device="cpu", progress="none", vis="tensorboard")
    with pytest.raises(HicoError, match="config.vis: 'tensorboard' needs the tensorboard package"):
        config.setup()


def test_progress_lines_print_the_expected_wall_time_from_the_first_steps():
    import io

    from hico_plugin.engine.callbacks import ProgressLines

    now = [0.0]
    out = io.StringIO()
    lines = ProgressLines(max_steps=100, timed_steps=5, every_seconds=30.0, stream=out, clock=lambda: now[0])
    lines.on_train_start(None, 0)
    now[0] = 10.0  # step 1: one-off costs, left out of the estimate
    lines.on_step_end(0, {"loss": 0.5})
    for step in range(1, 100):
        now[0] += 2.0
        lines.on_step_end(step, {"loss": 0.5})
    text = out.getvalue()
    # 10 s + 99 steps x 2 s = 3:28 expected, known after step 6
    assert "expected wall time 3:28 (2.00 s/step over steps 2-6;" in text
    assert "step 100/100" in text and text.count("\nstep ") >= 6

    # Timed on coarse images (the resolution schedule), the estimate says it is low.
    coarse = io.StringIO()
    lines = ProgressLines(max_steps=100, timed_steps=5, every_seconds=30.0, stream=coarse, clock=lambda: now[0])
    lines.on_train_start(None, 0)
    for step in range(10):
        now[0] += 2.0
        lines.on_step_end(step, {"loss": 0.5, "resolution_scale": 0.5})
    assert "over steps 2-6, images at 0.50 of full size: later steps cost more;" in coarse.getvalue()
