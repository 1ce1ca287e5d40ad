"""hico-view: bad input is one error line; --demo serves until Ctrl-C and exits cleanly."""

from __future__ import annotations

import os
import re
import signal
import socket
import subprocess
import sys
import threading
import time

import pytest

from hico_plugin.cli.view import ViewArgs, entrypoint, load_viewable_run
from hico_plugin.errors import HicoError


def test_missing_or_bad_config_is_one_clear_error(tmp_path, monkeypatch, capsys):
    with pytest.raises(HicoError, match="--load-config"):
        load_viewable_run(ViewArgs())
    missing = tmp_path / "nope.yml"
    monkeypatch.setattr(sys, "argv", ["hico-view", "--load-config", str(missing)])
    with pytest.raises(SystemExit) as exit_info:
        entrypoint()
    assert exit_info.value.code == 2
    assert capsys.readouterr().err.strip().splitlines() == [f"error: --load-config: {missing} is not a file (expected RUN/config.yml)"]


@pytest.mark.parametrize("stop_signal", [signal.SIGINT, signal.SIGTERM], ids=["ctrl-c", "sigterm"])
def test_demo_serves_and_stops_on_signal(stop_signal):
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    # Started as from a terminal, where Ctrl-C reaches the command: the test itself may run as a
    # background job, which a shell starts with SIGINT ignored, and hico-view keeps an ignored signal
    # ignored (engine.stopping).
    process = subprocess.Popen(
        [sys.executable, "-X", "faulthandler", "-m", "hico_plugin.cli.view", "--demo", "--viewer.port", str(port), "--viewer.thumbnail-size", "0"],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env={**os.environ, "PYTHONUNBUFFERED": "1"},
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )
    lines: list[str] = []
    served = threading.Event()

    def read() -> None:
        for line in process.stdout:
            lines.append(line)
            if "Ctrl-C to stop" in line:
                served.set()

    threading.Thread(target=read, daemon=True).start()
    try:
        assert served.wait(120), "".join(lines)
        output = "".join(lines)
        assert re.search(rf"viewer: http://localhost:{port}\b", output)
        assert f"ssh -L {port}:localhost:{port}" in output
        with socket.create_connection(("127.0.0.1", port), timeout=5):
            pass
        process.send_signal(stop_signal)
        try:
            returncode = process.wait(timeout=60)
        except subprocess.TimeoutExpired:  # SIGABRT makes faulthandler print every thread's stack
            process.send_signal(signal.SIGABRT)
            process.wait(timeout=30)
            time.sleep(0.2)
            raise AssertionError("no exit 60 s after the stop signal:\n" + "".join(lines)) from None
        time.sleep(0.2)  # let the reader collect the last lines
        assert returncode == 0, "".join(lines)
    finally:
        if process.poll() is None:
            process.kill()
            process.wait()
    time.sleep(0.1)
    with socket.socket() as probe, pytest.raises(ConnectionRefusedError):
        probe.connect(("127.0.0.1", port))
