"""This package's compiled CPU kernels: C++ sources built with the system compiler on first use.

A torch extension (``loader="torch"``) for the compositor, which needs ATen; a plain ``extern "C"`` library
(``loader="ctypes"``, one compiler call, no torch headers) for the per-pixel kernels. Each build has its own
folder per package, torch, source and flags (under ``storage.cache_dir("kernels")``), an
``flock`` and a child process bounded by ``BUILD_TIMEOUT_SECONDS``; one that fails, times out or cannot start
within ``BUILD_WAIT_SECONDS`` leaves the torch twin in use. ``HICO_NO_FUSED=1`` turns all off.
"""

from __future__ import annotations

import ctypes
import fcntl
import hashlib
import importlib.util
import json
import os
import signal
import subprocess
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from types import ModuleType
from typing import Any

import torch

BUILD_TIMEOUT_SECONDS = 300.0
"""Longest a first-use build may run before it is killed and the torch twin used: several times a torch
extension's build on an idle core, room for a loaded machine, while a hung compiler still costs a
command minutes, not forever. ``$HICO_KERNEL_BUILD_TIMEOUT`` (seconds) overrides it."""
BUILD_WAIT_SECONDS = BUILD_TIMEOUT_SECONDS + 60.0
"""How long to wait for another process's build before using the torch twin: longer than that
builder's own bound, so a waiter does not give up on a build that is about to finish."""
BUILT_MARKER = "hico-built"
"""Written into the build folder once a build finished: the name of the module file to load."""
INCLUDE_DIR = Path(__file__).parent / "csrc"
"""Headers shared by the kernels (``#include "name.h"``); every build gets it as an include path, and
its headers' bytes are part of every build folder's key, so a changed header never reuses a stale build."""
FIRST_BUILD_NOTE = "hico: building the CPU kernels, first run only (a minute or two); cached in {root}"
"""Printed before the first build into a kernels folder in this process, so a first run says why it waits
(the two torch extensions take most of that time, the plain libraries seconds)."""
_announced_roots: set[Path] = set()
DTYPE_SUFFIXES = {torch.float32: "f32", torch.float64: "f64"}
"""The dtypes the plain libraries compute in, and each one's function-name suffix (``hico_ssim_forward_f32``)."""
Signature = tuple[Sequence[Any], Any]
"""A C function's ``ctypes`` argument types and return type (None for void)."""

# Run by the child process: torch's loader compiles (or finds up to date) and imports the module.
_TORCH_BUILD_SCRIPT = """
import json, sys
from torch.utils.cpp_extension import load
args = json.loads(sys.argv[1])
print(load(verbose=False, **args).__file__)
"""


def vector_flags() -> list[str]:
    """``-mavx2`` where torch found AVX2 (or AVX-512) on this CPU, so float32 loops take 8 values at a time
    instead of SSE2's 4. torch's own detection, which ``ATEN_CPU_CAPABILITY=default`` overrides, decides;
    the flags are part of the build folder's key, so a cache shared with a machine without AVX2 keeps a
    separate build."""
    return ["-mavx2"] if torch.backends.cpu.get_cpu_capability() in ("AVX2", "AVX512") else []


def build_timeout() -> float:
    """``BUILD_TIMEOUT_SECONDS``, or ``$HICO_KERNEL_BUILD_TIMEOUT`` when set."""
    return float(os.environ.get("HICO_KERNEL_BUILD_TIMEOUT", BUILD_TIMEOUT_SECONDS))


class NativeKernel:
    """C++ sources built into one module once per machine and loaded once per process (``get()`` is None
    when it cannot be built; ``error`` then says why).

    name: the module / library name; sources: the .cpp file, or several compiled into one module; what:
    the kernel in words, for the one line printed when it cannot be built; fallback: what is used instead,
    for that line; loader: "torch" (an extension module) or "ctypes" (a shared library of C functions);
    functions: a plain library's C functions and their ``Signature``, set once it loads, a name holding
    ``{dtype}`` standing for one function per ``DTYPE_SUFFIXES`` entry.
    """

    def __init__(self, name: str, sources: Path | Sequence[Path], what: str, fallback: str, loader: str = "ctypes",
                 flags: list[str] | None = None, functions: dict[str, Signature] | None = None):
        if loader not in ("torch", "ctypes"):
            raise ValueError(f"loader must be 'torch' or 'ctypes', got {loader!r}")
        if functions and loader != "ctypes":
            raise ValueError("only a plain library (loader='ctypes') declares its functions' signatures")
        self.name, self.what, self.fallback, self.loader = name, what, fallback, loader
        self.sources = (Path(sources),) if isinstance(sources, (str, os.PathLike)) else tuple(map(Path, sources))
        self.flags = ["-O3", "-fopenmp", *vector_flags()] if flags is None else list(flags)
        self.functions = dict(functions or {})
        self.module: Any = None
        self.error: str | None = None

    def get(self) -> ModuleType | ctypes.CDLL | None:
        if self.module is None and self.error is None:
            if os.environ.get("HICO_NO_FUSED") == "1":
                self.error = "disabled by HICO_NO_FUSED=1"
                return None
            try:
                module = self._build(self.build_dir())
            except Exception as err:  # noqa: BLE001 - no compiler / headers / hung build: use the torch twin
                last_line = (str(err).strip().splitlines() or [""])[-1]  # a build log ends with the cause
                self.error = f"{type(err).__name__}: {last_line}"
                print(f"hico: the {self.what} could not be built, using {self.fallback}: {self.error}",
                      file=sys.stderr, flush=True)
            else:
                self.module = self._typed(module)
        return self.module

    def function(self, name: str, dtype: torch.dtype) -> Any:
        """The built library's function ``name`` for ``dtype`` (its ``{dtype}`` filled in), typed."""
        return getattr(self.get(), name.format(dtype=DTYPE_SUFFIXES[dtype]))

    def available(self) -> bool:
        """Whether the kernel is built (building it on the first call)."""
        return self.get() is not None

    def build_dir(self) -> Path:
        """The private build folder of this package version + torch version + kernel sources + the headers
        they may include (``INCLUDE_DIR``'s and those beside them) + flags."""
        from hico_plugin import __version__
        from hico_plugin.storage import cache_dir

        first, *others = self.sources  # hashed as a lone source always was: one-source builds stay cached
        digest = hashlib.sha256(first.read_bytes() + repr((self.loader, self.flags)).encode())
        for source in others:
            digest.update(source.name.encode() + source.read_bytes())
        folders = dict.fromkeys([INCLUDE_DIR, *(source.parent for source in self.sources)])
        for header in (header for folder in folders for header in sorted(folder.glob("*.h"))):
            digest.update(header.name.encode() + header.read_bytes())
        key = f"{self.name}-{__version__}_torch-{torch.__version__}_{digest.hexdigest()[:12]}".replace("+", "-")
        return cache_dir("kernels") / key

    def _build(self, folder: Path) -> Any:
        """Build (once) and load the kernel in ``folder``; TimeoutError when another live builder holds
        it longer than ``BUILD_WAIT_SECONDS`` or our build runs longer than ``build_timeout()``."""
        folder.mkdir(parents=True, exist_ok=True)
        with (folder / "hico-build.lock").open("a+") as guard:
            deadline, told = time.monotonic() + BUILD_WAIT_SECONDS, False
            while True:
                try:
                    fcntl.flock(guard.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
                    break
                except BlockingIOError:
                    if time.monotonic() > deadline:
                        raise TimeoutError(f"another process has been building the kernel in {folder} for "
                                           f"over {BUILD_WAIT_SECONDS:.0f} s") from None
                    if not told:
                        print(f"waiting for another process building the {self.what} in {folder}", file=sys.stderr)
                        told = True
                    time.sleep(0.5)
            torch_lock = folder / "lock"  # torch's FileBaton: no live builder holds it while we hold the flock
            if torch_lock.exists():
                print(f"hico: removing the stale kernel build lock {torch_lock} (its builder is gone)",
                      file=sys.stderr, flush=True)
                torch_lock.unlink(missing_ok=True)
            marker = folder / BUILT_MARKER
            if not marker.is_file():
                if folder.parent not in _announced_roots:
                    _announced_roots.add(folder.parent)
                    print(FIRST_BUILD_NOTE.format(root=folder.parent), file=sys.stderr, flush=True)
                if self.loader == "torch":
                    print(f"building the {self.what} (about 40 s)...", file=sys.stderr, flush=True)
                module_file = self._build_in_child(folder)
                tmp = marker.with_suffix(".tmp")
                tmp.write_text(Path(module_file).name)
                tmp.replace(marker)
            try:
                return self._load(folder / marker.read_text().strip())
            except Exception:
                marker.unlink()  # a damaged module file: the next process rebuilds it
                raise

    def _command(self, folder: Path) -> tuple[list[str], Path | None]:
        """The build command and, for a plain library, the file it writes."""
        if self.loader == "torch":
            args = {"name": self.name, "sources": list(map(str, self.sources)), "build_directory": str(folder),
                    "extra_cflags": self.flags, "extra_ldflags": ["-fopenmp"],
                    "extra_include_paths": [str(INCLUDE_DIR)]}
            return [sys.executable, "-c", _TORCH_BUILD_SCRIPT, json.dumps(args)], None
        library = folder / f"{self.name}.so"
        compiler = os.environ.get("CXX", "c++")
        return [compiler, *self.flags, f"-I{INCLUDE_DIR}", "-fPIC", "-shared", "-std=c++17", *map(str, self.sources),
                "-o", str(library.with_suffix(".so.tmp"))], library

    def _build_in_child(self, folder: Path) -> str:
        """Compile in a child process (its own session, so ninja and the compiler die with it) and return
        the module file; a build still running after ``build_timeout()`` is killed."""
        command, library = self._command(folder)
        child = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, stdin=subprocess.DEVNULL,
                                 text=True, start_new_session=True)
        timeout = build_timeout()
        try:
            out, err = child.communicate(timeout=timeout)
        except subprocess.TimeoutExpired:
            raise TimeoutError(f"the kernel build in {folder} did not finish within {timeout:g} s "
                               "(set HICO_KERNEL_BUILD_TIMEOUT to allow longer)") from None
        finally:
            if child.poll() is None:  # timed out, or we were interrupted: no orphaned compiler
                os.killpg(child.pid, signal.SIGKILL)
                child.communicate()
                (folder / "lock").unlink(missing_ok=True)  # the killed child's torch lock (we hold the flock)
        if child.returncode != 0:
            raise RuntimeError(err.strip() or f"the kernel build exited with code {child.returncode}")
        if library is None:
            return out.strip().splitlines()[-1]
        library.with_suffix(".so.tmp").replace(library)  # a killed compiler leaves no half-written library
        return str(library)

    def _typed(self, library: Any) -> Any:
        """``library`` with the argument and return types of ``functions`` set on its functions."""
        for name, (argtypes, restype) in self.functions.items():
            for each in {name.format(dtype=suffix) for suffix in DTYPE_SUFFIXES.values()}:
                function = getattr(library, each)
                function.argtypes, function.restype = list(argtypes), restype
        return library

    def _load(self, module_file: Path) -> Any:
        """Import the built extension module from its file (as torch's loader does, without a rebuild
        check), or open the shared library."""
        if self.loader == "ctypes":
            return ctypes.CDLL(str(module_file))
        spec = importlib.util.spec_from_file_location(self.name, module_file)
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
        return module


def pointer(tensor: torch.Tensor) -> ctypes.c_void_p:
    """The address of a contiguous CPU tensor's first element, for a ``ctypes`` kernel argument."""
    if not tensor.is_contiguous() or tensor.device.type != "cpu":
        raise ValueError("a native kernel takes contiguous CPU tensors")
    return ctypes.c_void_p(tensor.data_ptr())
