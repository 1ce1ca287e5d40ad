"""``hico-bench [--presets ...] [--scenes ...] [--data DIR] [--budgets ...] [--quick] [--output-dir DIR]``
and ``hico-bench compare A B`` (two results.json files or bench output directories)."""

from __future__ import annotations

import sys
from collections.abc import Sequence
from pathlib import Path

import tyro

from hico_plugin.bench import (
    BenchConfig,
    compare_results,
    load_results,
    run_matrix,
    write_outputs,
)
from hico_plugin.cli import run_cli
from hico_plugin.errors import HicoError


def bench(config: BenchConfig) -> None:
    config = config.resolved()
    cells = run_matrix(config)
    write_outputs(config, cells, Path(config.output_dir))
    print(f"report: {Path(config.output_dir) / 'report.md'}")


def compare(args: Sequence[str]) -> None:
    if len(args) != 2 or any(a.startswith("-") for a in args):
        raise HicoError("usage: hico-bench compare A B (two results.json files or hico-bench output directories)")
    print(compare_results(load_results(args[0]), load_results(args[1]), args[0], args[1]), end="")


def main(argv: Sequence[str]) -> None:
    if argv and argv[0] == "compare":
        compare(argv[1:])
        return
    bench(tyro.cli(BenchConfig, args=list(argv), prog="hico-bench",
                   description="Benchmark presets x scenes x training budgets: accuracy vs time, "
                               "per-stage step time; writes results.json and report.md. "
                               "`hico-bench compare A B` compares two results."))


def entrypoint(argv: Sequence[str] | None = None) -> None:
    run_cli(lambda: main(sys.argv[1:] if argv is None else argv))
