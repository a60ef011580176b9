"""Camera response: the project's one Debevec-Malik solver, Robertson's estimate, raw linearity.

Processed (RGB8) output: the inverse response ``exp(g(z))`` is solved from an exposure bracket
with Debevec & Malik's least squares [1, eq. 3] (:func:`gsolve`, all channels in one system;
:func:`fit_stack` / :func:`solve_debevec`: samples from smooth regions, robustly reweighted; it
also works on the tiny stacks where OpenCV's ``CalibrateDebevec`` asserts) or Robertson's ML
estimate [2] (``cv2.createCalibrateRobertson``). A stack fused with its own response
(``lightprobe fuse``) also has its frames' effective exposures solved for (:func:`fit_stack`,
as Mitsunaga & Nayar [4] do for unknown exposure ratios): shutter labels are nominal and a
phone changes its gain unlabelled. A calibration (:func:`solve_debevec`) keeps the labels: its
response is used later with the exposures the driver reports.
Either way the bracket also gives ``log_sigma`` and ``log_sigma_core``, the scatter of one sample
per code (its variance, tails included, and its typical spread), measured on every pixel through
the joint histograms of consecutive exposures [3] (:func:`code_scatter`), which the HDR merge
uses as its noise model.
``lightprobe fuse`` (estimating a stack's own response) and the technicians' ``lightprobe
calibrate response`` both call :func:`response_from_stack` / :func:`solve_debevec`. Every table
goes through the one repair rule (:func:`lightprobe.core.calibration.repair_inverse`) and is
normalised so the full-scale code maps to 1 (:meth:`Response.normalised`, as
:meth:`Response.linear`).

Raw output is linear after black-level subtraction; :func:`linearity_check` verifies that
instead: for consecutive exposures, the ratio of summed signals over pixels valid in both frames
must equal the exposure ratio; it reports the largest deviation in percent.

:func:`capture_bracket` drives any ``lightprobe.drivers.base.Camera``: it applies each exposure and waits for
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
.. [4] T. Mitsunaga, S. K. Nayar, "Radiometric self calibration", CVPR 1999: the response and the
   exposure ratios estimated together, from the labels as a start.
"""

from __future__ import annotations

import itertools
import warnings
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from lightprobe.core.calibration import Response, repair_inverse
from lightprobe.core.errors import InputError
from lightprobe.drivers.base import Camera, Controls, Frame

__all__ = ["SAMPLES", "SMOOTHNESS", "LinearityReport", "PairBins", "StackFit", "capture_bracket", "check_brightens",
           "code_scatter", "compare_inverse", "fit_stack", "gsolve", "linearity_check", "pair_bins",
           "response_from_stack", "sample_pixels", "solve_debevec"]

LEVELS = 256
SMOOTHNESS = 40.0  # lambda of eq. 3 per data row (gsolve)
SAMPLES = 3000  # sampled pixels per channel
SCATTER_QUANTILE = 0.6827  # of |r|: one standard deviation of Gaussian scatter (code_scatter)
SCATTER_MIN_COUNT = 20  # pixels a code needs for its own scatter (code_scatter)
CENSOR = 3  # codes within this many of 0 or 255 are clipped: censored data, not values
IRLS_ROUNDS = 3
EXPOSURE_RIDGE = 0.01  # gsolve: the exposure corrections' ridge, in units of a frame's data weight
REFINE_MIN_SHARE = 0.02  # fit_stack: a frame's exposure is refined when this share of its samples is well exposed
REFINE_MIN_SAMPLES = 100  # ... and at least this many (all channels): a thumbnail's few pixels say nothing
MAX_EXPOSURE_CORRECTION = float(np.log(2.0))  # fit_stack: beyond a factor 2 the labels are kept


def _uncensored(z: np.ndarray) -> np.ndarray:
    """Codes that are values, not clipped data (within :data:`CENSOR` of neither end)."""
    return (z >= CENSOR) & (z <= LEVELS - 1 - CENSOR)


def _well_exposed(z: np.ndarray) -> np.ndarray:
    """Samples clear of both ends' clipping, JPEG smear and crushed shadows."""
    return (z > 10) & (z < LEVELS - 11)


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
        ok = _uncensored(a) & _uncensored(b)
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


def gsolve(z: Sequence[np.ndarray], log_t: np.ndarray, smoothness: float,
           weights: Sequence[np.ndarray] | None = None, refine: np.ndarray | None = None
           ) -> tuple[np.ndarray, list[np.ndarray], np.ndarray]:
    """gsolve.m [1] for every channel at once: samples ``z[c]`` (N_c, P) ints of channel ``c``,
    ``log_t`` (P,) -> (g (256, C), ln X per channel (N_c,), d (P,)), g_c(128) = 0.

    Minimises ``sum_cij [w(Z_cij) (g_c(Z_cij) - ln X_ci - ln t_j - d_j)]^2 + lambda sum_cz
    [w(z) g_c''(z)]^2`` (eq. 3). ``lambda`` is per data row: each channel's smoothness term is
    scaled by ``N_c P / 256`` so that the balance does not change with the number of samples.
    ``weights[c]`` (N_c, P) multiply the hat (robust reweighting). Each ``ln X_i`` is the
    weighted mean of its own sample's terms, so it is eliminated in closed form and the normal
    equations shrink to the curves and the corrections (256 C + P unknowns, solved densely; a
    real stack's whole fit, 4 solves and the scatter, takes 0.2-0.5 s where one sparse system
    per channel with every sample's ``ln X`` took 5-13 s).

    ``d`` corrects the labelled log exposure of the frames marked in ``refine`` (the others keep
    ``d = 0``), shared by the channels: a camera's shutter labels are nominal (1/15 s for
    2^-4 s, 1/125 for 2^-7), and a label off by 4% bends the curve where that pair of frames
    dominates. Data fix the corrections only up to the eq.-3 ambiguity ``(g, ln X, ln t) ->
    k (g, ln X, ln t) + const``, so they are held to the labels on average, in level and in span
    (``sum d = 0``, ``sum d (ln t - mean) = 0`` over the refined frames, exactly, by solving in
    the complement of those two directions), with a weak ridge (:data:`EXPOSURE_RIDGE` of an
    average frame's data weight) for frames the data barely reach. Fewer than 3 refined
    frames leave nothing to refine.
    """
    import scipy.linalg as sla

    lt = np.asarray(log_t, np.float64)
    p = lt.size
    nch = len(z)
    free = np.zeros(p, bool) if refine is None else np.asarray(refine, bool)
    basis = np.zeros((p, 0))
    if free.sum() >= 3:  # directions of d that keep the level and the span of the labels
        cons = np.stack([np.ones(int(free.sum())), lt[free] - lt[free].mean()], axis=1)
        _, _, vt = np.linalg.svd(cons.T)
        basis = np.zeros((p, int(free.sum()) - 2))
        basis[free] = vt[2:].T
    nb = basis.shape[1]
    size = LEVELS * nch + nb
    nrm = np.zeros((size, size))
    rhs = np.zeros(size)
    zz = np.arange(1, LEVELS - 1)
    second = np.zeros((zz.size, LEVELS))
    for off, coef in ((-1, 1.0), (0, -2.0), (1, 1.0)):  # g''(z) = g(z - 1) - 2 g(z) + g(z + 1)
        second[np.arange(zz.size), zz + off] = coef
    data_w2 = np.zeros(p)
    sq = [(_hat(zc) if weights is None else _hat(zc) * weights[c]) ** 2 for c, zc in enumerate(z)]
    for c, (zc, a) in enumerate(zip(z, sq, strict=True)):
        n = zc.shape[0]
        data_w2 += a.sum(axis=0)
        # Eliminating ln X_i leaves each sample's terms weighted by M_i = diag(a_i) - a_i a_i^T / s_i
        m = a[:, :, None] * np.eye(p)[None] - a[:, :, None] * a[:, None, :] / a.sum(axis=1)[:, None, None]
        o = LEVELS * c
        pairs = (zc[:, :, None] * LEVELS + zc[:, None, :]).ravel()
        nrm[o:o + LEVELS, o:o + LEVELS] += np.bincount(pairs, m.ravel(), LEVELS * LEVELS).reshape(LEVELS, LEVELS)
        rhs[o:o + LEVELS] += np.bincount(zc.ravel(), (m @ lt).ravel(), LEVELS)
        if nb:
            mb = m @ basis  # (N, P, nb)
            cross = np.stack([np.bincount(zc.ravel(), mb[..., q].ravel(), LEVELS) for q in range(nb)], axis=1)
            nrm[o:o + LEVELS, LEVELS * nch:] -= cross
            nrm[LEVELS * nch:, o:o + LEVELS] -= cross.T
            msum = m.sum(axis=0)
            nrm[LEVELS * nch:, LEVELS * nch:] += basis.T @ msum @ basis
            rhs[LEVELS * nch:] -= basis.T @ (msum @ lt)
        # Smoothness sqrt(lambda) w(z) g''(z) = 0 for z = 1..254, and g(128) = 0             (eq. 3)
        sm = np.sqrt(smoothness * n * p / LEVELS) * _hat(zz)[:, None] * second
        nrm[o:o + LEVELS, o:o + LEVELS] += sm.T @ sm
        nrm[o + LEVELS // 2, o + LEVELS // 2] += 1.0
    if nb:  # the ridge: orthonormal basis, so |theta| = |d|
        nrm[LEVELS * nch:, LEVELS * nch:] += EXPOSURE_RIDGE * float(np.mean(data_w2[free])) * np.eye(nb)
    # Unsampled levels would make the normal matrix singular: a tiny ridge
    nrm[np.diag_indices(size)] += 1e-9
    try:
        with warnings.catch_warnings():  # codes no sample shows rest on the smoothness and the ridge alone
            warnings.simplefilter("ignore", sla.LinAlgWarning)
            sol = sla.solve(nrm, rhs, assume_a="pos", check_finite=False)
    except np.linalg.LinAlgError:  # rounding made it indefinite: least squares
        sol = np.linalg.lstsq(nrm, rhs, rcond=None)[0]
    g = sol[:LEVELS * nch].reshape(nch, LEVELS).T
    d = basis @ sol[LEVELS * nch:] if nb else np.zeros(p)
    lx = [np.sum(a * (g[zc, c] - lt - d), axis=1) / a.sum(axis=1) for c, (zc, a) in enumerate(zip(z, sq, strict=True))]
    return np.ascontiguousarray(g), lx, d


def _solve(z: Sequence[np.ndarray], log_t: np.ndarray, smoothness: float, rounds: int,
           refine: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """(g (256, C), d (P,)): :func:`gsolve`, then ``rounds`` of iteratively reweighted least
    squares (Cauchy weights on the residuals ``g(Z_ij) - ln X_i - ln t_j - d_j``, scale from
    their median over well-exposed samples, per channel), so the samples a moving object or a
    misregistration put off the curve stop bending it."""
    g, lx, d = gsolve(z, log_t, smoothness, refine=refine)
    for _ in range(rounds):
        wts = []
        for c, zc in enumerate(z):
            r = g[zc, c] - lx[c][:, None] - (log_t + d)[None, :]
            mid = _well_exposed(zc)
            s = 1.4826 * float(np.median(np.abs(r[mid]))) if mid.any() else 1.0
            u = r / (3.0 * max(s, 1e-4))
            wts.append(1.0 / np.sqrt(1.0 + u * u))
        g, lx, d = gsolve(z, log_t, smoothness, wts, refine=refine)
    return g, d


def _quantile_per_code(z: np.ndarray, a: np.ndarray, w: np.ndarray, total: np.ndarray, q: float) -> np.ndarray:
    """(LEVELS,): per code, the ``q`` quantile of the values ``a`` of the entries at that code
    ``z``, weighted by ``w`` (``total``: each code's weight). A code pair's ``|r|`` is one of a
    few discrete values (codes are integers), so the distribution function is drawn through the
    points half-way between consecutive values, where each value's weight is complete (a value
    stands for its rounding interval). Sorted by code, then value, the key ``code + share of the
    code's weight up to here`` rises through all entries: one search finds every code's place."""
    codes = np.arange(LEVELS)
    o = np.lexsort((a, z))
    z, a, w = z[o], a[o], w[o]
    cw = np.cumsum(w)
    first = np.searchsorted(z, codes)
    before = np.where(first > 0, cw[np.maximum(first - 1, 0)], 0.0)
    share = (cw - before[z]) / total[z]
    same_next = np.append(z[1:] == z[:-1], False)
    upper = np.where(same_next, (a + np.append(a[1:], 0.0)) / 2, a)  # where value k's weight is complete
    hi = np.minimum(np.searchsorted(z + share, codes + q), a.size - 1)
    lo = np.maximum(hi - 1, 0)
    prev = (hi > 0) & (z[lo] == codes)  # the point before, else (0, 0)
    u0 = np.where(prev, upper[lo], 0.0)
    f0 = np.where(prev, share[lo], 0.0)
    f = np.clip((q - f0) / np.maximum(share[hi] - f0, 1e-12), 0.0, 1.0)
    return u0 + f * (upper[hi] - u0)


def code_scatter(frames: Sequence[np.ndarray], times: Sequence[float] | np.ndarray,
                 inverse: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(log_sigma, log_sigma_core)``, each (256, 3): how far one sample at code z scatters in
    log exposure under the response ``inverse``, measured on the bracket itself.

    Every pixel of consecutive exposures gives the disagreement ``r = ln X_a - ln X_b`` of its two
    estimates, ``sigma(za)^2 + sigma(zb)^2`` in expectation, split evenly between the two codes.
    It holds everything that makes samples at that code disagree: shot, read and JPEG noise,
    quantisation and the response's own error. On real photographs that spread is heavy-tailed
    (edges, sub-pixel misregistration, leaves and clouds that moved), so two figures describe it:

    - ``log_sigma``, the root mean square of ``r`` over the pixels of each code (count-weighted,
      clipped at three times the typical disagreement, so moving objects do not count): the
      variance of a sample, tails included, which sums of many samples (the live map's
      footprints) and the deghosting's consistency test need;
    - ``log_sigma_core``, the half-width that holds :data:`SCATTER_QUANTILE` (68.3%) of the
      ``|r|`` of each code, one standard deviation for Gaussian scatter: the precision of a
      *typical* sample, which the merge weights by. On makehdr's room the rms is 1.2-2.3 times
      the core in green at codes 64-200, a ratio that varies from code to code: weighting by the
      rms let the tails set the precision of every sample at their codes.

    Codes no pixel shows (the core: fewer than :data:`SCATTER_MIN_COUNT`) take their neighbours'
    value.
    """
    g = np.log(np.maximum(np.asarray(inverse, np.float64), 1e-300))
    rms, core = np.empty((LEVELS, 3)), np.empty((LEVELS, 3))
    codes = np.arange(LEVELS)

    def per_sample(pair_var: np.ndarray, measured: np.ndarray) -> np.ndarray:  # half a pair's, gaps filled
        return np.sqrt(np.maximum(np.interp(codes, np.flatnonzero(measured), pair_var[measured]) / 2.0, 1e-8))

    for c in range(3):
        b = pair_bins(frames, times, c)
        if b.za.size == 0:
            rms[:, c] = core[:, c] = 1.0
            continue
        r = g[b.za, c] - g[b.zb, c] - b.dlog_t
        r2 = r**2
        clip = 9.0 * float(np.average(np.minimum(r2, np.quantile(r2, 0.9)), weights=b.count))
        r2 = np.minimum(r2, clip)
        num = np.bincount(b.za, b.count * r2, LEVELS) + np.bincount(b.zb, b.count * r2, LEVELS)
        den = np.bincount(b.za, b.count, LEVELS) + np.bincount(b.zb, b.count, LEVELS)
        seen = den > 0
        rms[:, c] = per_sample(num / np.maximum(den, 1.0), seen)
        half = _quantile_per_code(np.concatenate([b.za, b.zb]), np.abs(np.concatenate([r, r])),
                                  np.concatenate([b.count, b.count]), den, SCATTER_QUANTILE)
        enough = den >= SCATTER_MIN_COUNT
        core[:, c] = per_sample(half**2, enough if enough.sum() >= 2 else seen)  # a thumbnail: what it shows
    return rms, core


@dataclass(frozen=True)
class StackFit:
    """A stack's own response and the exposures it was fitted with: ``exposures_s`` are the
    labels ``labels_s`` times the corrections the data asked for (:func:`gsolve`; 1 where
    ``refined`` is False). Fuse the stack with ``exposures_s``: the response is consistent with
    those, not with the labels. ``rejected_correction``: the largest correction (factor) the
    data asked for when it was beyond belief and the labels were kept instead (else 1)."""

    response: Response
    exposures_s: np.ndarray
    labels_s: np.ndarray
    refined: np.ndarray
    rejected_correction: float = 1.0

    @property
    def corrections(self) -> np.ndarray:
        """Effective over labelled exposure, per frame."""
        return self.exposures_s / self.labels_s


def _check_bracket(frames: Sequence[np.ndarray], times: Sequence[float]) -> np.ndarray:
    """The labels as float64 after every check a response estimate (either method) needs: two
    frames or more, one positive time each, not all equal, and frames that brighten with them."""
    if len(frames) < 2:
        raise InputError("estimating a response needs at least 2 exposures (or give --response)",
                         param="--response")
    t = np.asarray(times, dtype=np.float64)
    if t.shape != (len(frames),) or not np.all(np.isfinite(t) & (t > 0)):
        raise InputError("exposure times must be positive, one per frame", param="times")
    if np.unique(t).size < 2:
        raise InputError("the exposure times of a bracket must differ", param="times")
    check_brightens(frames, t)
    return t


def check_brightens(frames: Sequence[np.ndarray], times: Sequence[float] | np.ndarray) -> None:
    """Raise :class:`InputError` (``times``) unless the longest-labelled frame is brighter than
    the shortest where both show the scene (codes not clipped in either): a stack taken with
    auto-exposure on, or labelled with another stack's times, does not change with its labels;
    a response fitted to it is noise, and a merge with a known one is too. Checked only where the
    labels span at least 2x and 100 samples show the scene in both."""
    t = np.asarray(times, np.float64)
    lo, hi = int(np.argmin(t)), int(np.argmax(t))
    if t[hi] < 2.0 * t[lo]:
        return
    a = np.asarray(frames[lo]).ravel()  # compared as they are: no wide copy of a full-size frame
    b = np.asarray(frames[hi]).ravel()
    if a.shape != b.shape:
        return
    both = _uncensored(a) & _uncensored(b)
    n = int(both.sum())
    if n < 100:
        return
    share = float((b[both] > a[both]).sum()) / n
    if share < 0.5:
        raise InputError(
            f"the frames do not get brighter with exposure time: the one labelled {t[hi]:.4g} s is brighter "
            f"than the one labelled {t[lo]:.4g} s at only {share:.0%} of the pixels both show (a bracket "
            f"gives nearly all). Was auto-exposure on, or are these another stack's times?", param="times")


def fit_stack(frames: Sequence[np.ndarray], times: Sequence[float], *, smoothness: float = SMOOTHNESS,
              samples: int = SAMPLES, rounds: int = IRLS_ROUNDS, refine_exposures: bool = True) -> StackFit:
    """Inverse response (256, 3) of 8-bit RGB frames of one static scene labelled ``times`` [1],
    with the per-code scatter of the bracket (:func:`code_scatter`) as ``log_sigma``, and, with
    ``refine_exposures``, the frames' effective exposures (:func:`gsolve`'s corrections).

    Real photographs break the textbook solve on randomly sampled pixels: samples on edges see
    JPEG ringing, demosaicing and sub-pixel misregistration, and a handful of them bend the curve
    (2.5x OpenCV's subset disagreement on a real stack). Samples come from smooth regions
    (:func:`sample_pixels`) and outliers are reweighted away (:func:`_solve`).

    Exposures are refined for frames with at least :data:`REFINE_MIN_SHARE` of their samples
    (and :data:`REFINE_MIN_SAMPLES`) well exposed (a white or black frame, or a thumbnail, has
    nothing to say); a correction beyond
    :data:`MAX_EXPOSURE_CORRECTION` means the labels and the pictures do not belong together,
    or the scene changed: then every label is kept and the response solved with them.
    """
    if not np.isfinite(smoothness) or smoothness <= 0:
        raise InputError(f"smoothness {smoothness!r} must be positive", param="--smoothness")
    t = _check_bracket(frames, times)
    zs = []
    for c in range(3):
        stack = np.stack([np.asarray(f)[..., c] for f in frames])
        idx = sample_pixels(stack, samples)
        zs.append(stack.reshape(len(frames), -1)[:, idx].T.astype(np.int64))
    refine = None
    if refine_exposures:
        good = sum(_well_exposed(zc).sum(axis=0) for zc in zs)
        refine = good >= max(REFINE_MIN_SHARE * sum(zc.shape[0] for zc in zs), REFINE_MIN_SAMPLES)
        if refine.sum() < 3:  # the level and the span take two: nothing left to refine
            refine = None
    g, d = _solve(zs, np.log(t), smoothness, rounds, refine)
    rejected = 1.0
    if np.max(np.abs(d)) > MAX_EXPOSURE_CORRECTION:
        rejected = float(np.exp(np.max(np.abs(d))))
        refine = None
        g, d = _solve(zs, np.log(t), smoothness, rounds, None)
    exposures = t * np.exp(d)
    inv = repair_inverse(np.exp(np.clip(g, -700, 700)))
    resp = Response("table", 8, inv, "debevec").normalised()
    resp = Response(resp.model, resp.bits, resp.inverse, resp.method, *code_scatter(frames, exposures, resp.inverse))
    return StackFit(resp, exposures, t, np.zeros(t.size, bool) if refine is None else refine, rejected)


def solve_debevec(frames: Sequence[np.ndarray], times: Sequence[float], *, smoothness: float = SMOOTHNESS,
                  samples: int = SAMPLES, rounds: int = IRLS_ROUNDS) -> Response:
    """:func:`fit_stack` with the labelled exposures taken as exact: the response a camera's
    calibration stores, to be used later with the exposures its driver reports."""
    return fit_stack(frames, times, smoothness=smoothness, samples=samples, rounds=rounds,
                     refine_exposures=False).response


def response_from_stack(images: Sequence[np.ndarray], exposures_s: Sequence[float], *,
                        method: str = "debevec", smoothness: float = SMOOTHNESS) -> Response:
    """Inverse response of 8-bit RGB frames of one static scene at ``exposures_s``, with its
    measured ``log_sigma``.

    Raises InputError (a ValueError) for fewer than 2 frames, mismatched sizes, non-uint8
    frames, frames that do not brighten with their times (either method) or a failed solve.
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

        times = _check_bracket(imgs, exposures_s).astype(np.float32)  # the checks the Debevec fit makes
        table = cv2.createCalibrateRobertson().process(imgs, times).reshape(LEVELS, 3)
        resp = Response("table", 8, repair_inverse(table), method).normalised()
        return Response(resp.model, resp.bits, resp.inverse, resp.method,
                        *code_scatter(imgs, exposures_s, resp.inverse))
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
