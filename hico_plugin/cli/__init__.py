"""Console entry points (tyro). Each catches HicoError and prints it as one line.

Exit status: 0 done, 2 bad input or a failed write (one ``error:`` line), 130 a training run stopped
early by a signal after saving its checkpoint (``engine.stopping.EXIT_INTERRUPTED``).
"""

from __future__ import annotations

import sys
from typing import Callable, TypeVar

from hico_plugin.errors import HicoError

T = TypeVar("T")


def run_cli(main: Callable[[], T]) -> T:
    """Run ``main``; a HicoError, or an OSError from writing outputs (disk full, read-only,
    permission), becomes ``error: <message>`` on stderr and exit status 2."""
    try:
        return main()
    except HicoError as err:
        print(f"error: {err}", file=sys.stderr)
        raise SystemExit(2) from None
    except OSError as err:
        where = err.filename or "output"
        print(f"error: {where}: {err.strerror or err} (check free space and permissions)", file=sys.stderr)
        raise SystemExit(2) from None
