"""``hico-analyze RUN [RUN...] [--output-dir DIR]``: the paper's cross-level feature analysis of trained
runs (cosine-distance matrix, adjacent-level distances, per-pair PCA, t-SNE); with several runs also
a side-by-side comparison (e.g. an octree-gs run next to a hico-gs run)."""

from __future__ import annotations

import sys
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import tyro

import hico_plugin.presets  # noqa: F401  (loads the config classes a config.yml may name)
from hico_plugin.cli import run_cli
from hico_plugin.errors import HicoError


@dataclass
class AnalyzeArgs:
    runs: tyro.conf.Positional[tuple[Path, ...]]
    """Training run directories (each with config.yml and checkpoints/)."""
    output_dir: Path = Path("analysis_out")
    """Where the per-run folders (run_0_<method>, ...) and the comparison go."""
    per_level: int = 3000
    """Anchors per level in each per-pair PCA (the paper's 3,000)."""
    tsne: bool = True
    """Run t-SNE (needs scikit-learn)."""
    tsne_per_level: int = 300
    """Anchors per level in the stratified t-SNE sample."""
    seed: int = 0
    """Seed of the subsampling and of t-SNE."""


def analyze(args: AnalyzeArgs) -> None:
    from hico_plugin.bench.run_features_report import analyze_run, compare_runs
    from hico_plugin.field.lookup_stats import format_table

    if not args.runs:
        raise HicoError("hico-analyze: expected at least one training run directory")
    documents = []
    for number, run in enumerate(args.runs):
        doc = analyze_run(run, args.output_dir / f"run_{number}_{Path(run).name}", args.per_level,
                          args.tsne_per_level, args.tsne, args.seed)
        documents.append(doc)
        adjacent = ", ".join("–" if v is None else f"{v:.3f}" for v in doc["f"]["adjacent"])
        print(f"{run} ({doc['method']}): anchors per level {doc['anchors_per_level']}; d(l, l+1) of f: {adjacent}")
        if doc["f_hat"] is not None:
            adjacent = ", ".join("–" if v is None else f"{v:.3f}" for v in doc["f_hat"]["adjacent"])
            print(f"  after CLCA (f̂): {adjacent}")
        print(f"  CLCA lookup per level over the test views ({doc['method']}):")
        print("    " + format_table(doc["lookup"]).replace("\n", "\n    "))
    if len(documents) > 1:
        compare_runs(documents, args.output_dir)
    print(f"analysis: {args.output_dir}")


def entrypoint(argv: Sequence[str] | None = None) -> None:
    run_cli(lambda: analyze(tyro.cli(AnalyzeArgs, args=sys.argv[1:] if argv is None else argv, prog="hico-analyze")))
