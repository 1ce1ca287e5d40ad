"""field.gather: take_rows (rows that never repeat) and repeat_rows (ascending rows that repeat) against
index_select's values and gradients."""

import pytest
import torch

from hico_plugin.field import gather
from hico_plugin.field.gather import repeat_rows, take_rows
from hico_plugin.row_sparse import sparse_rows
from helpers_native import require_kernel


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


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("shape", [(5, 3), (7,), ()])
def test_ascending_rows_are_placed_as_index_copy_places_them(dtype, shape):
    """Strictly ascending rows (the decoder's): the one-pass placement, bit for bit index_copy_'s, the
    first and last rows named, runs of unnamed rows between, -0, inf and NaN gradients kept as they are."""
    source = torch.randn(300, *shape, dtype=dtype, requires_grad=True)
    rows = torch.cat([torch.tensor([0]), _rows(298, 7) + 1, torch.tensor([299])])
    grad = torch.randn(rows.numel(), *shape, dtype=dtype)
    grad[1], grad[2], grad[3] = -0.0, float("inf"), float("nan")
    take_rows(source, rows).backward(grad)
    expected = torch.zeros(300, *shape, dtype=dtype).index_copy_(0, rows, grad)
    bits = torch.int64 if dtype == torch.float64 else torch.int32  # -0 and NaN compared as stored
    assert torch.equal(source.grad.view(-1).view(bits), expected.view(-1).view(bits))


def test_placement_is_independent_of_threads_and_falls_back_off_its_case():
    """1, 2, 3 threads (a thread with no named row, threads ending on one) give index_copy_'s table; rows
    that descend are index_copy_'s own case, and the kernel declines rows that repeat, descend or leave
    the source (status 1, nothing written)."""
    grad = torch.randn(40, 4)  # 16-byte rows: the kernel's (narrower rows stay with index_copy_)
    shape = torch.Size((120, 4))
    before = torch.get_num_threads()
    try:
        for rows in (torch.arange(40) * 3, torch.arange(40) + 80, torch.arange(40).flip(0)):
            expected = torch.zeros(shape).index_copy_(0, rows, grad)
            for threads in (1, 2, 3):
                torch.set_num_threads(threads)
                assert torch.equal(gather._placed_rows(grad, rows, shape), expected)
    finally:
        torch.set_num_threads(before)
    require_kernel(gather.KERNEL)
    lib = gather.KERNEL.get()
    for rows, status in ((torch.arange(40) * 3, 0), (torch.arange(40).flip(0), 1), (torch.tensor([5] * 40), 1),
                         (torch.arange(40) + 81, 1), (torch.arange(40) - 1, 1)):
        out = torch.full(shape, 7.0)
        got = lib.hico_place_rows(gather.pointer(grad), gather.pointer(rows), 40, 16, 120, gather.pointer(out), 2)
        assert got == status
        assert torch.equal(out, torch.zeros(shape).index_copy_(0, rows, grad) if status == 0 else torch.full(shape, 7.0))


def _children(count: int, k: int, seed: int) -> torch.Tensor:
    """The anchor of every kept child, as the decoder forms it: ascending, each anchor 0..k times."""
    keep = torch.rand(count, k, generator=torch.Generator().manual_seed(seed)) < 0.6
    return keep.nonzero(as_tuple=True)[0]


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("shape", [(6,), (3,), ()])
def test_repeat_rows_equals_index_select_bit_for_bit(dtype, shape):
    source = torch.randn(300, *shape, dtype=dtype, requires_grad=True)
    rows = _children(300, 5, 3)
    assert rows.diff().eq(0).any() and rows.diff().ge(0).all()  # repeats, ascending
    weights = torch.randn(rows.numel(), *shape, dtype=dtype)
    out = repeat_rows(source, rows)
    (out * weights).sum().backward()
    got = source.grad.clone()
    source.grad = None
    (source.index_select(0, rows) * weights).sum().backward()
    assert torch.equal(out, source.index_select(0, rows))
    assert torch.equal(got, source.grad)


def test_repeat_rows_gradcheck_float64():
    source = torch.randn(10, 3, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda s: repeat_rows(s, _children(10, 4, 4)), (source,))


def test_repeat_rows_out_of_order_falls_back_to_index_add():
    """Rows that do not ascend (or lie outside the source) are not the kernel's case: index_add_ sums them."""
    source = torch.randn(5, 2, requires_grad=True)
    rows = torch.tensor([3, 1, 3, 0])
    repeat_rows(source, rows).backward(torch.ones(4, 2))
    assert torch.equal(source.grad, torch.tensor([[1.0, 1.0], [1.0, 1.0], [0.0, 0.0], [2.0, 2.0], [0.0, 0.0]]))


def test_repeat_rows_hard_cases():
    """No rows; every row on one anchor; non-finite gradients stay on their anchor; any thread count."""
    source = torch.randn(4, 3, requires_grad=True)
    repeat_rows(source, torch.zeros(0, dtype=torch.long)).sum().backward()
    assert torch.equal(source.grad, torch.zeros(4, 3))
    source.grad = None
    repeat_rows(source, torch.full((7,), 2)).backward(torch.ones(7, 3))
    assert torch.equal(source.grad[2], torch.full((3,), 7.0)) and source.grad[[0, 1, 3]].eq(0).all()
    source.grad = None
    grad = torch.zeros(3, 3)
    grad[1, 0] = float("inf")
    repeat_rows(source, torch.tensor([0, 1, 1])).backward(grad)
    assert source.grad[1, 0] == float("inf") and source.grad[[0, 2, 3]].eq(0).all()
    grad = torch.randn(5000, 3)
    rows = _children(1000, 5, 5)[:5000]
    before = torch.get_num_threads()
    try:
        sums = []
        for threads in (1, 2, 3):
            torch.set_num_threads(threads)
            sums.append(gather._row_sums(grad[: rows.numel()], rows, 1000))
    finally:
        torch.set_num_threads(before)
    assert torch.equal(sums[0], sums[1]) and torch.equal(sums[0], sums[2])
    assert torch.equal(sums[0], torch.zeros(1000, 3).index_add_(0, rows, grad[: rows.numel()]))



@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("shape", [(40, 5, 3), (40,)])
def test_sparse_gradient_names_only_the_rows_and_equals_the_dense_one(shape, dtype):
    """The dense gradient (gradchecked above) bit for bit, laid out as the rows it names."""
    source = torch.randn(*shape, dtype=dtype, requires_grad=True)
    for rows in (_rows(40, 3), _rows(40, 4).flip(0), torch.zeros(0, dtype=torch.long)):
        weights = torch.randn(rows.numel(), *shape[1:], dtype=dtype)
        source.grad = None
        (take_rows(source, rows, sparse_grad=True) * weights).sum().backward()
        sparse = source.grad
        assert sparse.is_sparse and sparse.shape == source.shape
        assert sparse._nnz() == rows.numel()
        named, values = sparse_rows(sparse)
        assert torch.equal(named, rows.sort().values) and values.shape == (rows.numel(), *shape[1:])
        source.grad = None
        (take_rows(source, rows) * weights).sum().backward()
        assert torch.equal(sparse.to_dense(), source.grad)


def test_sparse_gradients_of_two_gathers_add_up():
    """A batch of two views gathers overlapping rows; the gradients accumulate to the dense sum."""
    source = torch.randn(30, 4, requires_grad=True)
    first, second = _rows(30, 5), _rows(30, 6)
    w1, w2 = torch.randn(first.numel(), 4), torch.randn(second.numel(), 4)
    ((take_rows(source, first, True) * w1).sum() + (take_rows(source, second, True) * w2).sum()).backward()
    sparse = source.grad
    source.grad = None
    ((take_rows(source, first) * w1).sum() + (take_rows(source, second) * w2).sum()).backward()
    assert torch.equal(sparse.to_dense(), source.grad)
    assert torch.equal(sparse_rows(sparse)[0], torch.cat([first, second]).unique())

