"""engine.adam.Adam: torch.optim.Adam(fused=True)'s parameters bit for bit, its state_dict layout both ways, and
no torch._dynamo import."""

import copy
import subprocess
import sys

import torch
from torch import nn

from hico_plugin.engine.adam import Adam


def _params(seed: int) -> list[nn.Parameter]:
    generator = torch.Generator().manual_seed(seed)
    return [nn.Parameter(torch.randn(5, 3, generator=generator)), nn.Parameter(torch.randn(4, generator=generator)),
            nn.Parameter(torch.randn(2, generator=generator))]


def _train(optimizer, params: list[nn.Parameter], steps: range) -> None:
    """Steps with seeded gradients, a changing lr and the last parameter without a gradient until step 3."""
    for step in steps:
        generator = torch.Generator().manual_seed(100 + step)
        optimizer.zero_grad()
        for i, param in enumerate(params):
            if i < 2 or step >= 3:
                param.grad = torch.randn(param.shape, generator=generator)
        optimizer.param_groups[0]["lr"] = 0.01 / (1 + step)
        optimizer.step()


def test_same_parameters_and_state_as_torch_fused_adam():
    ours, theirs = _params(0), _params(0)
    mine = Adam(ours, lr=0.01, eps=1e-15)
    torch_adam = torch.optim.Adam(theirs, lr=0.01, eps=1e-15, fused=True)
    _train(mine, ours, range(6))
    _train(torch_adam, theirs, range(6))
    for a, b in zip(ours, theirs):
        assert torch.equal(a, b)
    mine_state, torch_state = mine.state_dict(), torch_adam.state_dict()
    assert mine_state["param_groups"] == torch_state["param_groups"]
    for index, state in torch_state["state"].items():
        for key, value in state.items():
            assert torch.equal(mine_state["state"][index][key], value) and mine_state["state"][index][key].dtype == value.dtype


def test_state_dict_moves_both_ways():
    start = _params(1)
    torch_adam = torch.optim.Adam(start, lr=0.01, eps=1e-15, fused=True)
    _train(torch_adam, start, range(4))
    # torch -> ours -> torch, each continuing where the other stopped, against torch alone
    ours = [nn.Parameter(p.detach().clone()) for p in start]
    mine = Adam(ours, lr=0.0, eps=1e-15)
    mine.load_state_dict(copy.deepcopy(torch_adam.state_dict()))  # as read from a file
    _train(mine, ours, range(4, 6))
    back = [nn.Parameter(p.detach().clone()) for p in ours]
    torch_again = torch.optim.Adam(back, lr=0.0, eps=1e-15, fused=True)
    torch_again.load_state_dict(copy.deepcopy(mine.state_dict()))
    _train(torch_again, back, range(6, 8))
    _train(torch_adam, start, range(4, 8))
    for a, b in zip(back, start):
        assert torch.equal(a, b)


def test_does_not_import_dynamo():
    code = ("import sys, torch\nfrom hico_plugin.engine.adam import Adam\n"
            "p = torch.nn.Parameter(torch.ones(3)); adam = Adam([p], lr=0.1)\n"
            "p.grad = torch.ones(3); adam.step(); adam.zero_grad(); adam.load_state_dict(adam.state_dict())\n"
            "print('torch._dynamo' in sys.modules)")
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert result.stdout.strip() == "False"


def test_continues_a_default_torch_adam_state_to_float32_rounding():
    """A checkpoint written with torch's default (single-tensor) Adam resumes here; the fused kernel
    differs from that implementation only by float32 rounding."""
    start = _params(2)
    torch_adam = torch.optim.Adam(start, lr=0.01, eps=1e-15)
    _train(torch_adam, start, range(4))
    ours = [nn.Parameter(p.detach().clone()) for p in start]
    mine = Adam(ours, lr=0.0, eps=1e-15)
    mine.load_state_dict(copy.deepcopy(torch_adam.state_dict()))
    _train(mine, ours, range(4, 8))
    _train(torch_adam, start, range(4, 8))
    for a, b in zip(ours, start):
        torch.testing.assert_close(a, b, rtol=1e-6, atol=1e-6)


def test_row_sparse_gradient_updates_its_rows_as_the_dense_update_and_no_other():
    """Rows a sparse gradient names take the dense update (the global step's bias correction; to float32
    rounding, as the fused kernel's vector and scalar lanes may differ); every other row and its
    moments stay exactly as they were (Taming 3DGS's sparse Adam)."""
    generator = torch.Generator().manual_seed(4)
    dense_param = nn.Parameter(torch.randn(10, 2, 3, generator=generator))
    sparse_param = nn.Parameter(dense_param.detach().clone())
    dense, sparse = Adam([dense_param], lr=0.01, eps=1e-15), Adam([sparse_param], lr=0.01, eps=1e-15)
    for step in range(4):  # every row touched: the two agree exactly
        grad = torch.randn(10, 2, 3, generator=generator)
        dense_param.grad, sparse_param.grad = grad.clone(), grad.to_sparse(1)
        dense.step()
        sparse.step()
    assert torch.equal(dense_param, sparse_param)
    rows = torch.tensor([1, 4, 7])
    before = sparse_param.detach().clone()
    moments = {k: v.clone() for k, v in sparse.state[sparse_param].items()}
    grad = torch.randn(3, 2, 3, generator=generator)
    full = torch.zeros(10, 2, 3).index_copy_(0, rows, grad)
    dense_param.grad = full
    sparse_param.grad = torch.sparse_coo_tensor(rows[None], grad, (10, 2, 3))
    dense.step()
    sparse.step()
    torch.testing.assert_close(sparse_param[rows], dense_param[rows], rtol=1e-6, atol=0)
    untouched = torch.tensor([0, 2, 3, 5, 6, 8, 9])
    assert torch.equal(sparse_param[untouched], before[untouched])
    state = sparse.state[sparse_param]
    for key in ("exp_avg", "exp_avg_sq"):
        assert torch.equal(state[key][untouched], moments[key][untouched])
        torch.testing.assert_close(state[key][rows], dense.state[dense_param][key][rows], rtol=1e-6, atol=0)
    assert float(state["step"]) == 5.0
