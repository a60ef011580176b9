"""Camera response recovery from an exposure stack (Debevec & Malik 1997), pure numpy.

Solves, per channel, for the log inverse response ``g(z) = ln E(z)`` (256 levels) and the log
irradiance ``ln X_i`` of sampled pixels, minimising (Debevec-Malik eq. 3)

    sum_ij [w(Z_ij) (g(Z_ij) - ln X_i - ln t_j)]^2 + lambda sum_z [w(z) g''(z)]^2

with ``g(128) = 0`` fixing the scale and the hat ``w(z) = min(z, 255 - z) + 1``. Pixels are
sampled deterministically, stratified over the levels of the middle exposure so that every part of
the curve is constrained (the paper's advice: N (P - 1) > 255 samples), which also works on tiny
images where OpenCV's ``CalibrateDebevec`` asserts. The result is repaired to be finite and
monotone (:func:`device.hdr.fusion.sanitize_inverse`) and normalised to 1 at full scale.

References
----------
P. Debevec, J. Malik, "Recovering High Dynamic Range Radiance Maps from Photographs", SIGGRAPH 1997,
sec. 2.1 and the appendix's gsolve.m.
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence

import numpy as np

from calibration.model import Response
from device.errors import InputError

from .fusion import sanitize_inverse

__all__ = ["sample_pixels", "solve_debevec"]

LEVELS = 256


def _hat(z: np.ndarray) -> np.ndarray:
    return np.minimum(z, LEVELS - 1 - z).astype(np.float64) + 1.0


def sample_pixels(frames: Sequence[np.ndarray], channel: int, count: int = 256, seed: int = 0) -> np.ndarray:
    """Flat pixel indices stratified over the levels of the middle exposure (deterministic)."""
    mid = np.asarray(frames[len(frames) // 2])[..., channel].ravel()
    rng = np.random.default_rng(seed)
    bins = np.linspace(0, LEVELS, min(count, LEVELS) + 1)
    picks: list[int] = []
    for lo, hi in itertools.pairwise(bins):
        cand = np.flatnonzero((mid >= lo) & (mid < hi))
        if cand.size:
            picks.append(int(cand[rng.integers(cand.size)]))
    extra = count - len(picks)
    if extra > 0 and mid.size > len(picks):  # Top up with uniformly random pixels
        picks.extend(int(i) for i in rng.choice(mid.size, size=min(extra, mid.size), replace=False))
    return np.unique(np.asarray(picks, dtype=np.int64))


def _gsolve(z: np.ndarray, log_t: np.ndarray, smoothness: float) -> np.ndarray:
    """gsolve.m: z (N, P) ints, log_t (P,) -> g (256,).

    The system is sparse (2 entries per data row, 3 per smoothness row), so it is solved through
    its sparse normal equations with SuperLU: no multi-threaded dense LAPACK, which crawls on a
    busy 2-core board.
    """
    import scipy.sparse as sp
    import scipy.sparse.linalg as spla

    n, p = z.shape
    w = _hat(z).ravel()
    k = np.arange(n * p)
    ii = np.repeat(np.arange(n), p)
    # Data term w (g(Z_ij) - ln X_i) = w ln t_j                                            (eq. 3)
    rows = [k, k]
    cols = [z.ravel(), LEVELS + ii]
    vals = [w, -w]
    b = [w * np.tile(log_t, n)]
    r0 = n * p
    # Fix the curve: g(128) = 0
    rows.append(np.array([r0]))
    cols.append(np.array([LEVELS // 2]))
    vals.append(np.array([1.0]))
    b.append(np.zeros(1))
    # Smoothness lambda w(z) g''(z) = 0 for z = 1..254                                      (eq. 3)
    zz = np.arange(1, LEVELS - 1)
    wz = np.sqrt(smoothness) * _hat(zz)
    rr = r0 + 1 + np.arange(zz.size)
    for off, coef in ((-1, 1.0), (0, -2.0), (1, 1.0)):
        rows.append(rr)
        cols.append(zz + off)
        vals.append(coef * wz)
    b.append(np.zeros(zz.size))
    a = sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                      shape=(r0 + 1 + zz.size, LEVELS + n))
    rhs = np.concatenate(b)
    # Unsampled levels and pixels would make the normal matrix singular: a tiny ridge
    m = (a.T @ a + 1e-9 * sp.identity(LEVELS + n)).tocsc()
    sol = spla.spsolve(m, a.T @ rhs)
    return np.asarray(sol[:LEVELS], dtype=np.float64)


def solve_debevec(frames: Sequence[np.ndarray], times: Sequence[float], *, smoothness: float = 10.0,
                  samples: int = 200) -> Response:
    """Recover the inverse response (levels, 3) of 8-bit frames with known exposure times."""
    if len(frames) < 2:
        raise InputError("estimating a response needs at least 2 exposures (or give --response)",
                         param="--response")
    t = np.asarray(times, dtype=np.float64)
    if t.shape != (len(frames),) or not np.all(np.isfinite(t) & (t > 0)):
        raise InputError("exposure times must be positive, one per frame", param="times")
    if not np.isfinite(smoothness) or smoothness <= 0:
        raise InputError(f"smoothness {smoothness!r} must be positive", param="--smoothness")
    inv = np.empty((LEVELS, 3))
    for c in range(3):
        idx = sample_pixels(frames, c, samples)
        z = np.stack([np.asarray(f)[..., c].ravel()[idx] for f in frames], axis=1).astype(np.int64)
        inv[:, c] = np.exp(np.clip(_gsolve(z, np.log(t), smoothness), -700, 700))
    inv = sanitize_inverse(inv)
    inv = inv / max(float(inv[-1].max()), 1e-300)
    return Response("table", 8, inv, "debevec")
