"""engine.memory: freed heap pages go back to the system; evaluation releases them around each view."""

import subprocess
import sys
import weakref

import pytest
import torch
from helpers_toy_model import ToyDataConfig, ToyModelConfig

from hico_plugin.engine import evaluation

# 800 blocks of 64 KiB (below glibc's mmap threshold, so they live in the heap), all freed but the
# last, which pins the heap's top: only malloc_trim can return the pages below it.
_FRAGMENTED_HEAP = """
import ctypes, ctypes.util, re
from hico_plugin.engine.memory import release_free_memory
libc = ctypes.CDLL(ctypes.util.find_library("c"))
libc.malloc.restype = ctypes.c_void_p
libc.free.argtypes = [ctypes.c_void_p]
def rss(): return int(re.search(r"VmRSS:\\s+(\\d+)", open("/proc/self/status").read()).group(1)) // 1024
blocks = [libc.malloc(64 * 1024) for _ in range(800)]
for block in blocks:
    ctypes.memset(block, 1, 64 * 1024)
for block in blocks[:-1]:
    libc.free(block)
before = rss()
print(release_free_memory(), before - rss())
"""


def test_release_free_memory_returns_freed_heap_pages():
    if not sys.platform.startswith("linux"):
        pytest.skip("glibc's malloc_trim and /proc are Linux's")
    out = subprocess.run([sys.executable, "-c", _FRAGMENTED_HEAP], capture_output=True, text=True, check=True)
    released, mib = out.stdout.split()
    assert released == "True" and int(mib) >= 40  # of the 50 MiB freed


def test_evaluate_releases_memory_before_and_after_each_view(monkeypatch):
    calls = []
    monkeypatch.setattr(evaluation, "release_free_memory", lambda: calls.append(1) or True)
    dataset = ToyDataConfig().setup()
    results = evaluation.evaluate(ToyModelConfig().setup(dataset), dataset, [3, 7, 11], torch.device("cpu"))
    assert results["num_views"] == 3 and len(calls) == 4


def test_evaluate_keeps_nothing_of_a_view_but_its_scalars(monkeypatch):
    """A view's images are dropped before the next view is rendered: memory does not grow with the
    test views (a thousand-photo capture evaluates a hundred of them)."""
    dataset = ToyDataConfig().setup()
    model = ToyModelConfig().setup(dataset)
    rendered = []
    eval_view = model.eval_view

    def tracked(camera, image, gt):
        results = eval_view(camera, image, gt)
        rendered.append(weakref.ref(results["rgb"]))
        assert all(ref() is None for ref in rendered[:-1])  # the earlier views' images are gone
        return results

    monkeypatch.setattr(model, "eval_view", tracked)
    results = evaluation.evaluate(model, dataset, [3, 7, 11], torch.device("cpu"))
    assert len(rendered) == 3 and results["psnr"] is not None and "rgb" not in results


# Eight 6 MiB blocks allocated, written and freed five times: page faults per round.
_REUSED_BLOCKS = """
import ctypes, ctypes.util, resource, sys
from hico_plugin.engine.memory import keep_freed_memory
libc = ctypes.CDLL(ctypes.util.find_library("c"))
libc.malloc.restype = ctypes.c_void_p
libc.malloc.argtypes = [ctypes.c_size_t]
libc.free.argtypes = [ctypes.c_void_p]
kept = keep_freed_memory() if sys.argv[1] == "keep" else None
size, faults = 6 << 20, []
for _ in range(5):
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    blocks = [libc.malloc(size) for _ in range(8)]
    for block in blocks:
        ctypes.memset(block, 1, size)
    for block in blocks:
        libc.free(block)
    faults.append(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
print(kept, *faults)
"""


def test_keep_freed_memory_reuses_freed_blocks_without_page_faults():
    if not sys.platform.startswith("linux"):
        pytest.skip("glibc's mallopt and getrusage's fault counts are Linux's")

    def rounds(mode):
        out = subprocess.run([sys.executable, "-c", _REUSED_BLOCKS, mode], capture_output=True, text=True,
                             check=True).stdout.split()
        return out[0], [int(n) for n in out[1:]]

    pages = 8 * (6 << 20) // 4096
    kept, faults = rounds("keep")
    if kept != "True":
        pytest.skip("mallopt is glibc's")
    assert faults[0] >= pages // 2  # the first round maps its pages ...
    assert max(faults[1:]) < pages // 20  # ... the next ones reuse them
    _, default_faults = rounds("default")
    assert min(default_faults[1:]) >= pages // 2  # glibc's defaults map them again every round
