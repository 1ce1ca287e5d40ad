"""Shared by the native kernels' tests."""

import os

import pytest


def require_kernel(kernel) -> None:
    """Skip a kernel's tests only when ``HICO_NO_FUSED=1`` turned the kernels off; anywhere else a kernel
    that does not build fails them (a compile error must not pass as skipped tests)."""
    if os.environ.get("HICO_NO_FUSED") == "1":
        pytest.skip("HICO_NO_FUSED=1: the native kernels are off")
    assert kernel.available(), f"the {kernel.what} could not be built: {kernel.error}"
