"""engine.stopping: every stop signal asks for a stop, except one the process was started with ignored."""

from __future__ import annotations

import os
import signal

import pytest

from hico_plugin.engine.stopping import STOP_SIGNALS, stop_on_signals
from helpers_viewer import wait_for


@pytest.fixture
def restore_signals():
    saved = {sig: signal.getsignal(sig) for sig in STOP_SIGNALS}
    yield
    for sig, handler in saved.items():
        signal.signal(sig, handler)


def _send_all(asked: list[int]) -> None:
    for sig in STOP_SIGNALS:
        os.kill(os.getpid(), sig)
    assert wait_for(lambda: len(asked) >= 1, 10.0)  # a handler runs in the main thread right after the kill


def test_each_stop_signal_asks_for_a_stop(restore_signals):
    for sig in STOP_SIGNALS:
        signal.signal(sig, signal.SIG_DFL if sig != signal.SIGINT else signal.default_int_handler)
    asked: list[int] = []
    with stop_on_signals(lambda: asked.append(1) or False, announce=False):
        _send_all(asked)
        assert wait_for(lambda: len(asked) == len(STOP_SIGNALS), 10.0)
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler  # restored after the block


def test_a_signal_started_ignored_stays_ignored(restore_signals):
    signal.signal(signal.SIGHUP, signal.SIG_IGN)  # as nohup starts a command
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # as a shell without job control starts `cmd &`
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    asked: list[int] = []
    with stop_on_signals(lambda: asked.append(1) or False, announce=False):
        assert signal.getsignal(signal.SIGHUP) is signal.SIG_IGN and signal.getsignal(signal.SIGINT) is signal.SIG_IGN
        _send_all(asked)  # SIGINT and SIGHUP first, then SIGTERM
    assert asked == [1]  # only SIGTERM asked
    assert signal.getsignal(signal.SIGHUP) is signal.SIG_IGN and signal.getsignal(signal.SIGTERM) is signal.SIG_DFL
