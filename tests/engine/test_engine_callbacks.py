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
    assert "over steps 2-6, images at 0.50 of full size, later steps weighed by their pixels;" in coarse.getvalue()


def test_a_slow_first_step_does_not_inflate_the_time_left():
    """A first run's first step holds the kernel builds (here 111 s against 0.125 s steps): the line it
    prints makes no estimate, and the next ones count the steps after it only."""
    import io

    from hico_plugin.engine.callbacks import ProgressLines

    now = [0.0]
    out = io.StringIO()
    lines = ProgressLines(max_steps=3500, timed_steps=5, every_seconds=60.0, stream=out, clock=lambda: now[0])
    lines.on_train_start(None, 0)
    now[0] = 111.0
    lines.on_step_end(0, {"loss": 0.5})
    for step in range(1, 3500):
        now[0] += 0.125
        lines.on_step_end(step, {"loss": 0.5})
    printed = out.getvalue().splitlines()
    first = next(line for line in printed if line.startswith("step 1/3500"))
    assert "1:51 elapsed, the first step, one-off setup included" in first and "~" not in first
    # 60 s after the first step: step 481, 3,019 steps of 0.125 s left
    assert any(line.startswith("step 481/3500  2:51 elapsed, ~6:17 left") for line in printed), printed
    assert "expected wall time 9:08 (0.12 s/step over steps 2-6;" in "\n".join(printed)
    assert printed[-1].startswith("step 3500/3500  9:08 elapsed, ~0:00 left")


def test_under_the_resolution_schedule_the_time_left_is_counted_in_full_steps():
    """A step whose time is a fixed part plus a part that follows its pixels (4 s at full size) is
    foreseen exactly from the first, quarter-size steps."""
    import io
    from types import SimpleNamespace

    import torch

    from hico_plugin.engine.callbacks import ProgressLines
    from hico_plugin.engine.resolution import FIXED_STEP_SHARE, ResolutionSchedule

    schedule = ResolutionSchedule(start_scale=0.25, min_long_side=0)
    trainer = SimpleNamespace(config=SimpleNamespace(resolution=schedule), dataset=SimpleNamespace(
        cameras=SimpleNamespace(widths=torch.tensor([960, 960]), heights=torch.tensor([540, 540]))))
    scales = [schedule.scale(step, 100, 960) for step in range(100)]
    cost = [4.0 * (FIXED_STEP_SHARE + (1 - FIXED_STEP_SHARE) * scale ** 2) for scale in scales]
    now = [0.0]
    out = io.StringIO()
    lines = ProgressLines(max_steps=100, timed_steps=5, every_seconds=1e9, stream=out, clock=lambda: now[0])
    lines.on_train_start(trainer, 0)
    for step in range(100):
        now[0] += cost[step]
        lines.on_step_end(step, {"loss": 0.5, "resolution_scale": scales[step]})
    total = sum(cost)
    assert scales[1] == 0.25  # timed on quarter-size images
    expected = [line for line in out.getvalue().splitlines() if "expected wall time" in line][0]
    assert f"expected wall time {round(total) // 60}:{round(total) % 60:02d} " in expected
    assert abs(schedule.full_steps(0, 100, 100, 960) - total / 4.0) < 1e-9
    assert ResolutionSchedule().full_steps(3, 10, 100, 960) == 7.0  # no schedule: every step full size
