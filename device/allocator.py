"""Allocator settings for a small board (glibc; a no-op elsewhere).

The service allocates and frees frame-sized arrays (hundreds of kB to a few MB) from several
threads, 30 times a second. glibc's defaults keep such memory: one arena per thread that
allocated (up to 8 x cores), and a mmap threshold that grows after the first large free, after
which every large array lives on a heap that is trimmed only at its top. On the simulator that
held ~200 MB of freed memory (569 MB RSS for ~350 MB in use). :func:`tune_allocator` caps the
arenas at two and fixes the thresholds (arrays of 256 kB and more are mapped and unmapped,
freed heap tops beyond 1 MB are returned), as the environment variables ``MALLOC_ARENA_MAX``,
``MALLOC_MMAP_THRESHOLD_`` and ``MALLOC_TRIM_THRESHOLD_`` would; call it before threads start.
:func:`release_memory` returns what a one-off burst of allocations (building projection tables)
left behind, and :func:`release_library_pages` the start's library pages: numba links its cached
kernels with LLVM (``libllvmlite.so``, 180 MB on disk), which leaves ~40-65 MB of the library's
read-only pages resident although no kernel runs LLVM code, and OpenCV's module init (thousands
of bindings registered) leaves ~12 MB of which a frame's colour conversion uses ~3. They are
clean file pages, so the kernel would drop them under memory pressure anyway; they are dropped
now (``MADV_PAGEOUT``, Linux 5.4+), and whatever a later call needs faults back in from the page
cache. Writable and relocated pages are never touched (the advice is given for read-only
mappings only, and ``MADV_PAGEOUT`` never discards data). :func:`skip_numba_blas_probe` keeps
numba's import-time BLAS probe from loading all of ``scipy.linalg`` (16 MB RSS) into the service.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import gc
import os
import sys

__all__ = ["release_library_pages", "release_memory", "skip_numba_blas_probe", "tune_allocator"]

_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3
_M_ARENA_MAX = -8
_MADV_PAGEOUT = 21
_STARTUP_LIBS = ("libllvmlite", "cv2.abi3")  # mostly one-off pages (module doc)


def _libc() -> ctypes.CDLL | None:
    try:
        lib = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
    except OSError:
        return None
    return lib if hasattr(lib, "mallopt") and hasattr(lib, "malloc_trim") else None


def tune_allocator(arenas: int = 2, mmap_threshold: int = 256 * 1024, trim_threshold: int = 1 << 20) -> bool:
    """Apply the settings above unless the environment already sets them; True if glibc took
    them."""
    lib = _libc()
    if lib is None:
        return False
    ok = True
    for env, param, value in (("MALLOC_ARENA_MAX", _M_ARENA_MAX, arenas),
                              ("MALLOC_MMAP_THRESHOLD_", _M_MMAP_THRESHOLD, mmap_threshold),
                              ("MALLOC_TRIM_THRESHOLD_", _M_TRIM_THRESHOLD, trim_threshold)):
        if env not in os.environ:
            ok = bool(lib.mallopt(param, value)) and ok
    return ok


def skip_numba_blas_probe() -> bool:
    """Load numba's array maths without its BLAS probe; True if the probe was skipped.

    ``numba.np.arraymath`` asks at import whether SciPy's BLAS is there (``import
    scipy.linalg.cython_blas``, ``_HAVE_BLAS``): that loads all of ``scipy.linalg``, 16 MB RSS and
    0.15 s on the 2-core VM (measured 2026-12-06), for one use: the inner product of jitted
    ``np.convolve`` / ``np.correlate`` (a BLAS dot instead of a plain loop), which no kernel of the
    service calls. ``scipy.linalg`` is hidden while that module loads and visible again after it,
    so a later import of it works as usual (numba's ``np.dot`` and ``np.linalg`` bind BLAS when
    they are compiled, not through this probe). Call it before the first jitted call (numba
    imports the module when its CPU target starts); a no-op if either module is already loaded."""
    if "numba.np.arraymath" in sys.modules or "scipy.linalg" in sys.modules:
        return False
    sys.modules["scipy.linalg"] = None  # type: ignore[assignment]  # the import machinery's "not here"
    try:
        import numba.np.arraymath  # noqa: F401
    finally:
        del sys.modules["scipy.linalg"]
    return True


def release_memory() -> None:
    """Collect garbage, give freed heap memory back to the system, and the start's library pages."""
    gc.collect()
    lib = _libc()
    if lib is not None:
        lib.malloc_trim(0)
    release_library_pages()


def release_library_pages(maps: str = "/proc/self/maps") -> int:
    """Advise the kernel to reclaim the resident read-only pages of the libraries whose pages are
    mostly one-off (see the module doc); the bytes advised (0 where unsupported)."""
    lib = _libc()
    if lib is None or not hasattr(lib, "madvise"):
        return 0
    try:
        with open(maps) as f:
            lines = f.readlines()
    except OSError:
        return 0
    madvise = lib.madvise
    if hasattr(madvise, "restype"):  # a C function (64-bit addresses: not ctypes' default int)
        madvise.argtypes = [ctypes.c_void_p, ctypes.c_size_t, ctypes.c_int]
    done = 0
    for line in lines:
        parts = line.split()
        if len(parts) < 6 or "w" in parts[1] or not any(n in parts[5] for n in _STARTUP_LIBS):
            continue
        lo, hi = (int(x, 16) for x in parts[0].split("-"))
        if madvise(lo, hi - lo, _MADV_PAGEOUT) == 0:
            done += hi - lo
    return done
