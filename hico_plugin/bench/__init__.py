"""Benchmarks and feature analysis: ``hico-bench`` (accuracy vs time) and ``hico-analyze``. Public API::

    BenchConfig(...).resolved() -> BenchConfig (BENCH_MODES: full / quick defaults); run_matrix(config, log=print) -> list[cell dict]
    write_outputs(config, cells, out_dir) -> results; load_results(path); compare_results(a, b) -> str
    StageTimer(device).attach(model, optimizers)   per-stage step time, as a context manager
    cross_level_distance(features, levels) -> [L, L]; analyze_run(run_dir, out_dir) -> dict
"""

from hico_plugin.bench.matrix import ABLATION_PRESETS, BENCH_MODES, BenchConfig, run_matrix
from hico_plugin.bench.report import (
    compare_results,
    load_results,
    pareto_front,
    write_outputs,
)
from hico_plugin.bench.stage_timer import STAGES, StageTimer

__all__ = [
    "ABLATION_PRESETS",
    "BENCH_MODES",
    "STAGES",
    "BenchConfig",
    "StageTimer",
    "compare_results",
    "load_results",
    "pareto_front",
    "run_matrix",
    "write_outputs",
]
