"""Camera response: the project's one Debevec-Malik solver, Robertson's estimate, raw linearity.

Processed (RGB8) output: the inverse response ``exp(g(z))`` is solved from an exposure bracket
with Debevec & Malik's least squares [1, eq. 3] (:func:`solve_debevec`: samples from smooth
regions, robustly reweighted; it also works on the tiny stacks where OpenCV's
``CalibrateDebevec`` asserts) or Robertson's ML estimate [2] (``cv2.createCalibrateRobertson``).
Either way the bracket also gives ``log_sigma``, the scatter of one sample per code, measured on
every pixel through the joint histograms of consecutive exposures [3] (:func:`code_scatter`),
which the HDR merge uses as its noise model.
``lightprobe fuse`` (estimating a stack's own response) and the technicians' ``lightprobe
calibrate response`` both call :func:`response_from_stack` / :func:`solve_debevec`. Every table
goes through the one repair rule (:func:`device.core.calibration.repair_inverse`) and is
normalised so the full-scale code maps to 1 (:meth:`Response.normalised`, as
:meth:`Response.linear`).

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
.. [3] S. Mann, R. Picard, "On being 'undigital' with digital cameras", IS&T 1995, and
   M. Grossberg, S. Nayar, "Determining the camera response from images: what is knowable?",
   PAMI 2003: the response from joint histograms of exposure pairs (comparametric equations).
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from device.core.calibration import Response, repair_inverse
from device.core.errors import InputError
from drivers.base import Camera, Controls, Frame

__all__ = ["SAMPLES", "SMOOTHNESS", "LinearityReport", "PairBins", "capture_bracket", "code_scatter",
           "compare_inverse", "gsolve", "linearity_check", "pair_bins", "response_from_stack", "sample_pixels",
           "solve_debevec"]

LEVELS = 256
SMOOTHNESS = 40.0  # lambda of eq. 3 per data row (gsolve)
SAMPLES = 3000  # sampled pixels per channel
CENSOR = 3  # codes within this many of 0 or 255 are clipped: censored data, not values
IRLS_ROUNDS = 3


def _hat(z: np.ndarray) -> np.ndarray:
    """Debevec-Malik weight w(z) = min(z, 255 - z) + 1 [1, eq. 4] (never zero)."""
    return np.minimum(z, LEVELS - 1 - z).astype(np.float64) + 1.0


@dataclass(frozen=True)
class PairBins:
    """The joint histogram of one channel over consecutive exposures (sorted by time): bin ``k``
    holds ``count[k]`` pixels showing code ``za[k]`` in the longer exposure and ``zb[k]`` in the
    shorter, whose log exposure ratio is ``dlog_t[k]``."""

    za: np.ndarray
    zb: np.ndarray
    dlog_t: np.ndarray
    count: np.ndarray


def pair_bins(frames: Sequence[np.ndarray], times: Sequence[float] | np.ndarray, channel: int) -> PairBins:
    """Joint code histograms of consecutive exposures for one channel: every pixel of the stack
    enters, codes within :data:`CENSOR` of either end (clipped) are left out."""
    t = np.asarray(times, np.float64)
    order = np.argsort(t, kind="stable")
    za, zb, dl, cnt = [], [], [], []
    for short, long_ in itertools.pairwise(order):
        a = np.asarray(frames[long_])[..., channel].ravel().astype(np.int64)
        b = np.asarray(frames[short])[..., channel].ravel().astype(np.int64)
        ok = (a >= CENSOR) & (a <= LEVELS - 1 - CENSOR) & (b >= CENSOR) & (b <= LEVELS - 1 - CENSOR)
        h = np.bincount(a[ok] * LEVELS + b[ok], minlength=LEVELS * LEVELS)
        k = np.flatnonzero(h)
        za.append(k // LEVELS)
        zb.append(k % LEVELS)
        dl.append(np.full(k.size, np.log(t[long_]) - np.log(t[short])))
        cnt.append(h[k].astype(np.float64))
    if not za:
        return PairBins(*(np.empty(0, np.int64),) * 2, np.empty(0), np.empty(0))  # type: ignore[arg-type]
    return PairBins(np.concatenate(za), np.concatenate(zb), np.concatenate(dl), np.concatenate(cnt))


def sample_pixels(stack: np.ndarray, count: int, seed: int = 0) -> np.ndarray:
    """Flat pixel indices of about ``count`` samples of one channel's stack ``(P, H, W)`` uint8.

    Only pixels that change with exposure (not black in every frame, e.g. outside a fisheye's
    image circle, nor saturated in every frame) and sit in smooth regions (their largest
    deviation from the 5 x 5 mean over all frames is in the lower half): on real photographs
    edge pixels carry JPEG ringing, demosaicing and sub-pixel misregistration, and a handful of
    them bend the curve. Stratified over the middle exposure's codes so every part of the curve
    is constrained (the paper's N (P - 1) > 255 advice). Tiny or flat stacks take what there is.
    Deterministic."""
    import cv2

    p, h, w = stack.shape
    flat = stack.reshape(p, -1)
    useful = (flat.max(axis=0) > 8) & (flat.min(axis=0) < LEVELS - 9)
    if h >= 5 and w >= 5 and int(useful.sum()) >= 64:
        dev = np.zeros(h * w, np.float32)
        for f in stack:
            x = f.astype(np.float32)
            np.maximum(dev, np.abs(x - cv2.blur(x, (5, 5))).ravel(), out=dev)
        useful &= dev <= np.percentile(dev[useful], 50)
    idx = np.flatnonzero(useful)
    if idx.size < 16:
        idx = np.arange(h * w)
    mid = flat[p // 2, idx].astype(np.int64)
    rng = np.random.default_rng(seed)
    bins = min(count, 64)
    per = max(1, count // bins)
    picks = [np.empty(0, np.int64)]
    for lo in np.linspace(0, LEVELS, bins + 1)[:-1]:
        cand = idx[(mid >= lo) & (mid < lo + LEVELS / bins)]
        if cand.size:
            picks.append(rng.choice(cand, size=min(per, cand.size), replace=False))
    out = np.concatenate(picks)
    if out.size < count:  # top up with uniformly random pixels of the same kind
        out = np.union1d(out, rng.choice(idx, size=min(count - out.size, idx.size), replace=False))
    return np.unique(out.astype(np.int64))


def gsolve(z: np.ndarray, log_t: np.ndarray, smoothness: float,
           weights: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """gsolve.m [1]: samples ``z`` (N, P) ints, ``log_t`` (P,) -> (g (256,), ln X (N,)), g(128) = 0.

    Minimises ``sum_ij [w(Z_ij) (g(Z_ij) - ln X_i - ln t_j)]^2 + lambda sum_z [w(z) g''(z)]^2``
    (eq. 3) through its sparse normal equations (SuperLU, float64: no multi-threaded dense LAPACK,
    which crawls on a busy 2-core board). ``lambda`` is per data row: the smoothness term is
    scaled by ``N P / 256`` so that the balance does not change with the number of samples.
    ``weights`` (N, P) multiply the hat (robust reweighting).
    """
    import scipy.sparse as sp
    import scipy.sparse.linalg as spla

    n, p = z.shape
    w = _hat(z).ravel() if weights is None else _hat(z).ravel() * weights.ravel()
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
    return np.asarray(sol[:LEVELS], np.float64), np.asarray(sol[LEVELS:], np.float64)


def _solve_channel(z: np.ndarray, log_t: np.ndarray, smoothness: float, rounds: int) -> np.ndarray:
    """g of one channel: :func:`gsolve`, then ``rounds`` of iteratively reweighted least squares
    (Cauchy weights on the residuals ``g(Z_ij) - ln X_i - ln t_j``, scale from their median over
    well-exposed samples), so the samples a moving object or a misregistration put off the curve
    stop bending it."""
    g, lx = gsolve(z, log_t, smoothness)
    mid = (z > 10) & (z < LEVELS - 11)
    for _ in range(rounds):
        r = g[z] - lx[:, None] - log_t[None, :]
        s = 1.4826 * float(np.median(np.abs(r[mid]))) if mid.any() else 1.0
        u = r / (3.0 * max(s, 1e-4))
        g, lx = gsolve(z, log_t, smoothness, 1.0 / np.sqrt(1.0 + u * u))
    return g


def code_scatter(frames: Sequence[np.ndarray], times: Sequence[float] | np.ndarray, inverse: np.ndarray) -> np.ndarray:
    """``log_sigma`` (256, 3): how far one sample at code z scatters in log exposure under the
    response ``inverse``, measured on the bracket itself.

    Every pixel of consecutive exposures gives the disagreement ``ln X_a - ln X_b`` of its two
    estimates; averaged over the pixels of each code (count-weighted, clipped at three times the
    typical disagreement, so moving objects do not count) it is ``sigma(za)^2 + sigma(zb)^2``,
    split evenly between the two. It holds everything that makes samples at that code disagree:
    shot, read and JPEG noise, quantisation and the response's own error. Codes no pixel shows
    take their neighbours' value.
    """
    g = np.log(np.maximum(np.asarray(inverse, np.float64), 1e-300))
    out = np.empty((LEVELS, 3))
    for c in range(3):
        b = pair_bins(frames, times, c)
        if b.za.size == 0:
            out[:, c] = 1.0
            continue
        r2 = (g[b.za, c] - g[b.zb, c] - b.dlog_t) ** 2
        clip = 9.0 * float(np.average(np.minimum(r2, np.quantile(r2, 0.9)), weights=b.count))
        r2 = np.minimum(r2, clip)
        num = np.bincount(b.za, b.count * r2, LEVELS) + np.bincount(b.zb, b.count * r2, LEVELS)
        den = np.bincount(b.za, b.count, LEVELS) + np.bincount(b.zb, b.count, LEVELS)
        seen = den > 0
        ms = np.interp(np.arange(LEVELS), np.flatnonzero(seen), num[seen] / den[seen])
        out[:, c] = np.sqrt(np.maximum(ms / 2.0, 1e-8))
    return out


def solve_debevec(frames: Sequence[np.ndarray], times: Sequence[float], *, smoothness: float = SMOOTHNESS,
                  samples: int = SAMPLES, rounds: int = IRLS_ROUNDS) -> Response:
    """Inverse response (256, 3) of 8-bit RGB frames of one static scene at ``times`` [1], with
    the per-code scatter of the bracket (:func:`code_scatter`) as ``log_sigma``.

    Real photographs break the textbook solve on randomly sampled pixels: samples on edges see
    JPEG ringing, demosaicing and sub-pixel misregistration, and a handful of them bend the curve
    (2.5x OpenCV's subset disagreement on a real stack). Samples come from smooth regions
    (:func:`sample_pixels`) and outliers are reweighted away (:func:`_solve_channel`).
    """
    if len(frames) < 2:
        raise InputError("estimating a response needs at least 2 exposures (or give --response)",
                         param="--response")
    t = np.asarray(times, dtype=np.float64)
    if t.shape != (len(frames),) or not np.all(np.isfinite(t) & (t > 0)):
        raise InputError("exposure times must be positive, one per frame", param="times")
    if np.unique(t).size < 2:
        raise InputError("the exposure times of a bracket must differ", param="times")
    if not np.isfinite(smoothness) or smoothness <= 0:
        raise InputError(f"smoothness {smoothness!r} must be positive", param="--smoothness")
    g = np.empty((LEVELS, 3))
    for c in range(3):
        stack = np.stack([np.asarray(f)[..., c] for f in frames])
        idx = sample_pixels(stack, samples)
        z = stack.reshape(len(frames), -1)[:, idx].T.astype(np.int64)
        g[:, c] = _solve_channel(z, np.log(t), smoothness, rounds)
    inv = repair_inverse(np.exp(np.clip(g, -700, 700)))
    resp = Response("table", 8, inv, "debevec").normalised()
    return Response(resp.model, resp.bits, resp.inverse, resp.method, code_scatter(frames, t, resp.inverse))


def response_from_stack(images: Sequence[np.ndarray], exposures_s: Sequence[float], *,
                        method: str = "debevec", smoothness: float = SMOOTHNESS) -> Response:
    """Inverse response of 8-bit RGB frames of one static scene at ``exposures_s``, with its
    measured ``log_sigma``.

    Raises InputError (a ValueError) for fewer than 2 frames, mismatched sizes, non-uint8
    frames or a failed solve.
    """
    if len(images) < 2 or len(images) != len(exposures_s):
        raise InputError("need at least 2 frames and one exposure time per frame", param="times")
    imgs = [np.ascontiguousarray(im) for im in images]
    if any(im.dtype != np.uint8 or im.shape != imgs[0].shape or im.ndim != 3 for im in imgs):
        raise InputError("frames must be uint8 (H, W, 3) of one size", param="IMG")
    if method == "debevec":
        return solve_debevec(imgs, exposures_s, smoothness=smoothness)
    if method == "robertson":
        import cv2

        times = np.asarray(exposures_s, dtype=np.float32)
        if not np.all(np.isfinite(times) & (times > 0)):
            raise InputError("exposure times must be positive", param="times")
        table = cv2.createCalibrateRobertson().process(imgs, times).reshape(LEVELS, 3)
        resp = Response("table", 8, repair_inverse(table), method).normalised()
        return Response(resp.model, resp.bits, resp.inverse, resp.method,
                        code_scatter(imgs, exposures_s, resp.inverse))
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
