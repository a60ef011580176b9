"""Shipping compiled kernels (issue 14): ``seed_cache`` files the install's numba kernels under
the layout numba reads with ``NUMBA_CACHE_DIR`` (``<dirname>_<sha1 of the source dir>``), copies
only what is missing or older, and never leaves half a file; a service started with a fresh
cache directory compiles nothing. ``tune_allocator`` honours the environment's settings."""

from __future__ import annotations

import hashlib
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

from lightprobe.cli.warm_kernels import seed_cache, shipped_kernel_dirs
from lightprobe.device import allocator as memory


def _fake_install(root: Path) -> Path:
    src = root / "device" / "hdr"
    (src / "__pycache__").mkdir(parents=True)
    (src / "rolling.py").write_text("x = 1\n")
    for name in ("rolling._merge_kernel-1.py312.nbi", "rolling._merge_kernel-1.py312.1.nbc"):
        (src / "__pycache__" / name).write_bytes(b"kernel " + name.encode())
    (src / "__pycache__" / "rolling.cpython-312.pyc").write_bytes(b"bytecode")
    (root / "device" / "empty" / "__pycache__").mkdir(parents=True)  # no kernels: not shipped
    return src


def test_seed_cache_files_kernels_in_numbas_layout_once(tmp_path: Path) -> None:
    root = tmp_path / "install"
    src = _fake_install(root)
    assert shipped_kernel_dirs(root) == [src]
    cache = tmp_path / "state" / "cache" / "numba"
    assert seed_cache(cache, root) == 2
    sub = cache / f"hdr_{hashlib.sha1(str(src.resolve()).encode()).hexdigest()}"
    assert sorted(p.name for p in sub.iterdir()) == ["rolling._merge_kernel-1.py312.1.nbc",
                                                     "rolling._merge_kernel-1.py312.nbi"]
    assert (sub / "rolling._merge_kernel-1.py312.nbi").read_bytes().startswith(b"kernel ")
    assert seed_cache(cache, root) == 0  # up to date: nothing copied
    # a newer install replaces the copy; no temporary file is left behind
    later = time.time() + 10
    os.utime(src / "__pycache__" / "rolling._merge_kernel-1.py312.nbi", (later, later))
    assert seed_cache(cache, root) == 1
    assert not [p for p in sub.iterdir() if p.name.endswith(".tmp")]


def test_the_shipped_kernels_load_from_a_fresh_cache_dir_without_compiling(tmp_path: Path) -> None:
    """numba, pointed at a fresh NUMBA_CACHE_DIR seeded from the install, loads the rolling
    merge's kernel instead of compiling it (its cache-hit counter says so)."""
    code = """
import os, numpy as np
from lightprobe.cli.warm_kernels import seed_cache
if "NUMBA_CACHE_DIR" in os.environ:
    seed_cache(os.environ["NUMBA_CACHE_DIR"])
from lightprobe.device.hdr import rolling
from types import SimpleNamespace
n = 4
t = SimpleNamespace(indptr=np.arange(0, n + 1, dtype=np.int64), indices=np.arange(n, dtype=np.int64),
                    data=np.ones(n, np.float32))
lut = np.zeros((257, 3, 4), np.float32); lut[:, :, 0] = np.linspace(0, 1, 257)[:, None]; lut[:, :, 1] = 1
m = rolling.RollingMerge(n)
m.update((0.01, 1.0), 0, t, np.ones(n, np.float32), np.ones(n), np.full((n, 3), 100, np.uint8), lut,
         (np.zeros(3), np.ones(3)))
print(sum(rolling._merge_kernel.stats.cache_hits.values()), sum(rolling._merge_kernel.stats.cache_misses.values()))
"""
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "numba")}
    # the in-tree cache must exist first (the install's warm-kernels); compile it here if not
    subprocess.run([sys.executable, "-c", code], env={**os.environ}, check=True, capture_output=True,
                   cwd=Path(__file__).resolve().parents[1])
    out = subprocess.run([sys.executable, "-c", code], env=env, check=True, capture_output=True, text=True,
                         cwd=Path(__file__).resolve().parents[1])
    hits, misses = (int(v) for v in out.stdout.split())
    assert hits >= 1, out.stdout
    assert misses == 0, out.stdout


def test_tune_allocator_leaves_settings_the_environment_made(monkeypatch) -> None:  # type: ignore[no-untyped-def]
    calls: list[tuple[int, int]] = []

    class FakeLibc:
        def mallopt(self, param: int, value: int) -> int:
            calls.append((param, value))
            return 1

        def malloc_trim(self, pad: int) -> int:
            return 1

    monkeypatch.setattr(memory, "_libc", lambda: FakeLibc())
    monkeypatch.setenv("MALLOC_ARENA_MAX", "4")
    monkeypatch.delenv("MALLOC_MMAP_THRESHOLD_", raising=False)
    monkeypatch.delenv("MALLOC_TRIM_THRESHOLD_", raising=False)
    assert memory.tune_allocator() is True
    assert calls == [(memory._M_MMAP_THRESHOLD, 256 * 1024), (memory._M_TRIM_THRESHOLD, 1 << 20)]
    monkeypatch.setattr(memory, "_libc", lambda: None)  # not glibc: nothing to do
    assert memory.tune_allocator() is False


def test_release_library_pages_advises_read_only_startup_mappings_only(monkeypatch, tmp_path) -> None:  # type: ignore[no-untyped-def]
    calls: list[tuple[int, int, int]] = []

    class FakeLibc:
        def madvise(self, addr: int, length: int, advice: int) -> int:
            calls.append((addr, length, advice))
            return 0

        def mallopt(self, param: int, value: int) -> int:
            return 1

        def malloc_trim(self, pad: int) -> int:
            return 1

    maps = tmp_path / "maps"
    maps.write_text(
        "1000-3000 r--p 00000000 08:01 1 /venv/llvmlite/binding/libllvmlite.so\n"
        "3000-8000 r-xp 00002000 08:01 1 /venv/llvmlite/binding/libllvmlite.so\n"
        "8000-9000 rw-p 00007000 08:01 1 /venv/llvmlite/binding/libllvmlite.so\n"
        "9000-a000 r-xp 00000000 08:01 2 /venv/cv2/cv2.abi3.so\n"
        "a000-b000 r-xp 00000000 08:01 3 /usr/lib/libc.so.6\n"
        "b000-c000 rw-p 00000000 00:00 0 \n")
    monkeypatch.setattr(memory, "_libc", lambda: FakeLibc())
    assert memory.release_library_pages(str(maps)) == 0x2000 + 0x5000 + 0x1000
    assert calls == [(0x1000, 0x2000, 21), (0x3000, 0x5000, 21), (0x9000, 0x1000, 21)]


def test_release_library_pages_drops_llvm_pages_and_kernels_still_run() -> None:
    """On this kernel (MADV_PAGEOUT, Linux 5.4+): numba's LLVM pages leave the resident set,
    and a cached kernel and a fresh compile still run after it."""
    code = """
import re, numba, numpy as np
from lightprobe.device import allocator as memory
def llvm_kb():
    kb, cur = 0, False
    for line in open('/proc/self/smaps'):
        if re.match(r'^[0-9a-f]+-[0-9a-f]+ ', line):
            cur = 'libllvmlite' in line
        elif cur and line.startswith('Rss:'):
            kb += int(line.split()[1])
    return kb
f = numba.njit(lambda a: a.sum() * 2.0)
assert f(np.ones(10)) == 20.0
before = llvm_kb()
done = memory.release_library_pages()
after = llvm_kb()
g = numba.njit(lambda a: a.max() + 1.0)
print(before, done, after, f(np.ones(3)), g(np.arange(4.0)))
"""
    # MADV_PAGEOUT leaves a page another process maps too: this test process's own LLVM pages
    # (resident if earlier tests compiled here) would keep the child's resident
    from lightprobe.device import allocator as memory

    memory.release_library_pages()
    out = subprocess.run([sys.executable, "-c", code], check=True, capture_output=True, text=True,
                         cwd=Path(__file__).resolve().parents[1])
    before, done, after, f3, g4 = out.stdout.split()
    if int(done) == 0:
        pytest.skip("madvise(MADV_PAGEOUT) not supported here")
    assert int(before) > 10_000, out.stdout  # > 10 MB of LLVM resident after one compile
    assert int(after) < int(before) / 4, out.stdout
    assert (float(f3), float(g4)) == (6.0, 4.0)


def test_skip_numba_blas_probe_keeps_scipy_linalg_out_and_numba_whole() -> None:
    """The service's numba loads without scipy.linalg (16 MB); a service kernel from the cache, a
    jitted np.convolve (the probe's one user, now a loop) and a jitted np.dot (BLAS bound when it
    compiles) still give NumPy's results, and scipy.linalg still imports afterwards."""
    code = """
import sys
import numpy as np
from lightprobe.device import allocator as memory
assert memory.skip_numba_blas_probe() is True
from lightprobe.core.sphere import equirect_directions
from lightprobe.device.formats.sgfit import _cell_power
a = np.random.default_rng(1).random((8, 16, 3)).astype(np.float32)
p = _cell_power(a, np.ones(8), np.zeros(128, np.int32), 1)
assert np.allclose(p[0], a.reshape(-1, 3).sum(axis=0), rtol=1e-6)
import numba
conv = numba.njit(lambda x, y: np.convolve(x, y))
x, y = np.arange(5.0), np.array([1.0, -2.0, 0.5])
assert np.allclose(conv(x, y), np.convolve(x, y))
print("linalg_before_dot", "scipy.linalg" in sys.modules)
dot = numba.njit(lambda x, y: np.dot(x, y))
assert dot(np.arange(3.0), np.arange(3.0)) == 5.0
import scipy.linalg
assert scipy.linalg.norm([3.0, 4.0]) == 5.0
assert memory.skip_numba_blas_probe() is False
"""
    out = subprocess.run([sys.executable, "-c", code], check=True, capture_output=True, text=True,
                         cwd=Path(__file__).resolve().parents[1])
    assert "linalg_before_dot False" in out.stdout, out.stdout
