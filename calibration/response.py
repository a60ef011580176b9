"""Camera response: the project's one Debevec-Malik solver, Robertson's estimate, raw linearity.

Processed (RGB8) output: the inverse response ``exp(g(z))`` is solved from an exposure bracket
with Debevec & Malik's least squares [1, eq. 3] (:func:`solve_debevec`, our own sparse solve:
it also works on the tiny stacks where OpenCV's ``CalibrateDebevec`` asserts) or Robertson's ML
estimate [2] (``cv2.createCalibrateRobertson``). ``lightprobe fuse`` (estimating a stack's own
response) and the technicians' ``lightprobe calibrate response`` both call
:func:`response_from_stack`. Every table goes through the one repair rule
(:func:`device.core.calibration.repair_inverse`) and is normalised so the full-scale code maps
to 1 (:meth:`Response.normalised`, as :meth:`Response.linear`).

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
   SIGGRAPH 1997, sec. 2.1 and the appendix's gsolve.m.
.. [2] M. A. Robertson, S. Borman, R. L. Stevenson, "Estimation-theoretic approach to dynamic
   range enhancement using multiple exposures", J. Electronic Imaging 12(2), 2003.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from device.core.calibration import Response, repair_inverse
from device.core.errors import InputError
from drivers.base import Camera, Controls, Frame

__all__ = ["SMOOTHNESS", "LinearityReport", "capture_bracket", "compare_inverse", "gsolve", "linearity_check",
           "response_from_stack", "sample_pixels", "solve_debevec"]

LEVELS = 256
SMOOTHNESS = 160.0  # lambda per data row (gsolve); the sim bracket and synthetic stacks hold at it


def _hat(z: np.ndarray) -> np.ndarray:
    """Debevec-Malik weight w(z) = min(z, 255 - z) + 1 [1, eq. 4] (never zero)."""
    return np.minimum(z, LEVELS - 1 - z).astype(np.float64) + 1.0


def sample_pixels(frames: Sequence[np.ndarray], channel: int, count: int = 256, seed: int = 0) -> np.ndarray:
    """Flat pixel indices of about ``count`` samples, stratified over the values of the middle
    exposure so every part of the curve is constrained (the paper's N (P - 1) > 255 advice),
    skipping pixels that never change (black in every frame, e.g. outside a fisheye's image
    circle, or saturated in every frame) when enough others exist. Deterministic."""
    stack = np.stack([np.asarray(f)[..., channel].ravel() for f in frames])
    useful = np.flatnonzero((stack.max(axis=0) > 8) & (stack.min(axis=0) < LEVELS - 9))
    if useful.size < 16:
        useful = np.arange(stack.shape[1])  # tiny or flat stacks: take what there is
    mid = stack[stack.shape[0] // 2, useful]
    rng = np.random.default_rng(seed)
    bins = min(count, 64)
    per = max(1, count // bins)
    picks: list[np.ndarray] = []
    for lo in np.linspace(0, LEVELS, bins + 1)[:-1]:
        cand = useful[(mid >= lo) & (mid < lo + LEVELS / bins)]
        if cand.size:
            picks.append(rng.choice(cand, size=min(per, cand.size), replace=False))
    out = np.concatenate(picks) if picks else np.empty(0, np.int64)
    if out.size < count:  # top up with uniformly random useful pixels
        extra = rng.choice(useful, size=min(count - out.size, useful.size), replace=False)
        out = np.union1d(out, extra)
    return np.unique(out.astype(np.int64))


def gsolve(z: np.ndarray, log_t: np.ndarray, smoothness: float) -> np.ndarray:
    """gsolve.m [1]: samples ``z`` (N, P) ints, ``log_t`` (P,) -> g (256,) with g(128) = 0.

    Minimises ``sum_ij [w(z_ij) (g(z_ij) - ln X_i - ln t_j)]^2 + lambda sum_z [w(z) g''(z)]^2``
    (eq. 3) through its sparse normal equations (SuperLU, float64: no multi-threaded dense LAPACK,
    which crawls on a busy 2-core board). ``lambda`` is per data row: the smoothness term is
    scaled by ``N P / 256`` so that the balance does not change with the number of samples.
    """
    import scipy.sparse as sp
    import scipy.sparse.linalg as spla

    n, p = z.shape
    w = _hat(z).ravel()
    k = np.arange(n * p)
    ii = np.repeat(np.arange(n), p)
    # Data term w (g(Z_ij) - ln X_i) = w ln t_j                                            (eq. 3)
    rows, cols, vals = [k, k], [z.ravel(), LEVELS + ii], [w, -w]
    b = [w * np.tile(log_t, n)]
    r0 = n * p
    # Fix the curve: g(128) = 0
    rows.append(np.array([r0]))
    cols.append(np.array([LEVELS // 2]))
    vals.append(np.array([1.0]))
    b.append(np.zeros(1))
    # Smoothness sqrt(lambda) w(z) g''(z) = 0 for z = 1..254                                (eq. 3)
    zz = np.arange(1, LEVELS - 1)
    wz = np.sqrt(smoothness * n * p / LEVELS) * _hat(zz)
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


def solve_debevec(frames: Sequence[np.ndarray], times: Sequence[float], *, smoothness: float = SMOOTHNESS,
                  samples: int = 256) -> Response:
    """Inverse response (256, 3) of 8-bit RGB frames of one static scene at ``times`` [1]."""
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
        inv[:, c] = np.exp(np.clip(gsolve(z, np.log(t), smoothness), -700, 700))
    return Response("table", 8, repair_inverse(inv), "debevec").normalised()


def response_from_stack(images: Sequence[np.ndarray], exposures_s: Sequence[float], *,
                        method: str = "debevec", samples: int = 400, smoothness: float = SMOOTHNESS) -> Response:
    """Inverse response of 8-bit RGB frames of one static scene at ``exposures_s``.

    Raises InputError (a ValueError) for fewer than 2 frames, mismatched sizes, non-uint8
    frames or a failed solve.
    """
    if len(images) < 2 or len(images) != len(exposures_s):
        raise InputError("need at least 2 frames and one exposure time per frame", param="times")
    imgs = [np.ascontiguousarray(im) for im in images]
    if any(im.dtype != np.uint8 or im.shape != imgs[0].shape or im.ndim != 3 for im in imgs):
        raise InputError("frames must be uint8 (H, W, 3) of one size", param="IMG")
    if method == "debevec":
        return solve_debevec(imgs, exposures_s, smoothness=smoothness, samples=samples)
    if method == "robertson":
        import cv2

        times = np.asarray(exposures_s, dtype=np.float32)
        if not np.all(np.isfinite(times) & (times > 0)):
            raise InputError("exposure times must be positive", param="times")
        table = cv2.createCalibrateRobertson().process(imgs, times).reshape(LEVELS, 3)
        return Response("table", 8, repair_inverse(table), method).normalised()
    raise InputError(f"unknown response method {method!r} (debevec or robertson)", param="--method")


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
