"""``hico-bench [full|quick] [--presets ...] [--scenes ...] [--data DIR] [--budgets ...] [--output-dir DIR]``
and ``hico-bench compare A B`` (two results.json files or bench output directories).

``full`` (the default) and ``quick`` are two sets of default settings; ``--quick`` anywhere on the line
is another spelling of ``quick``. The mode is chosen before parsing, so a typed flag always wins, even
one whose value equals the full default."""

from __future__ import annotations

import sys
from collections.abc import Sequence
from pathlib import Path

import tyro

from hico_plugin.bench import (
    BENCH_MODES,
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


def parse(argv: Sequence[str]) -> BenchConfig:
    """The benchmark config of a ``hico-bench`` command line (without ``compare``)."""
    args = list(argv)
    mode = args.pop(0) if args and args[0] in BENCH_MODES else "full"
    if "--quick" in args:
        args = [a for a in args if a != "--quick"]
        mode = "quick"
    return tyro.cli(BenchConfig, args=args, default=BENCH_MODES[mode], prog=f"hico-bench {mode}",
                    description=f"Benchmark presets x scenes x training budgets ({mode} defaults shown; "
                                f"modes: {', '.join(BENCH_MODES)}, --quick = quick): accuracy vs time, per-stage "
                                "step time; writes results.json and report.md. `hico-bench compare A B` "
                                "compares two results.")


def main(argv: Sequence[str]) -> None:
    if argv and argv[0] == "compare":
        compare(argv[1:])
        return
    bench(parse(argv))


def entrypoint(argv: Sequence[str] | None = None) -> None:
    run_cli(lambda: main(sys.argv[1:] if argv is None else argv))
