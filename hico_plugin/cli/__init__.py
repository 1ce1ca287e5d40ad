"""Console entry points (tyro). Each catches HicoError and prints it as one line."""

from __future__ import annotations

import sys
from typing import Callable, TypeVar

from hico_plugin.errors import HicoError

T = TypeVar("T")


def run_cli(main: Callable[[], T]) -> T:
    """Run ``main``; a HicoError becomes ``error: <message>`` on stderr and exit status 2."""
    try:
        return main()
    except HicoError as err:
        print(f"error: {err}", file=sys.stderr)
        raise SystemExit(2) from None
