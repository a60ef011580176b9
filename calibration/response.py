"""Camera response from a bracketed static scene captured by the probe itself.

Processed (RGB8) output: the inverse response ``exp(g(z))`` is solved from an exposure bracket
with Debevec & Malik's least squares [1, eq. 3] (``cv2.createCalibrateDebevec``) or Robertson's
ML estimate [2] (``cv2.createCalibrateRobertson``). OpenCV 5's Robertson can return NaN for the
darkest codes, so :func:`clean_inverse` fills non-finite entries from their nearest finite
neighbour and makes the table non-decreasing (``Response.from_json`` requires it). Tables are
normalised so the mid code (128) maps to 1.

Raw output is linear after black-level subtraction; :func:`linearity_check` verifies that
instead: for consecutive exposures, the ratio of summed signals over pixels valid in both frames
must equal the exposure ratio; it reports the largest deviation in percent.

:func:`capture_bracket` drives any ``drivers.base.Camera``: it applies each exposure and waits for
a frame whose metadata shows it (the control latency of real sensors), averaging
``frames_per_exposure`` frames.

Dtype policy: frames uint8 / uint16; tables and statistics float64.

References
----------
.. [1] P. E. Debevec, J. Malik, "Recovering high dynamic range radiance maps from photographs",
   SIGGRAPH 1997.
.. [2] M. A. Robertson, S. Borman, R. L. Stevenson, "Estimation-theoretic approach to dynamic
   range enhancement using multiple exposures", J. Electronic Imaging 12(2), 2003.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from drivers.base import Camera, Controls, Frame

from .model import Response

__all__ = ["LinearityReport", "capture_bracket", "clean_inverse", "compare_inverse",
           "gsolve", "linearity_check", "response_from_stack"]


def clean_inverse(table: np.ndarray) -> np.ndarray:
    """(levels, 3) float64: non-finite/non-positive entries filled, non-decreasing, mid = 1."""
    t = np.array(table, dtype=np.float64).reshape(table.shape[0], -1)
    out = np.empty_like(t)
    for c in range(t.shape[1]):
        col = t[:, c]
        ok = np.isfinite(col) & (col > 0)
        if not np.any(ok):
            raise ValueError("response solve returned no finite values (is the bracket static and exposed?)")
        idx = np.arange(col.size)
        col = np.interp(idx, idx[ok], col[ok])  # nearest finite value at the ends
        out[:, c] = np.maximum.accumulate(col)
    mid = out[out.shape[0] // 2]
    return out / np.where(mid > 0, mid, 1.0)


def response_from_stack(images: Sequence[np.ndarray], exposures_s: Sequence[float], *,
                        method: str = "debevec", samples: int = 400, smoothness: float = 50.0) -> Response:
    """Inverse response of 8-bit RGB frames of one static scene at ``exposures_s``.

    Raises ValueError for fewer than 2 frames, mismatched sizes or non-uint8 frames.
    """
    if len(images) < 2 or len(images) != len(exposures_s):
        raise ValueError("need at least 2 frames and one exposure time per frame")
    imgs = [np.ascontiguousarray(im) for im in images]
    if any(im.dtype != np.uint8 or im.shape != imgs[0].shape or im.ndim != 3 for im in imgs):
        raise ValueError("frames must be uint8 (H, W, 3) of one size")
    times = np.asarray(exposures_s, dtype=np.float32)
    if not np.all(np.isfinite(times) & (times > 0)):
        raise ValueError("exposure times must be positive")
    if method == "debevec":
        stack = np.stack(imgs)  # (P, H, W, 3)
        table = np.stack([np.exp(gsolve(stack[..., c], times.astype(np.float64), samples, smoothness))
                          for c in range(3)], axis=1)
    elif method == "robertson":
        table = cv2.createCalibrateRobertson().process(imgs, times).reshape(256, 3)
    else:
        raise ValueError(f"unknown response method {method!r} (debevec or robertson)")
    return Response("table", 8, clean_inverse(table), method)


def _hat(z: np.ndarray) -> np.ndarray:
    """Debevec-Malik weight w(z) = min(z, 255 - z) + 1 [1, eq. 4] (never zero)."""
    return np.minimum(z, 255 - z).astype(np.float64) + 1.0


def _pick_samples(stack: np.ndarray, n: int) -> np.ndarray:
    """Flat pixel indices of ``n`` samples spread over the value range of the middle frame,
    skipping pixels black in every frame (outside a fisheye's image circle) or always saturated."""
    flat = stack.reshape(stack.shape[0], -1)
    useful = np.flatnonzero((flat.max(axis=0) > 8) & (flat.min(axis=0) < 247))
    if useful.size < 16:
        raise ValueError("bracket has too few pixels that change with exposure")
    mid = flat[flat.shape[0] // 2, useful].astype(np.int64)
    rng = np.random.default_rng(0)
    picks = []
    per = max(1, n // 64)
    for lo in range(0, 256, 4):  # stratified by value: every part of the curve is constrained
        cand = useful[(mid >= lo) & (mid < lo + 4)]
        if cand.size:
            picks.append(rng.choice(cand, size=min(per, cand.size), replace=False))
    out = np.concatenate(picks)
    if out.size < n:
        out = np.union1d(out, rng.choice(useful, size=min(n - out.size, useful.size), replace=False))
    return out


def gsolve(stack: np.ndarray, times: np.ndarray, samples: int = 200, smoothness: float = 10.0) -> np.ndarray:
    """Debevec-Malik log inverse response g(z), z = 0..255, of one channel [1, eq. 3].

    ``stack`` is (P, H, W) uint8. Minimises
    ``sum w(z_ij) (g(z_ij) - ln E_i - ln t_j)^2 + lambda sum w(z) g''(z)^2`` with g(128) = 0,
    solved through the sparse normal equations (float64).
    """
    P = stack.shape[0]
    idx = _pick_samples(stack, samples)
    Z = stack.reshape(P, -1)[:, idx].T.astype(np.int64)  # (N, P)
    N = Z.shape[0]
    n_eq = N * P + 1 + 254
    rows_l, cols_l, vals_l = [], [], []
    b = np.zeros(n_eq)
    # Data fit: w (g(z_ij) - ln E_i) = w ln t_j  [1, eq. 3]
    w = _hat(Z).ravel()
    rows = np.arange(N * P)
    rows_l += [rows, rows]
    cols_l += [Z.ravel(), 256 + np.repeat(np.arange(N), P)]
    vals_l += [w, -w]
    b[rows] = w * np.tile(np.log(times), N)
    # Fix the scale: g(128) = 0
    rows_l.append(np.array([N * P]))
    cols_l.append(np.array([128]))
    vals_l.append(np.array([1.0]))
    # Smoothness: lambda w(z) (g(z-1) - 2 g(z) + g(z+1)) = 0
    z = np.arange(1, 255)
    r = N * P + 1 + np.arange(254)
    ws = smoothness * _hat(z)
    rows_l += [r, r, r]
    cols_l += [z - 1, z, z + 1]
    vals_l += [ws, -2 * ws, ws]
    A = sp.csr_matrix((np.concatenate(vals_l), (np.concatenate(rows_l), np.concatenate(cols_l))),
                      shape=(n_eq, 256 + N))
    # Normal equations of the sparse system (well conditioned: every unknown is tied to data
    # or to its neighbours); float64 throughout.
    sol = spla.spsolve((A.T @ A).tocsc(), A.T @ b)
    return sol[:256]


def compare_inverse(estimate: Response, truth: Response, lo: int = 16, hi: int = 240) -> float:
    """Max relative error of ``estimate.inverse`` vs ``truth.inverse`` over codes lo..hi after
    the best common scale per channel (a response is only defined up to scale)."""
    e = estimate.inverse[lo : hi + 1]
    t = truth.inverse[lo : hi + 1]
    k = np.exp(np.mean(np.log(t) - np.log(e), axis=0))  # least squares in log
    return float(np.max(np.abs(e * k / t - 1.0)))


@dataclass(frozen=True)
class LinearityReport:
    """Raw linearity: per consecutive pair, measured signal ratio / exposure ratio - 1."""

    deviations_percent: tuple[float, ...]
    max_deviation_percent: float
    pixels_used: tuple[int, ...]

    def ok(self, tolerance_percent: float = 2.0) -> bool:
        return self.max_deviation_percent <= tolerance_percent


def linearity_check(frames: Sequence[np.ndarray], exposures_s: Sequence[float], black: float,
                    white: float, *, lo: float = 0.02, hi: float = 0.9) -> LinearityReport:
    """Check raw frames for linearity (module docs); valid pixels lie in (lo, hi) of the range."""
    order = np.argsort(exposures_s)
    span = white - black
    t = np.asarray(exposures_s, np.float64)
    devs, used = [], []
    for k in range(len(order) - 1):
        a, b = order[k], order[k + 1]
        # Select pixels on a third frame: selecting on za or zb would bias their sums by the
        # very noise that picked them.
        s = order[k + 2] if k + 2 < len(order) else order[k - 1] if k >= 1 else b
        za = np.asarray(frames[a], np.float64) - black
        zb = np.asarray(frames[b], np.float64) - black
        zs = np.asarray(frames[s], np.float64) - black
        ratio = t[b] / t[a]
        pred_b = zs * (t[b] / t[s])
        ok = (pred_b > lo * span * ratio) & (pred_b < hi * span) & (zs < hi * span) & (zs > lo * span)
        n = int(np.count_nonzero(ok))
        if n < 16:
            continue
        measured = zb[ok].sum() / za[ok].sum()
        devs.append(100.0 * (measured / ratio - 1.0))
        used.append(n)
    if not devs:
        raise ValueError("no exposure pair has enough unsaturated pixels above the noise floor")
    return LinearityReport(tuple(devs), float(np.max(np.abs(devs))), tuple(used))


async def capture_bracket(camera: Camera, exposures_s: Sequence[float], *, frames_per_exposure: int = 1,
                          gain: float | None = None, capture_timeout: float = 2.0) -> list[Frame]:
    """One frame per exposure (the average of ``frames_per_exposure``), metadata-verified.

    Frames whose ``meta.exposure_s`` is not the requested value (control latency) are skipped;
    more than ``control_latency_frames + 8`` skips raise TimeoutError.
    """
    out: list[Frame] = []
    patience = camera.capabilities.control_latency_frames + 8
    for t in exposures_s:
        await camera.apply(Controls(exposure_s=float(t), gain=gain))
        got: list[Frame] = []
        skipped = 0
        while len(got) < frames_per_exposure:
            f = await camera.capture(capture_timeout)
            if abs(f.meta.exposure_s - t) <= 1e-6 * t:
                got.append(f)
            else:
                skipped += 1
                if skipped > patience:
                    raise TimeoutError(f"exposure {t} s never showed in frame metadata")
        if frames_per_exposure > 1:
            mean = np.mean([g.data.astype(np.float64) for g in got], axis=0)
            data = np.rint(mean).astype(got[0].data.dtype)
            got[0] = Frame(data, got[0].meta, got[0].format, got[0].black_level, got[0].white_level)
        out.append(got[0])
    return out
