"""numba's threading layer: one that is safe when two threads launch parallel kernels at once.

The service runs parallel kernels from more than one thread (the pipeline's frame, the
projection tables built behind it, on-demand samplers in worker threads). numba's ``workqueue``
layer, which it falls back to when neither OpenMP (``libgomp.so.1``, Debian's ``libgomp1``) nor
TBB loads, aborts the whole process when that happens ("Numba workqueue threading layer is
terminating: Concurrent access has been detected"): a unit built on a minimal image crashed so,
at install and at every start (an arm64 root under emulation, issue 46). So every ``lightprobe``
command asks numba for a thread-safe layer (:func:`select`, before numba loads: numba reads its
configuration once, at import), and the service checks at start which one loaded
(:func:`require_threadsafe`): ``omp`` or ``tbb``, or it refuses to start (exit 2) naming the
library to install. ``/status`` reports the layer as ``threading_layer``.
"""

from __future__ import annotations

import os
from collections.abc import MutableMapping

__all__ = ["SAFE_LAYERS", "ThreadingLayerError", "loaded_layer", "require_threadsafe", "select"]

# numba's names: "threadsafe" lets numba pick tbb or omp, whichever loads (tbb first)
SAFE_LAYERS = ("omp", "tbb")
_REQUEST = "threadsafe"
_HELP = ("install OpenMP's runtime (Debian: apt install libgomp1, libgomp.so.1) or TBB "
         "(pip install 'tbb>=2021.6')")


class ThreadingLayerError(RuntimeError):
    """No thread-safe numba threading layer could be loaded (the message names the library)."""


def select(env: MutableMapping[str, str] | None = None) -> str:
    """Ask numba for a thread-safe layer (``NUMBA_THREADING_LAYER=threadsafe``) unless the
    environment names one already (``omp``, ``tbb``, ``threadsafe``, ``safe``); must run before
    numba is imported. Returns what was asked for. ``workqueue`` and ``default``, which may
    give ``workqueue``, are replaced: they are not safe here."""
    env = os.environ if env is None else env
    asked = env.get("NUMBA_THREADING_LAYER", "").strip().lower()
    if asked in (*SAFE_LAYERS, "threadsafe", "safe"):
        return asked
    env["NUMBA_THREADING_LAYER"] = _REQUEST
    return _REQUEST


def _probe() -> None:
    import numpy as np

    _kernel()(np.zeros(64, np.float64))


_KERNEL = None


def _kernel():  # type: ignore[no-untyped-def]
    global _KERNEL
    if _KERNEL is None:
        import numba

        @numba.njit(parallel=True, cache=True, nogil=True)
        def fill(a):  # type: ignore[no-untyped-def]
            for i in numba.prange(a.shape[0]):
                a[i] = i
            return a

        _KERNEL = fill
    return _KERNEL


def loaded_layer() -> str | None:
    """The layer numba loaded, or None while no parallel kernel has run yet."""
    import numba

    try:
        return str(numba.threading_layer())
    except ValueError:  # "Threading layer is not initialized."
        return None


def require_threadsafe(launch: object = None) -> str:
    """Launch a parallel kernel (so that numba loads its layer) and return the layer's name;
    :class:`ThreadingLayerError` when none loaded or the one loaded is not thread-safe.
    ``launch``: the kernel launch to try (tests); default a one-line parallel loop."""
    import numba

    configured = str(getattr(numba.config, "THREADING_LAYER", "default")).lower()
    try:
        (launch or _probe)()  # type: ignore[operator]
    except ValueError as e:  # numba: "No threading layer could be loaded." and why
        raise ThreadingLayerError(
            f"no thread-safe numba threading layer could be loaded (asked for {configured!r}): {_HELP}; "
            f"numba said: {str(e).strip().splitlines()[0] if str(e).strip() else e!r}") from e
    layer = loaded_layer()
    if layer not in SAFE_LAYERS:
        raise ThreadingLayerError(
            f"numba loaded the {layer!r} threading layer, which aborts the process when two threads "
            f"launch kernels at once: set NUMBA_THREADING_LAYER=threadsafe and {_HELP}")
    return layer
