"""NativeKernel's plain-library path: built once into a private folder, loaded with ctypes; a source that
does not compile makes the kernel unavailable with one line, not an exception."""

import ctypes

import pytest

import torch

import hico_plugin.native as native
from hico_plugin.native import NativeKernel, pointer

SOURCE = """
#include <cstdint>
extern "C" void add_one(float* x, int64_t n, int threads) {
#pragma omp parallel for num_threads(threads)
  for (int64_t i = 0; i < n; ++i) x[i] += 1.0f;
}
"""


def test_plain_library_builds_once_and_runs(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("HICO_CACHE_DIR", str(tmp_path))
    monkeypatch.delenv("HICO_NO_FUSED", raising=False)
    source = tmp_path / "add_one.cpp"
    source.write_text(SOURCE)
    kernel = NativeKernel("hico_test_add_one", source, "test kernel", "nothing")
    lib = kernel.get()
    assert lib is not None, kernel.error
    # a cold kernel cache says why a first run waits
    assert capsys.readouterr().err.splitlines() == [native.FIRST_BUILD_NOTE.format(root=tmp_path / "kernels")]
    x = torch.zeros(5)
    lib.add_one(pointer(x), ctypes.c_int64(5), 2)
    assert torch.equal(x, torch.ones(5))
    folder = kernel.build_dir()
    assert folder.parent == tmp_path / "kernels" and (folder / "hico-built").read_text() == "hico_test_add_one.so"
    assert not list(folder.glob("*.tmp"))
    again = NativeKernel("hico_test_add_one", source, "test kernel", "nothing")
    assert again.get() is not None and capsys.readouterr().err == ""  # built once, nothing said


TYPED_SOURCE = """
#include <cstdint>
extern "C" void add_one_f32(float* x, int64_t n) { for (int64_t i = 0; i < n; ++i) x[i] += 1.0f; }
extern "C" void add_one_f64(double* x, int64_t n) { for (int64_t i = 0; i < n; ++i) x[i] += 1.0; }
extern "C" double half(double x) { return x / 2; }
"""


def test_a_plain_library_is_loaded_with_its_declared_signatures(tmp_path, monkeypatch):
    """The declared argument and return types are set on the loaded library, one function per dtype where the
    name holds {dtype}; a torch extension declares none."""
    monkeypatch.setenv("HICO_CACHE_DIR", str(tmp_path))
    monkeypatch.delenv("HICO_NO_FUSED", raising=False)
    source = tmp_path / "typed.cpp"
    source.write_text(TYPED_SOURCE)
    kernel = NativeKernel("hico_test_typed", source, "test kernel", "nothing", functions={
        "add_one_{dtype}": ([ctypes.c_void_p, ctypes.c_int64], None), "half": ([ctypes.c_double], ctypes.c_double)})
    lib = kernel.get()
    assert lib is not None, kernel.error
    assert lib.half(3) == 1.5  # an int converted to double, a double returned: the types are set
    for dtype, suffix in native.DTYPE_SUFFIXES.items():
        assert getattr(lib, f"add_one_{suffix}").argtypes == [ctypes.c_void_p, ctypes.c_int64]
        x = torch.zeros(4, dtype=dtype)
        kernel.function("add_one_{dtype}", dtype)(pointer(x), 4)
        assert torch.equal(x, torch.ones(4, dtype=dtype))
    with pytest.raises(ValueError, match="loader='ctypes'"):
        NativeKernel("hico_test_typed", source, "test kernel", "nothing", loader="torch",
                     functions={"half": ([ctypes.c_double], ctypes.c_double)})


def test_several_sources_build_one_library_whose_key_covers_each(tmp_path, monkeypatch, capsys):
    """Two sources compiled into one library, calling each other; an edit of either is a new build, and
    either failing to compile makes the kernel unavailable with one line."""
    monkeypatch.setenv("HICO_CACHE_DIR", str(tmp_path))
    monkeypatch.delenv("HICO_NO_FUSED", raising=False)
    outer, inner = tmp_path / "outer.cpp", tmp_path / "inner.cpp"
    outer.write_text('extern "C" int twice(int x);\nextern "C" int add_twice(int x, int y) { return x + twice(y); }\n')
    results = []
    for factor in (2, 3):
        inner.write_text(f'extern "C" int twice(int x) {{ return {factor} * x; }}\n')
        kernel = NativeKernel("hico_test_two", [outer, inner], "test kernel", "nothing",
                              functions={"add_twice": ([ctypes.c_int, ctypes.c_int], ctypes.c_int)})
        assert kernel.available(), kernel.error
        results.append((kernel.build_dir(), kernel.get().add_twice(1, 3)))
    (first_dir, first), (second_dir, second) = results
    assert first_dir != second_dir and (first, second) == (7, 10)
    capsys.readouterr()
    inner.write_text("this is not C++\n")
    broken = NativeKernel("hico_test_two", [outer, inner], "test kernel", "the torch twin")
    assert broken.get() is None
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("hico: the test kernel could not be built, using the torch twin: ")


def test_the_first_build_note_is_said_once_per_process(tmp_path, monkeypatch, capsys):
    """Several kernels built into one cold cache: one note, before the first build; the torch
    extensions add their own line (their build is the long one)."""
    monkeypatch.setenv("HICO_CACHE_DIR", str(tmp_path))
    monkeypatch.delenv("HICO_NO_FUSED", raising=False)
    built = []
    monkeypatch.setattr(NativeKernel, "_build_in_child", lambda self, folder: built.append(self.name) or "module.so")
    monkeypatch.setattr(NativeKernel, "_load", lambda self, module_file: object())
    source = tmp_path / "k.cpp"
    source.write_text("// any\n")
    for name, loader in (("hico_test_a", "ctypes"), ("hico_test_b", "torch"), ("hico_test_c", "ctypes")):
        assert NativeKernel(name, source, f"kernel {name[-1]}", "nothing", loader=loader).available()
    assert built == ["hico_test_a", "hico_test_b", "hico_test_c"]
    assert capsys.readouterr().err.splitlines() == [native.FIRST_BUILD_NOTE.format(root=tmp_path / "kernels"),
                                                    "building the kernel b (about 40 s)..."]


def test_source_that_does_not_compile_is_one_line(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("HICO_CACHE_DIR", str(tmp_path))
    monkeypatch.delenv("HICO_NO_FUSED", raising=False)
    source = tmp_path / "broken.cpp"
    source.write_text("this is not C++\n")
    kernel = NativeKernel("hico_test_broken", source, "test kernel", "the torch twin")
    assert kernel.get() is None and not kernel.available()
    err = capsys.readouterr().err.strip().splitlines()
    assert err[0] == native.FIRST_BUILD_NOTE.format(root=tmp_path / "kernels")
    assert len(err) == 2 and err[1].startswith("hico: the test kernel could not be built, using the torch twin: ")
    assert not (kernel.build_dir() / "hico-built").exists()


def test_a_kernel_includes_the_shared_headers_and_a_changed_header_means_a_new_build(tmp_path, monkeypatch):
    monkeypatch.setenv("HICO_CACHE_DIR", str(tmp_path))
    monkeypatch.delenv("HICO_NO_FUSED", raising=False)
    monkeypatch.setattr(native, "INCLUDE_DIR", tmp_path / "include")
    (tmp_path / "include").mkdir()
    header = tmp_path / "include" / "offset.h"
    header.write_text("constexpr float kOffset = 1.0f;\n")
    source = tmp_path / "add_offset.cpp"
    source.write_text('#include <cstdint>\n#include "offset.h"\n'
                      'extern "C" void add_offset(float* x, int64_t n) { for (int64_t i = 0; i < n; ++i) x[i] += kOffset; }\n')
    results = []
    for offset in ("1.0f", "2.0f"):
        header.write_text(f"constexpr float kOffset = {offset};\n")
        kernel = NativeKernel("hico_test_add_offset", source, "test kernel", "nothing")
        lib = kernel.get()
        assert lib is not None, kernel.error
        x = torch.zeros(3)
        lib.add_offset(pointer(x), ctypes.c_int64(3))
        results.append((kernel.build_dir(), float(x[0])))
    (first_dir, first), (second_dir, second) = results
    assert first_dir != second_dir and (first, second) == (1.0, 2.0)


def test_no_fused_turns_every_kernel_off(tmp_path, monkeypatch):
    monkeypatch.setenv("HICO_NO_FUSED", "1")
    kernel = NativeKernel("hico_test_off", tmp_path / "never_read.cpp", "test kernel", "nothing")
    assert kernel.get() is None and kernel.error == "disabled by HICO_NO_FUSED=1"


def test_pointer_refuses_non_contiguous():
    with pytest.raises(ValueError, match="contiguous CPU"):
        pointer(torch.zeros(4, 4).t())
