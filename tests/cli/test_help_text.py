"""Every hico-* command's --help reads as a reference: what an option does and why, never a measured
figure (dB, ms, a spread, a date, a speed-up, results over seeds, a wall time). Figures live in
benchmarks/RESULTS.md; tyro turns config docstrings into this help, so a figure in a docstring shows here."""

from __future__ import annotations

import contextlib
import io
import re
import sys

import pytest

from hico_plugin.bench import BENCH_MODES
from hico_plugin.cli import analyze, bench, evaluate, export, inspect, process, render, scene, train, view
from hico_plugin.data.formats import DATA_FORMATS
from hico_plugin.export.exporters import EXPORTERS
from hico_plugin.presets import all_presets
from hico_plugin.scenes import SCENES

FIGURE = re.compile(r"""
      \d\.\d+\s?dB\b                     # a score: 29.3 dB (not a definition such as "1 dB below it")
    | \d\s?ms\b|\d\.\d+\s?s\b            # a timing: 120 ms, 0.12 s
    | ±|\+-\s?\d                         # a spread
    | \b20\d\d-\d\d-\d\d\b               # a date
    | \b\d+\.\d+x(?![\w.])               # a speed-up: 0.42x (not 1600x1200, "1.2 x the size", "rings at 2x")
    | \b\d+x\s(?:faster|slower)          # 2x faster
    | \d\.\d+\s?%|\d\s?-\s?\d+\s?%       # a measured share: 0.7 %, 10-15 % (not "12% smaller")
    | \d\s?%\s(?:more|fewer|less)        # 27 % more anchors
    | \bseeds?\s\d                       # results over seeds
    | (?<![\d.:])\d{1,2}:\d\d(?![\d.:])  # a wall time: 9:58
    """, re.VERBOSE)
DEFAULT = re.compile(r"\(default: [^()]*(?:\([^()]*\)[^()]*)*\)")
BOX = re.compile(r"[│╭╮╰╯─•]")

COMMANDS = {
    "hico-train": train.entrypoint, "hico-eval": evaluate.entrypoint, "hico-render": render.entrypoint,
    "hico-export": export.entrypoint, "hico-scene": scene.entrypoint, "hico-process": process.entrypoint,
    "hico-inspect": inspect.entrypoint, "hico-view": view.entrypoint, "hico-bench": bench.entrypoint,
    "hico-analyze": analyze.entrypoint,
}


def help_lines() -> list[tuple[str, ...]]:
    """Every command line whose help is checked: each preset (and one with each dataset format), each
    subcommand of the other commands."""
    lines = [("hico-train", name) for name in all_presets()]
    lines += [("hico-train", "hico-gs-lite", name) for name in DATA_FORMATS.names()]
    lines += [(command,) for command in COMMANDS if command != "hico-train"]
    lines += [("hico-export", name) for name in EXPORTERS.names()]
    lines += [("hico-scene", name) for name in SCENES.names()]
    lines += [("hico-process", kind) for kind in ("images", "video")]
    lines += [("hico-bench", mode) for mode in BENCH_MODES]
    return lines


def render_help(monkeypatch, command_line: tuple[str, ...]) -> str:
    """The text ``command_line --help`` prints, one single-column layout flattened to one line (the box
    drawing and the line wrapping removed, so a figure split over two lines is whole again)."""
    monkeypatch.setenv("COLUMNS", "100")
    monkeypatch.setattr(sys, "argv", [*command_line, "--help"])
    out = io.StringIO()
    with contextlib.redirect_stdout(out), pytest.raises(SystemExit) as exit_info:
        COMMANDS[command_line[0]]()
    assert exit_info.value.code == 0, out.getvalue()
    return " ".join(BOX.sub(" ", out.getvalue()).split())


def figures_in(text: str) -> list[str]:
    """The measured figures in help text, each with the words around it; defaults are left out."""
    text = DEFAULT.sub("", text)
    return [text[max(0, m.start() - 60): m.end() + 20] for m in FIGURE.finditer(text)]


@pytest.mark.parametrize("command_line", help_lines(), ids=" ".join)
def test_help_holds_no_measured_figure(monkeypatch, command_line):
    text = render_help(monkeypatch, command_line)
    assert "--help" in text
    assert figures_in(text) == []


def test_the_figure_pattern_catches_figures_and_spares_defaults_and_units():
    figures = ["29.33 ± 0.13 dB", "13.12 / 13.12 dB", "about 120 ms of a step", "0.42x the time", "1.8x faster",
               "2x faster", "measured 2026-11-29", "left 10-15 % of them", "0.7 % of the points",
               "27 % more anchors", "0.12 s per step", "seeds 0-2", "seed 1", "a wall time of 9:58", "-0.07 +- 0.22"]
    for text in figures:
        assert figures_in(text), text
    legitimate = ["Test PSNR levels (dB) of the table", "the lowest final score and 1 dB below it",
                  "photos at 1600x1200", "a 96 -> 32 -> 32 MLP", "http://127.0.0.1:7007", "(default: 0.42)",
                  "(default: 2026-11-29)", "3d -> d -> d", "YYYY-MM-DD_HHMMSS", "2x2 cells", "images_2|4|8",
                  "cuda:0", "camera rings at 1x, 2x and 4x distance", "each tier is 12% smaller",
                  "1.2 x the image size"]
    for text in legitimate:
        assert figures_in(text) == [], text
