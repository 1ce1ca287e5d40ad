"""Stages log where they are when no terminal shows a bar, and a stage run before with the same key is reused."""

from __future__ import annotations

import io

import pytest
from rich.console import Console

from hico_plugin.process.stages import StageRunner, duration


class Clock:
    def __init__(self):
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


def _runner(out, clock):
    text = io.StringIO()
    return StageRunner(out, Console(file=text, width=200), every_s=60.0, clock=clock), text


def test_a_long_stage_logs_its_start_a_line_a_minute_and_its_end(tmp_path):
    clock = Clock()
    runner, text = _runner(tmp_path, clock)

    def work(report):
        for done in range(0, 101, 10):
            report(done, 100)
            clock.now += 25.0  # a line every 60 s: after 75 s, 150 s, 225 s
        return {"pairs": 100, "verified": 70}

    summary = runner.run("matching", "key-1", work, unit="pairs",
                         describe=lambda s: f"{s['pairs']} pairs, {s['verified']} verified")
    lines = text.getvalue().splitlines()
    assert lines[0].startswith("hico-process: writing")
    assert lines[1:] == ["matching     started (100 pairs)",
                         "matching     30 of 100 pairs (30 %), 1 min 15 s so far",
                         "matching     60 of 100 pairs (60 %), 2 min 30 s so far",
                         "matching     90 of 100 pairs (90 %), 3 min 45 s so far",
                         "matching     done in 4 min 35 s: 100 pairs, 70 verified"]
    assert runner.timings == {"matching": pytest.approx(275.0)}
    again, text = _runner(tmp_path, clock)
    assert again.run("matching", "key-1", lambda report: pytest.fail("redone"), unit="pairs",
                     describe=lambda s: f"{s['pairs']} pairs") == summary
    assert text.getvalue() == "matching     reused (finished before with the same inputs): 100 pairs\n"
    assert again.reused == ["matching"]
    other, text = _runner(tmp_path, clock)
    assert other.run("matching", "key-2", lambda report: {"pairs": 5}, unit="pairs") == {"pairs": 5}
    assert other.reused == [] and "done in 0.0 s" in text.getvalue()


def test_durations_read_as_people_write_them():
    assert [duration(s) for s in (8.24, 61.0, 725.0, 7380.0)] == ["8.2 s", "1 min 01 s", "12 min 05 s", "2 h 03 min"]
