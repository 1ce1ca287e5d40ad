"""Distributed data parallel on 2 CPU processes (gloo, loopback): 2 workers x batch 1 (stopped after 7
steps and resumed) == 1 worker x batch 2."""

import os
import socket
from pathlib import Path

import pytest
import torch
import torch.multiprocessing as mp

from hico_plugin.engine import TrainerCallback, TrainerConfig, all_reduce_mean_, all_reduce_sum_, is_main_process
from hico_plugin.engine import distributed as dist_utils
from hico_plugin.engine.checkpoints import list_checkpoints, load_checkpoint
from helpers_toy_model import ToyDataConfig, ToyModelConfig

MAX_STEPS = 16  # densifies at steps 4, 9 and 14: parameter shapes change 3 times


def _config(output_dir: Path, batch_size: int, resume: bool = False, sparse_rows: bool = False) -> TrainerConfig:
    return TrainerConfig(
        output_dir=output_dir, data=ToyDataConfig(), model=ToyModelConfig(densify_until=MAX_STEPS, sparse_rows=sparse_rows),
        max_steps=MAX_STEPS, batch_size=batch_size, seed=5, device="cpu", save_every=8, eval_every=8,
        log_every=1, progress="none", vis="none", resume=resume,
        distributed_timeout_minutes=1.0,
    )


def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


class _StopAfter(TrainerCallback):
    """Asks to stop after step ``step``: it runs on rank 0 only, the stop reaches every rank."""

    def __init__(self, step):
        self.step, self.trainer = step, None

    def on_train_start(self, trainer, step):
        self.trainer = trainer

    def on_step_end(self, step, metrics):
        if step == self.step:
            self.trainer.request_stop()


def _worker(rank: int, world_size: int, port: int, output_dir: str, results_dir: str, sparse_rows: bool) -> None:
    os.environ.update(MASTER_ADDR="127.0.0.1", MASTER_PORT=str(port), RANK=str(rank),
                      WORLD_SIZE=str(world_size), LOCAL_RANK=str(rank))
    torch.set_num_threads(1)
    try:
        first = _config(Path(output_dir), batch_size=1, sparse_rows=sparse_rows).setup(callbacks=[_StopAfter(6)])
        # The collective helpers the model uses for its statistics.
        probe = torch.tensor([float(rank + 1)])
        assert all_reduce_sum_(probe.clone()).item() == 3.0
        assert all_reduce_mean_(probe.clone()).item() == 1.5
        assert is_main_process() == (rank == 0)
        stopped = first.train()
        assert stopped.interrupted and stopped.step == 7
        assert (stopped.checkpoint is not None) == (rank == 0)
        # Every rank resumes from rank 0's checkpoint, with its own RNG state.
        resumed = _config(Path(output_dir), batch_size=1, resume=True, sparse_rows=sparse_rows).setup()
        assert resumed.step == 7
        resumed.train()
        torch.save(resumed.model.state_dict(), Path(results_dir) / f"rank{rank}.pt")
    except BaseException:
        dist_utils.shutdown(wait_for_peers=False)
        raise
    dist_utils.shutdown()


def test_helpers_are_no_ops_on_one_process():
    tensor = torch.tensor([2.0, 4.0])
    assert all_reduce_sum_(tensor) is tensor and tensor.tolist() == [2.0, 4.0]
    assert all_reduce_mean_(tensor).tolist() == [2.0, 4.0]
    assert is_main_process() and dist_utils.get_world_size() == 1
    assert dist_utils.gather_objects("x") == ["x"]


@pytest.mark.skipif(not torch.distributed.is_gloo_available(), reason="torch built without gloo")
@pytest.mark.parametrize("sparse_rows", [False, True], ids=["dense", "row-sparse"])
def test_two_workers_batch_one_match_one_worker_batch_two(tmp_path, sparse_rows):
    """Row-sparse gradients too: the rows updated are those any worker's view touched, as one
    process's batch of both views touches them."""
    results_dir = tmp_path / "results"
    results_dir.mkdir()
    mp.spawn(_worker, args=(2, _free_port(), str(tmp_path / "ddp"), str(results_dir), sparse_rows), nprocs=2,
             join=True)

    single = _config(tmp_path / "single", batch_size=2, sparse_rows=sparse_rows).setup()
    single.train()
    reference = single.model.state_dict()
    rank0 = torch.load(results_dir / "rank0.pt")
    rank1 = torch.load(results_dir / "rank1.pt")
    assert reference["features"].shape[0] == 6 + 3
    for key in reference:
        torch.testing.assert_close(rank1[key], rank0[key], rtol=0, atol=0, msg=f"ranks differ: {key}")
        torch.testing.assert_close(rank0[key], reference[key], rtol=1e-5, atol=1e-5, msg=key)

    # Only rank 0 wrote files; its checkpoint holds the RNG state of both ranks.
    run = tmp_path / "ddp"
    assert {p.name for p in run.iterdir()} == {"config.yml", "metrics.jsonl", "checkpoints", "eval.json", ".lock"}
    payload = load_checkpoint(list_checkpoints(run / "checkpoints")[-1])
    assert payload["world_size"] == 2 and len(payload["rng"]) == 2
    lines = (run / "metrics.jsonl").read_text().splitlines()
    assert len([line for line in lines if '"loss"' in line]) == MAX_STEPS
