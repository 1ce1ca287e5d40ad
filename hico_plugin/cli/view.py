"""hico-view: serve a finished run (or the built-in analytic demo scene) in the live viewer.

    hico-view --load-config outputs/city-block/config.yml
    hico-view --demo --viewer.port 7010
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import tyro

import hico_plugin.presets  # noqa: F401  (loads the config classes a config.yml may name)
from hico_plugin.cli import run_cli
from hico_plugin.engine.stopping import EXIT_INTERRUPTED, stop_on_signals
from hico_plugin.errors import HicoError
from hico_plugin.viewer import RunViewerState, ViewableModel, ViewerConfig, model_render_fn
from hico_plugin.visualization import RenderOptions


@dataclass
class ViewArgs:
    """Open a trained run in the browser viewer (no training)."""

    load_config: Path | None = None
    """The run's config.yml (written by hico-train next to its checkpoints)."""
    checkpoint: Path | None = None
    """A checkpoint to show instead of the run's latest."""
    device: str | None = None
    """Device to render on (default: the run's)."""
    demo: bool = False
    """Serve the analytic demo scene instead of a run (checks the viewer without training anything)."""
    viewer: ViewerConfig = field(default_factory=ViewerConfig)


def _eval_stats(config_path: Path, output_dir: Any) -> dict[str, Any]:
    """The run's last evaluation (``eval.json`` in ns-eval layout) as ``eval/<metric>`` stats."""
    for run_dir in (Path(output_dir) if output_dir else None, config_path.parent):
        if run_dir is not None and (run_dir / "eval.json").is_file():
            try:
                results = json.loads((run_dir / "eval.json").read_text()).get("results", {})
            except (OSError, ValueError):
                return {}
            return {f"eval/{k}": v for k, v in results.items() if isinstance(v, (int, float))}
    return {}


def load_viewable_run(args: ViewArgs) -> tuple[Any, Any, dict[str, Any], Path | None]:
    """(model, dataset, initial stats, run folder) of ``--load-config`` or of ``--demo`` (no folder)."""
    if args.demo:
        from hico_plugin.viewer.demo import DemoDataset, DemoModel

        return DemoModel(), DemoDataset(), {}, None
    if args.load_config is None:
        raise HicoError("--load-config: expected a run's config.yml (or pass --demo)")
    if not args.load_config.is_file():
        raise HicoError(f"--load-config: {args.load_config} is not a file (expected RUN/config.yml)")
    from hico_plugin.engine import load_run

    run = load_run(args.load_config, checkpoint=args.checkpoint, device=args.device)
    config, model, dataset = run.config, run.model, run.dataset
    if not isinstance(model, ViewableModel):
        raise HicoError(
            f"{args.load_config}: model {type(model).__name__} cannot be viewed "
            "(it needs render_for_display(camera, options) and viewer_anchors())"
        )
    return model, dataset, _eval_stats(args.load_config, getattr(config, "output_dir", None)), run.run_dir


def render_once(render_fn: Callable[..., Any], dataset: Any, long_side: int = 64) -> None:
    """Render one small training view before serving: a first run's one-off setup (the CPU kernels'
    build, which says so) happens here rather than behind the page's first view."""
    camera = dataset.cameras[0]
    render_fn(camera.scaled(min(1.0, long_side / max(camera.width, camera.height))), RenderOptions())


def main(args: ViewArgs) -> None:
    model, dataset, stats, run_dir = load_viewable_run(args)
    state = RunViewerState(model, dataset, stats=stats, run_dir=run_dir)
    render_fn = model_render_fn(model)
    render_once(render_fn, dataset)
    viewer = args.viewer.setup(render_fn=render_fn, state=state)
    serve_until_signal(viewer.stop)


def serve_until_signal(stop: Callable[[], None]) -> None:
    """Block until Ctrl-C, SIGTERM or SIGHUP, then call ``stop()``; a second signal during that
    stop ends the process at once (exit status 130).

    The signal handler only sets a flag that a sleeping loop polls: a KeyboardInterrupt raised inside
    a lock's ``with`` block (as in ``Event.wait``) can leave the lock held, and stopping the viewer
    needs that lock again."""
    requested = [False]

    def request_stop() -> bool:
        already, requested[0] = requested[0], True
        return already

    try:
        with stop_on_signals(request_stop, announce=False):
            try:
                print("viewer: Ctrl-C to stop", flush=True)
                while not requested[0]:
                    time.sleep(0.2)
            finally:
                stop()
    except KeyboardInterrupt:
        raise SystemExit(EXIT_INTERRUPTED) from None


def entrypoint() -> None:
    run_cli(lambda: main(tyro.cli(ViewArgs)))


if __name__ == "__main__":
    entrypoint()
