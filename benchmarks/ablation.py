"""The paper's ablation as a benchmark script: ``python benchmarks/ablation.py [hico-bench flags]``.

Same as ``hico-bench`` (defaults: octree-gs, hico-gs-clca, hico-gs-dngc, hico-gs, hico-gs-max,
hico-gs-attn on city-block and pagoda); prints where results.json and report.md were written.
"""

from hico_plugin.cli.bench import entrypoint

if __name__ == "__main__":
    entrypoint()
