"""field.gather.take_rows: index_select's values and gradient for rows that never repeat."""

import torch

from hico_plugin.field.gather import take_rows


def _rows(count: int, seed: int) -> torch.Tensor:
    keep = torch.rand(count, generator=torch.Generator().manual_seed(seed)) < 0.6
    return keep.nonzero().squeeze(1)


def test_matches_index_select_values_and_gradients():
    source = torch.randn(40, 5, 3, requires_grad=True)
    rows = _rows(40, 0).flip(0)  # any order, each row once
    weights = torch.randn(rows.numel(), 5, 3)
    (take_rows(source, rows) * weights).sum().backward()
    got = source.grad.clone()
    source.grad = None
    (source.index_select(0, rows) * weights).sum().backward()
    assert torch.equal(take_rows(source, rows), source.index_select(0, rows))
    assert torch.equal(got, source.grad)


def test_gradcheck_float64():
    source = torch.randn(12, 4, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda s: take_rows(s, _rows(12, 1)), (source,))
    flat = torch.randn(9, dtype=torch.float64, requires_grad=True)  # a 1-D source (opacities)
    assert torch.autograd.gradcheck(lambda s: take_rows(s, _rows(9, 2)), (flat,))


def test_no_rows_and_rows_untouched_get_zero_gradient():
    source = torch.randn(6, 2, requires_grad=True)
    out = take_rows(source, torch.zeros(0, dtype=torch.long))
    assert out.shape == (0, 2)
    out.sum().backward()
    assert torch.equal(source.grad, torch.zeros(6, 2))


def test_source_without_grad_is_a_plain_gather():
    source = torch.randn(5, 3)
    out = take_rows(source, torch.tensor([4, 0]))
    assert not out.requires_grad and torch.equal(out, source[[4, 0]])


def test_nonfinite_gradients_reach_only_their_rows():
    source = torch.zeros(4, 1, requires_grad=True)
    out = take_rows(source, torch.tensor([2, 1]))
    out.backward(torch.tensor([[float("inf")], [float("nan")]]))
    assert source.grad[2, 0] == float("inf") and source.grad[1, 0].isnan()
    assert torch.equal(source.grad[[0, 3]], torch.zeros(2, 1))
