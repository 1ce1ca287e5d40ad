"""The fused CPU kernels: csrc/composite_cpu.cpp, built on first use with torch's C++ extension
loader (needs a C++ compiler, as torch.compile on CPU does).

The build folder is private to this package version, torch version, kernel source and build flags
(``$HICO_KERNEL_DIR`` or ``~/.cache/hico_plugin/kernels/<key>``), so checkouts and versions never
share torch's build lock. Builders take an ``flock`` first (the kernel drops it when a builder dies);
whoever holds it knows a leftover torch lock file is stale and removes it, saying so in one line.
The build itself runs in a child process bounded by ``BUILD_TIMEOUT_SECONDS`` (a hung compiler is
killed), and the finished module is then imported in-process. A build that fails, times out or cannot start
within ``BUILD_WAIT_SECONDS`` falls back to the torch compositor with one line, so no command waits
silently.

``composite_fused`` has the contract of ``composite.composite`` (the vectorised torch version, which
stays the reference and the fallback): one pass per pixel with early termination instead of every
(pixel, row) pair of the tile, so deep tiles cost what is visible, not what is binned.
``bin_gaussians_fused`` returns exactly what ``tiling.bin_gaussians`` does, without the
intermediate tensors of every candidate (Gaussian, tile) pair.
"""

from __future__ import annotations

import fcntl
import hashlib
import importlib.util
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from types import ModuleType

import torch
from torch import Tensor

from hico_plugin.rasterizer.composite import ALPHA_MAX, LOG_T_MIN
from hico_plugin.rasterizer.projection import ALPHA_MIN
from hico_plugin.rasterizer.tiling import TileBins

SOURCE = Path(__file__).parent / "csrc" / "composite_cpu.cpp"
MODULE_NAME = "hico_composite_cpu"


def _vector_flags() -> list[str]:
    """``-mavx2`` where torch found AVX2 (or AVX-512) on this CPU, so the float32 loops take 8 pixels at a
    time instead of SSE2's 4 (the compositor about 1.8x faster on a 540x960 capture). torch's own detection,
    which ``ATEN_CPU_CAPABILITY=default`` overrides, decides; the flags are part of the build folder's
    key, so a cache shared with a machine without AVX2 keeps a separate build."""
    return ["-mavx2"] if torch.backends.cpu.get_cpu_capability() in ("AVX2", "AVX512") else []


BUILD_FLAGS = {"extra_cflags": ["-O3", "-fopenmp", *_vector_flags()], "extra_ldflags": ["-fopenmp"]}
BUILD_TIMEOUT_SECONDS = 300.0
"""Longest a first-use build may run before it is killed and the torch compositor used. The build
takes about 40 s on an idle core; 300 s leaves room for a loaded machine while a hung compiler still
costs a command minutes, not forever. ``$HICO_KERNEL_BUILD_TIMEOUT`` (seconds) overrides it."""
BUILD_WAIT_SECONDS = BUILD_TIMEOUT_SECONDS + 60.0
"""How long to wait for another process's build before using the torch compositor: longer than that
builder's own bound, so a waiter does not give up on a build that is about to finish."""
BUILT_MARKER = "hico-built"
"""Written into the build folder once a build finished: the name of the module file to import."""
T_MIN = float(torch.tensor(LOG_T_MIN, dtype=torch.float64).exp())  # the torch version's cut, 1e-4

# Run by the child process: torch's loader compiles (or finds up to date) and imports the module.
_BUILD_SCRIPT = """
import json, sys
from torch.utils.cpp_extension import load
args = json.loads(sys.argv[1])
print(load(verbose=False, **args).__file__)
"""


class _Extension:
    """The compiled module, built once per process (None when building failed)."""

    def __init__(self):
        self.module: ModuleType | None = None
        self.error: str | None = None

    def get(self) -> ModuleType | None:
        if self.module is None and self.error is None:
            if os.environ.get("HICO_NO_FUSED") == "1":
                self.error = "disabled by HICO_NO_FUSED=1"
                return None
            try:
                self.module = _build(build_dir())
            except Exception as err:  # noqa: BLE001 - no compiler / headers / hung build: use torch
                last_line = (str(err).strip().splitlines() or [""])[-1]  # a build log ends with the cause
                self.error = f"{type(err).__name__}: {last_line}"
                print("hico: the fused CPU compositor could not be built, using the torch one (slower): "
                      f"{self.error}", file=sys.stderr, flush=True)
        return self.module


def build_dir() -> Path:
    """The private build folder of this package version + torch version + kernel source + flags."""
    from hico_plugin import __version__

    if os.environ.get("HICO_KERNEL_DIR"):
        return Path(os.environ["HICO_KERNEL_DIR"])
    digest = hashlib.sha256(SOURCE.read_bytes() + repr(sorted(BUILD_FLAGS.items())).encode())
    key = f"hico-{__version__}_torch-{torch.__version__}_{digest.hexdigest()[:12]}".replace("+", "-")
    cache = Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache"))
    return cache / "hico_plugin" / "kernels" / key


def build_timeout() -> float:
    """``BUILD_TIMEOUT_SECONDS``, or ``$HICO_KERNEL_BUILD_TIMEOUT`` when set."""
    return float(os.environ.get("HICO_KERNEL_BUILD_TIMEOUT", BUILD_TIMEOUT_SECONDS))


def _build(folder: Path) -> ModuleType:
    """Build (once) and import the kernel in ``folder``; TimeoutError when another live builder holds
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
                    raise TimeoutError(f"another process has been building the kernel in {folder} for over "
                                       f"{BUILD_WAIT_SECONDS:.0f} s") from None
                if not told:
                    print(f"waiting for another process building the CPU kernel in {folder}", file=sys.stderr)
                    told = True
                time.sleep(0.5)
        torch_lock = folder / "lock"  # torch's FileBaton: no live builder holds it while we hold the flock
        if torch_lock.exists():
            print(f"hico: removing the stale kernel build lock {torch_lock} (its builder is gone)",
                  file=sys.stderr, flush=True)
            torch_lock.unlink(missing_ok=True)
        marker = folder / BUILT_MARKER
        if not marker.is_file():
            print("building the CPU kernel (first use, about 40 s)...", file=sys.stderr, flush=True)
            module_file = _build_in_child(folder)
            tmp = marker.with_suffix(".tmp")
            tmp.write_text(Path(module_file).name)
            tmp.replace(marker)
        try:
            return _import(folder / marker.read_text().strip())
        except Exception:
            marker.unlink()  # a damaged module file: the next process rebuilds it
            raise


def _build_in_child(folder: Path) -> str:
    """Compile in a child process (its own session, so ninja and the compiler die with it) and return
    the module file; a build still running after ``build_timeout()`` is killed."""
    args = {"name": MODULE_NAME, "sources": [str(SOURCE)], "build_directory": str(folder), **BUILD_FLAGS}
    child = subprocess.Popen([sys.executable, "-c", _BUILD_SCRIPT, json.dumps(args)], stdout=subprocess.PIPE,
                             stderr=subprocess.PIPE, stdin=subprocess.DEVNULL, text=True, start_new_session=True)
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
    return out.strip().splitlines()[-1]


def _import(module_file: Path) -> ModuleType:
    """Import the built extension module from its file (as torch's loader does, without a rebuild check)."""
    spec = importlib.util.spec_from_file_location(MODULE_NAME, module_file)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


EXTENSION = _Extension()


def fused_available() -> bool:
    """Whether the fused CPU compositor is built (building it on the first call)."""
    return EXTENSION.get() is not None


class _FusedComposite(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means2d, conics, opacities, features, bins, image_size):
        ext = EXTENSION.get()
        grid = (bins.tiles_x, bins.tiles_x * bins.tiles_y, bins.tile_size)
        inputs = [t.contiguous() for t in (means2d, conics, opacities, features)]
        out, acc, final_t, n_drawn = ext.forward(*inputs, bins.gaussian_ids, bins.tile_offsets,
                                                 *grid, ALPHA_MIN, ALPHA_MAX, T_MIN, *image_size)
        ctx.save_for_backward(*inputs, final_t, n_drawn)
        ctx.bins, ctx.grid, ctx.image_size = bins, grid, image_size
        return out, acc

    @staticmethod
    def backward(ctx, grad_out, grad_acc):
        means2d, conics, opacities, features, final_t, n_drawn = ctx.saved_tensors
        bins = ctx.bins
        grads = EXTENSION.get().backward(
            means2d, conics, opacities, features, bins.gaussian_ids, bins.tile_offsets, *ctx.grid,
            ALPHA_MIN, ALPHA_MAX, final_t, n_drawn, grad_out.contiguous(), grad_acc.contiguous(),
            *ctx.image_size)
        return (*grads, None, None)


def bin_gaussians_fused(means2d: Tensor, conics: Tensor, reach: Tensor, extents: Tensor,
                        depths: Tensor, radii: Tensor, width: int, height: int,
                        tile_size: int) -> TileBins:
    """The arguments and result of ``tiling.bin_gaussians`` (CPU tensors). Call ``fused_available()``
    first."""
    num_cams, n = depths.shape
    with torch.no_grad():
        flat_radii = radii.reshape(-1).to(torch.int32).contiguous()
        order = torch.argsort(depths.reshape(-1), stable=True)
        order = order[flat_radii[order] > 0].contiguous()
        gaussian_ids, tile_ids, tile_offsets = EXTENSION.get().bin(
            means2d.detach().reshape(-1, 2).contiguous(), conics.detach().reshape(-1, 3).contiguous(),
            reach.detach().contiguous(), extents.detach().reshape(-1, 2).contiguous(), flat_radii,
            order, num_cams, n, width, height, tile_size)
    return TileBins(gaussian_ids, tile_ids, tile_offsets, -(-width // tile_size),
                    -(-height // tile_size), tile_size)


def composite_fused(means2d: Tensor, conics: Tensor, opacities: Tensor, features: Tensor,
                    bins: TileBins, image_size: tuple[int, int] | None = None) -> tuple[Tensor, Tensor]:
    """means2d [G,2], conics [G,3], opacities [G], features [G,D] -> features [T,P,D], alpha [T,P]
    (T tiles camera-major, P = tile_size^2 pixels row-major); with ``image_size`` = (width, height),
    the cameras' images instead: features [C,H,W,D], alpha [C,H,W] (the tiles laid out as images and
    cropped, written in place). CPU tensors, float32 or float64. Differentiable w.r.t. the four
    inputs. Call ``fused_available()`` first."""
    return _FusedComposite.apply(means2d, conics, opacities, features, bins, tuple(image_size or (0, 0)))
