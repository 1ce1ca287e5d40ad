"""Optimizers: LR schedules, Adam state following resized rows, state dict round trips."""

import copy
import math

import pytest
import torch
from torch import nn

from hico_plugin.engine.optimizers import ADAM_EPS, Optimizers
from hico_plugin.engine.schedule import LRSchedule
from hico_plugin.errors import HicoError

BETA1, BETA2 = 0.9, 0.999


def test_schedule_log_linear_then_held():
    schedule = LRSchedule(1e-2, 1e-4, max_steps=100)
    assert schedule.lr(0) == pytest.approx(1e-2)
    assert schedule.lr(50) == pytest.approx(1e-3)  # geometric midpoint
    assert schedule.lr(100) == pytest.approx(1e-4)
    assert schedule.lr(1000) == pytest.approx(1e-4)
    assert LRSchedule(0.0075).lr(12345) == 0.0075  # constant
    assert LRSchedule(0.0, 1e-6, max_steps=10).lr(5) == 0.0  # frozen group


def test_schedule_warmup_then_decay():
    schedule = LRSchedule(1e-2, 1e-3, max_steps=110, warmup_steps=10, lr_pre_warmup=0.0)
    assert schedule.lr(0) == 0.0
    assert schedule.lr(5) == pytest.approx(5e-3)
    assert schedule.lr(10) == pytest.approx(1e-2)
    assert schedule.lr(60) == pytest.approx(math.sqrt(1e-2 * 1e-3))
    assert schedule.lr(110) == pytest.approx(1e-3)


def _adam_step_by_hand(param, grad, m, v, t, lr):
    m = BETA1 * m + (1 - BETA1) * grad
    v = BETA2 * v + (1 - BETA2) * grad**2
    m_hat = m / (1 - BETA1**t)
    v_hat = v / (1 - BETA2**t)
    return param - lr * m_hat / (v_hat.sqrt() + ADAM_EPS), m, v


def test_resize_group_carries_kept_rows_and_zeros_new_rows():
    torch.manual_seed(0)
    rows = nn.Parameter(torch.randn(4, 2, dtype=torch.float64))
    other = nn.Parameter(torch.randn(3, dtype=torch.float64))
    optimizers = Optimizers({"rows": [rows], "other": [other]},
                            {"rows": LRSchedule(0.1), "other": LRSchedule(0.2)})
    grad1 = torch.randn(4, 2, dtype=torch.float64)
    rows.grad = grad1.clone()
    other.grad = torch.ones(3, dtype=torch.float64)
    expected, m, v = _adam_step_by_hand(rows.detach().clone(), grad1, torch.zeros_like(grad1), torch.zeros_like(grad1), 1, 0.1)
    optimizers.step(0)
    torch.testing.assert_close(rows.detach(), expected)

    kept = torch.tensor([3, 0, 2])
    resized = nn.Parameter(torch.cat([rows.detach()[kept], torch.full((2, 2), 5.0, dtype=torch.float64)]))
    optimizers.resize_group("rows", [resized], kept, num_new=2)
    state = optimizers.optimizers["rows"].state[resized]
    torch.testing.assert_close(state["exp_avg"], torch.cat([m[kept], torch.zeros(2, 2, dtype=torch.float64)]))
    torch.testing.assert_close(state["exp_avg_sq"], torch.cat([v[kept], torch.zeros(2, 2, dtype=torch.float64)]))
    assert float(state["step"]) == 1.0
    assert optimizers.params("rows") == [resized]

    # The next step uses the carried moments for kept rows, fresh ones for new rows, and t = 2.
    grad2 = torch.randn(5, 2, dtype=torch.float64)
    resized.grad = grad2.clone()
    m_full = torch.cat([m[kept], torch.zeros(2, 2, dtype=torch.float64)])
    v_full = torch.cat([v[kept], torch.zeros(2, 2, dtype=torch.float64)])
    expected2, _, _ = _adam_step_by_hand(resized.detach().clone(), grad2, m_full, v_full, 2, 0.1)
    optimizers.step(1)
    torch.testing.assert_close(resized.detach(), expected2)


def test_resize_rejects_wrong_shapes():
    rows = nn.Parameter(torch.zeros(4, 2))
    optimizers = Optimizers({"rows": [rows]}, {"rows": LRSchedule(0.1)})
    with pytest.raises(ValueError, match="expected"):
        optimizers.resize_group("rows", [nn.Parameter(torch.zeros(4, 2))], torch.tensor([0, 1]), 1)


def test_missing_schedule_is_a_clear_error():
    with pytest.raises(HicoError, match="no schedule for parameter group"):
        Optimizers({"rows": [nn.Parameter(torch.zeros(1))]}, {})


def test_state_dict_round_trip_after_resize():
    torch.manual_seed(1)

    def make(rows):
        return Optimizers({"rows": [rows]}, {"rows": LRSchedule(0.05, 0.005, max_steps=10)})

    rows = nn.Parameter(torch.randn(5, 3))
    optimizers = make(rows)
    for step in range(3):
        rows.grad = torch.randn_like(rows)
        optimizers.step(step)
    kept = torch.tensor([0, 2, 4])
    rows = nn.Parameter(torch.cat([rows.detach()[kept], torch.zeros(1, 3)]))
    optimizers.resize_group("rows", [rows], kept, 1)
    saved = copy.deepcopy(optimizers.state_dict())  # as if read back from a checkpoint file

    restored_rows = nn.Parameter(rows.detach().clone())
    restored = make(restored_rows)
    restored.load_state_dict(saved)
    grad = torch.randn_like(rows)
    rows.grad, restored_rows.grad = grad.clone(), grad.clone()
    optimizers.step(3)
    restored.step(3)
    torch.testing.assert_close(restored_rows.detach(), rows.detach(), rtol=0, atol=0)
