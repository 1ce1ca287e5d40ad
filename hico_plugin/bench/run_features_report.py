"""``hico-analyze`` outputs: analysis.json and PNGs per run, and a side-by-side comparison of runs."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from hico_plugin.bench.run_features import analyze_features, run_features, stratified_sample
from hico_plugin.storage import write_text_atomic


def _pyplot():
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return None
    return plt


def tsne_embedding(features: Tensor, levels: Tensor, per_level: int, seed: int) -> tuple[Tensor, Tensor] | None:
    """2-D t-SNE (perplexity 30, 1000 iterations) of a stratified sample; None without scikit-learn."""
    try:
        from sklearn.manifold import TSNE
    except ImportError:
        return None
    ids = stratified_sample(levels, per_level, torch.Generator().manual_seed(seed))
    if len(ids) < 5:
        return None
    tsne = TSNE(n_components=2, perplexity=min(30.0, (len(ids) - 1) / 3), init="pca", random_state=seed)
    return torch.from_numpy(tsne.fit_transform(features[ids].double().numpy())).float(), levels[ids]



def _plot_matrices(plt, numbers: dict[str, Any], title: str, path: Path) -> None:
    kinds = [k for k in ("f", "f_hat") if numbers[k] is not None]
    fig, axes = plt.subplots(1, len(kinds), figsize=(4.5 * len(kinds), 4), squeeze=False)
    for ax, kind in zip(axes[0], kinds):
        matrix = torch.tensor([[float("nan") if v is None else v for v in row] for row in numbers[kind]["distance"]])
        image = ax.imshow(matrix.numpy(), vmin=0, vmax=max(1.0, float(matrix.nan_to_num(0).max())), cmap="viridis")
        for (i, j), value in zip(torch.cartesian_prod(torch.arange(len(matrix)), torch.arange(len(matrix))).tolist(),
                                 matrix.flatten().tolist()):
            ax.text(j, i, f"{value:.2f}", ha="center", va="center", fontsize=7, color="w")
        ax.set(title=f"{title}: d(la, lb) of {'f̂ (after CLCA)' if kind == 'f_hat' else 'f'}",
               xlabel="level", ylabel="level")
        fig.colorbar(image, ax=ax, fraction=0.046)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def _plot_adjacent(plt, series: dict[str, list[float | None]], path: Path, title: str) -> None:
    fig, ax = plt.subplots(figsize=(6, 3.5))
    width = 0.8 / max(len(series), 1)
    for k, (label, values) in enumerate(series.items()):
        xs = [i + k * width for i in range(len(values))]
        ax.bar(xs, [float("nan") if v is None else v for v in values], width, label=label)
    pairs = max(len(v) for v in series.values())
    ax.set_xticks([i + width * (len(series) - 1) / 2 for i in range(pairs)], [f"L{i}-L{i + 1}" for i in range(pairs)])
    ax.set(ylabel="cosine distance d(l, l+1)", title=title)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def _plot_pca(plt, numbers: dict[str, Any], path: Path) -> None:
    kinds = [k for k in ("f", "f_hat") if numbers[k] is not None]
    pairs = len(numbers["f"]["_pca"])
    if pairs == 0:
        return
    fig, axes = plt.subplots(len(kinds), pairs, figsize=(3 * pairs, 3 * len(kinds)), squeeze=False)
    for row, kind in enumerate(kinds):
        for col, pca in enumerate(numbers[kind]["_pca"]):
            ax = axes[row][col]
            if pca is None:
                ax.axis("off")
                continue
            for level in (col, col + 1):
                pts = pca["projection"][pca["levels"] == level]
                ax.scatter(pts[:, 0], pts[:, 1], s=3, alpha=0.5, label=f"L{level}")
            ax.set_title(f"{kind} L{col}-L{col + 1}\ncos {pca['cos_sim']:.3f}, PC1 {100 * pca['explained'][0]:.1f}%",
                         fontsize=8)
            ax.legend(fontsize=6)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def _plot_tsne(plt, embeddings: dict[str, tuple[Tensor, Tensor]], path: Path) -> None:
    fig, axes = plt.subplots(1, len(embeddings), figsize=(4.5 * len(embeddings), 4), squeeze=False)
    for ax, (kind, (points, levels)) in zip(axes[0], embeddings.items()):
        scatter = ax.scatter(points[:, 0], points[:, 1], c=levels.numpy(), cmap="coolwarm", s=4)
        ax.set_title(f"t-SNE of {kind} (stratified)")
        fig.colorbar(scatter, ax=ax, label="level")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def analyze_run(run_dir: str | Path, out_dir: str | Path, per_level: int = 3000, tsne_per_level: int = 300,
                tsne: bool = True, seed: int = 0) -> dict[str, Any]:
    """Analyse one run; writes ``OUT/analysis.json`` and (with matplotlib) distance_matrix.png,
    adjacent.png, pair_pca.png, tsne.png. Returns the JSON document."""
    run_dir, out_dir = Path(run_dir), Path(out_dir)
    loaded = run_features(run_dir)
    numbers = analyze_features(loaded["f"], loaded["levels"], loaded["num_levels"], loaded["f_hat"], per_level, seed)
    document = {"run": str(run_dir), "method": loaded["method"], **_public(numbers), "lookup": loaded["lookup"],
                "figures": []}
    plt = _pyplot()
    out_dir.mkdir(parents=True, exist_ok=True)
    if plt is None:
        document["note"] = "matplotlib is not installed: numbers only, no figures"
    else:
        _plot_matrices(plt, numbers, loaded["method"], out_dir / "distance_matrix.png")
        series = {"f": numbers["f"]["adjacent"]}
        if numbers["f_hat"] is not None:
            series["f̂ (after CLCA)"] = numbers["f_hat"]["adjacent"]
        _plot_adjacent(plt, series, out_dir / "adjacent.png", f"{loaded['method']}: adjacent-level distance")
        _plot_pca(plt, numbers, out_dir / "pair_pca.png")
        document["figures"] = ["distance_matrix.png", "adjacent.png", "pair_pca.png"]
        if tsne:
            embeddings = {}
            for kind, feats in (("f", loaded["f"]), ("f_hat", loaded["f_hat"])):
                if feats is not None and (emb := tsne_embedding(feats, loaded["levels"], tsne_per_level, seed)):
                    embeddings[kind] = emb
            if embeddings:
                _plot_tsne(plt, embeddings, out_dir / "tsne.png")
                document["figures"].append("tsne.png")
            else:
                document["note"] = "t-SNE skipped (scikit-learn not installed or too few anchors)"
    write_text_atomic(out_dir / "analysis.json", json.dumps(document, indent=2) + "\n")
    return document


def _public(numbers: dict[str, Any]) -> dict[str, Any]:
    """The JSON-able numbers (PCA projections left out)."""
    strip = lambda n: None if n is None else {k: v for k, v in n.items() if not k.startswith("_")}
    return {**numbers, "f": strip(numbers["f"]), "f_hat": strip(numbers["f_hat"])}


def compare_runs(documents: list[dict[str, Any]], out_dir: str | Path) -> dict[str, Any]:
    """Side by side: each run's adjacent-level distances (of f̂ when it has CLCA, else f); writes
    compare.json and compare_adjacent.png. Returns {"runs": [{"run", "method", "features", "adjacent"}]}."""
    out_dir = Path(out_dir)
    rows = []
    for doc in documents:
        kind = "f_hat" if doc["f_hat"] is not None else "f"
        rows.append({"run": doc["run"], "method": doc["method"], "features": kind, "adjacent": doc[kind]["adjacent"]})
    comparison = {"runs": rows}
    write_text_atomic(out_dir / "compare.json", json.dumps(comparison, indent=2) + "\n")
    plt = _pyplot()
    if plt is not None:
        labels = [f"{r['method']} ({'f̂' if r['features'] == 'f_hat' else 'f'})" for r in rows]
        unique = [f"{label} #{i}" if labels.count(label) > 1 else label for i, label in enumerate(labels)]
        _plot_adjacent(plt, {label: r["adjacent"] for label, r in zip(unique, rows)},
                       out_dir / "compare_adjacent.png", "adjacent-level cosine distance")
    return comparison
