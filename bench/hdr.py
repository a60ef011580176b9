"""Fusion benchmark: speed and accuracy of :func:`lightprobe.device.hdr.fuse` against OpenCV, on a synthetic
stack, on every real stack in ``../shared/data/exposure_stacks`` and on the simulator's truth.

``run(out_dir, quick)`` follows the ``lightprobe bench NAME`` contract (``cli/bench.py``): it writes
``hdr_fusion.json`` and ``hdr_fusion.png`` into ``out_dir`` and returns ``{"summary": {...}, ...}``.

Real stacks (:func:`score_stack`, also what ``tests/test_hdr_real_stacks.py`` asserts): the
response is estimated from the whole stack by each method (ours: ``lightprobe fuse``'s own;
OpenCV's ``CalibrateDebevec`` + ``MergeDebevec`` and ``CalibrateRobertson`` +
``MergeRobertson``), then the even and the odd exposures are fused apart and compared
(:func:`lightprobe.device.hdr.quality.subset_consistency`: no ground truth needed); the whole stack's
fusion is compared with OpenCV Debevec's (log-luminance correlation, dynamic range). Frames wider
than ``max_width`` are downscaled (area average) first, as the tests do.

Simulator (:func:`simulator_accuracy`): VGA frames of the planner's bracket fused with the
truth response, against the simulator's noise-free radiance.

Stack: 3 x VGA 8-bit frames (1/20, 1/5, 4/5 s) of a smooth log-uniform scene spanning 1e3:1, from a
sensor with the simulator's noise (6000 e- full well, 2.5 e- read noise) and a gamma-2.2 response
that both merges are given exactly. Timing: median of N runs of each merge on the same frames
(after one warm-up run; numba compiles once and caches), wall clock and this process's CPU time;
the 1-minute load average is recorded because this box is shared. Accuracy: relative error against the
known radiance over pixels not saturated in the shortest frame, plus the error normalised by the
ideal estimator's standard deviation (shot + read noise Fisher bound: 0.674 is optimal).
"""

from __future__ import annotations

import json
import os
import time
from pathlib import Path
from typing import Any

import numpy as np

from lightprobe.core.calibration import Response

__all__ = ["run", "synthetic_stack"]

TIMES = (0.05, 0.2, 0.8)
FULL_WELL, READ_NOISE, GAMMA = 6000.0, 2.5, 2.2


def synthetic_stack(h: int = 480, w: int = 640, seed: int = 0) -> tuple[np.ndarray, list[np.ndarray], Response]:
    """(radiance (H, W, 3) float64, 3 uint8 frames, the exact response)."""
    import cv2

    rng = np.random.default_rng(seed)
    x = np.exp(rng.uniform(np.log(1e-3), np.log(1.2), (h, w, 3)))
    x = np.exp(cv2.GaussianBlur(np.log(x), (0, 0), 2.0))
    frames = []
    for t in TIMES:
        e = np.clip(x * t, 0, 2)
        el = rng.poisson(e * FULL_WELL) + rng.normal(0, READ_NOISE, e.shape)
        frames.append(np.rint(255 * np.clip(el / FULL_WELL, 0, 1) ** (1 / GAMMA)).astype(np.uint8))
    z = np.arange(256) / 255.0
    return x, frames, Response("table", 8, np.repeat((z**GAMMA)[:, None], 3, axis=1), "truth")


def _median_ms(fn: Any, n: int) -> tuple[float, float, list[float]]:
    """(median wall ms, median CPU ms of this process, wall samples). On a shared machine the
    CPU time is the steadier figure (it excludes time spent waiting for a core)."""
    fn()
    wall, cpu = [], []
    for _ in range(n):
        c0, t0 = time.process_time(), time.perf_counter()
        fn()
        wall.append((time.perf_counter() - t0) * 1e3)
        cpu.append((time.process_time() - c0) * 1e3)
    return float(np.median(wall)), float(np.median(cpu)), wall


def _errors(est: np.ndarray, x: np.ndarray, sel: np.ndarray) -> dict[str, float]:
    info = sum(np.where(x * t < 0.97, (t * FULL_WELL) ** 2 / (x * t * FULL_WELL + READ_NOISE**2), 0)
               for t in TIMES)
    rel = (np.abs(est - x) / x)[sel]
    zn = (np.abs(est - x) * np.sqrt(info))[sel]
    return {"median_rel_err": float(np.median(rel)), "p99_rel_err": float(np.percentile(rel, 99)),
            "median_err_over_ideal_sigma": float(np.median(zn)),
            "nonfinite": int((~np.isfinite(est[sel])).sum())}


def run(out_dir: Path, quick: bool = False) -> dict[str, Any]:
    import cv2
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numba

    from lightprobe.device.hdr.fusion import fuse

    n = 20 if quick else 100
    x, frames, resp = synthetic_stack()
    ours_ms, ours_cpu, ours_ts = _median_ms(lambda: fuse(frames, TIMES, resp), n)
    merge = cv2.createMergeDebevec()
    bgr = [np.ascontiguousarray(f[..., ::-1]) for f in frames]
    crf = np.ascontiguousarray(resp.inverse[:, None, ::-1], np.float32)
    tt = np.asarray(TIMES, np.float32)
    cv_ms, cv_cpu, cv_ts = _median_ms(lambda: merge.process(bgr, tt, crf), n)
    ours = fuse(frames, TIMES, resp).radiance.astype(np.float64)
    theirs = np.asarray(merge.process(bgr, tt, crf), np.float64)[..., ::-1]
    unsat = np.asarray((frames[0] < 255).all(axis=-1))
    sel = np.broadcast_to(unsat[..., None], x.shape)
    acc = {"lightprobe": _errors(ours, x, sel), "opencv_merge_debevec": _errors(theirs, x, sel)}
    summary = {
        "fusion_3xVGA_8bit_median_ms": ours_ms,
        "opencv_merge_debevec_median_ms": cv_ms,
        "speedup_vs_opencv": cv_ms / ours_ms,
        "fusion_cpu_ms": ours_cpu, "opencv_cpu_ms": cv_cpu,
        "load_average_1min": float(os.getloadavg()[0]),
        "median_rel_err": acc["lightprobe"]["median_rel_err"],
        "opencv_median_rel_err": acc["opencv_merge_debevec"]["median_rel_err"],
        "runs": n, "numba_threads": int(numba.get_num_threads()),
    }
    import asyncio

    from lightprobe.drivers.base import PixelFormat
    from lightprobe.sim.scenarios import default_shared_data

    shared = default_shared_data()
    stacks = run_stacks(shared, fit_runs=3)
    simulated = {f"{sc}/rgb8": asyncio.run(simulator_accuracy(sc, PixelFormat.RGB8, shared))
                 for sc in ("rooitou_park", "lebombo")}
    for name, r in stacks.items():
        for tag, row in (("", r), ("registered_", r.get("registered"))):
            if row is None:
                continue
            summary[f"{name}_{tag}even_odd_dlog"] = row["lightprobe"]["even_odd_dlog"]
            summary[f"{name}_{tag}labels_even_odd_dlog"] = row["lightprobe_labels"]["even_odd_dlog"]
            summary[f"{name}_{tag}opencv_debevec_even_odd_dlog"] = row["opencv_debevec"]["even_odd_dlog"]
            summary[f"{name}_{tag}opencv_robertson_even_odd_dlog"] = row["opencv_robertson"]["even_odd_dlog"]
            summary[f"{name}_{tag}correlation"] = row["lightprobe"]["log_correlation_vs_opencv_debevec"]
            summary[f"{name}_{tag}response_fit_s"] = row["lightprobe"]["response_fit_s"]
    result = {"summary": summary, "accuracy": acc, "stacks": stacks, "simulator": simulated,
              "timings_ms": {"lightprobe": ours_ts, "opencv": cv_ts}}
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "hdr_fusion.json").write_text(json.dumps(result, indent=1))
    fig, ax = plt.subplots(1, 2, figsize=(10, 4))
    ax[0].hist([ours_ts, cv_ts], bins=30, label=["lightprobe fuse", "cv2 MergeDebevec"])
    ax[0].set_xlabel("ms per 3 x VGA merge")
    ax[0].legend()
    for name, est in (("lightprobe fuse", ours), ("cv2 MergeDebevec", theirs)):
        rel = np.sort((np.abs(est - x) / x)[sel])
        ax[1].plot(rel, np.linspace(0, 1, rel.size), label=name)
    ax[1].set_xscale("log")
    ax[1].set_xlabel("relative error")
    ax[1].set_ylabel("fraction of pixels")
    ax[1].legend()
    fig.tight_layout()
    fig.savefig(out_dir / "hdr_fusion.png", dpi=100)
    plt.close(fig)
    return result


# ---- real stacks --------------------------------------------------------------------------------
STACKS = ("piccante_room_lamp", "makehdr_room_window", "pku_campus_trees")


def load_stack(shared_data: Path, name: str, max_width: int = 800) -> tuple[list[np.ndarray], list[float]]:
    """RGB uint8 frames (area-downscaled to ``max_width``) and exposure times of a shared stack."""
    import cv2

    from lightprobe.device.hdr.stack import read_stack, read_times_file

    d = Path(shared_data) / "exposure_stacks" / name
    images = sorted(p for p in d.iterdir() if p.suffix.lower() in (".jpg", ".jpeg", ".png", ".tif", ".tiff"))
    times = read_times_file(d / "exposure_times_seconds.txt", images)
    frames = read_stack(images)
    h, w = frames[0].shape[:2]
    if w > max_width:
        size = (max_width, round(h * max_width / w))
        frames = [cv2.resize(f, size, interpolation=cv2.INTER_AREA) for f in frames]
    return frames, times


def _opencv(frames: list[np.ndarray], times: list[float], method: str) -> Any:
    """A merge function of index lists with OpenCV's own response of the whole stack."""
    import cv2

    bgr = [np.ascontiguousarray(f[..., ::-1]) for f in frames]
    t = np.asarray(times, np.float32)
    merge: Any
    if method == "debevec":
        crf, merge = cv2.createCalibrateDebevec().process(bgr, t), cv2.createMergeDebevec()
    else:
        crf, merge = cv2.createCalibrateRobertson().process(bgr, t), cv2.createMergeRobertson()
        crf = np.nan_to_num(crf, nan=float(np.nanmin(crf)))  # OpenCV 5 Robertson: NaN at the darkest codes

    def fused(idx: list[int]) -> np.ndarray:
        return np.asarray(merge.process([bgr[i] for i in idx], t[idx], crf), np.float64)[..., ::-1]

    return fused


def _ours(frames: list[np.ndarray], fit: Any, deghost: bool) -> tuple[Any, list[float]]:
    """Our merge function of index lists, with the stack's own response and effective exposures
    (``fit``: :func:`lightprobe.device.hdr.stack.fit_response`, as ``lightprobe fuse`` has them), and those
    exposures' corrections of the labels."""
    from lightprobe.device.hdr.fusion import fuse
    from lightprobe.device.hdr.stack import fusion_settings

    response, exposures = fit.response, list(fit.exposures_s)
    settings = fusion_settings(response, deghost=deghost)

    def fused(idx: list[int]) -> Any:
        return fuse([frames[i] for i in idx], [exposures[i] for i in idx], response, settings=settings)

    return fused, [float(c) for c in fit.corrections]


def score_stack(frames: list[np.ndarray], times: list[float], fit_runs: int = 1) -> dict[str, dict[str, Any]]:
    """Per method: even-vs-odd consistency, dynamic range, correlation with OpenCV Debevec's
    merge of the whole stack, seconds; ours also the deghosting's rejected share, its agreement
    with ``--no-deghost``, the exposure corrections of the labels (``lightprobe_labels``: ours
    with the labels taken as exact) and ``response_fit_s``, the median of ``fit_runs`` timed
    fits of the stack's response (the first one is the fit scored)."""
    from lightprobe.device.hdr.quality import dynamic_range, log_correlation, subset_consistency
    from lightprobe.device.hdr.stack import fit_response

    t0 = time.perf_counter()
    fit = fit_response(frames, times)  # one fit for the deghosting on and off
    fit_times = [time.perf_counter() - t0]
    for _ in range(fit_runs - 1):  # timed again, the same fit
        t0 = time.perf_counter()
        fit_response(frames, times)
        fit_times.append(time.perf_counter() - t0)
    fit_s = float(np.median(fit_times))
    n = len(frames)
    even, odd, whole = list(range(0, n, 2)), list(range(1, n, 2)), list(range(n))
    out: dict[str, dict[str, Any]] = {}
    full: dict[str, np.ndarray] = {}
    for name, make in (("opencv_debevec", lambda: _opencv(frames, times, "debevec")),
                       ("opencv_robertson", lambda: _opencv(frames, times, "robertson")),
                       ("lightprobe", lambda: _ours(frames, fit, True)),
                       ("lightprobe_no_deghost", lambda: _ours(frames, fit, False)),
                       ("lightprobe_labels", lambda: _ours(frames, fit_response(frames, times, refine_exposures=False),
                                                          True))):
        t0 = time.perf_counter()
        fused = make()
        row: dict[str, Any] = {}
        if isinstance(fused, tuple):  # ours: (merge, exposure corrections)
            fused, row["exposure_corrections"] = fused
        a, e, o = fused(whole), fused(even), fused(odd)
        if not isinstance(a, np.ndarray):  # a FusionResult
            row["deghost_rejected_fraction"] = a.rejected_fraction
            a, e, o = a.radiance, e.radiance, o.radiance
        shared_fit = fit_s if name in ("lightprobe", "lightprobe_no_deghost") else 0.0  # each pays for it
        row.update(even_odd_dlog=subset_consistency(e, o), dynamic_range=dynamic_range(a),
                   seconds=time.perf_counter() - t0 + shared_fit)
        full[name] = a
        out[name] = row
    for name, row in out.items():
        row["log_correlation_vs_opencv_debevec"] = log_correlation(full[name], full["opencv_debevec"])
    out["lightprobe"]["vs_no_deghost_dlog"] = subset_consistency(full["lightprobe"], full["lightprobe_no_deghost"])
    out["lightprobe"]["response_fit_s"] = fit_s
    return out


# ---- the simulator's truth ----------------------------------------------------------------------
async def simulator_accuracy(scene: str, fmt: Any, shared_data: Path | None = None, seed: int = 11) -> dict[str, Any]:
    """VGA frames of ``scene`` in pixel format ``fmt``: a metering sweep, then the planner's
    bracket, fused with the truth response; fused x photometric scale / vignetting against the
    noise-free sensor-plane radiance over the clean field of view, on pixels not saturated in the
    shortest exposure."""
    from lightprobe.device.burst import (
        BracketPlanner,
        capture_burst,
        exposure_rates,
        field_of_view_mask,
    )
    from lightprobe.device.hdr import fuse_frames
    from lightprobe.sim.camera import SimCamera

    cam = SimCamera(scene, seed=seed, shared_data=shared_data)
    async with cam:
        mode = next(m for m in cam.capabilities.modes if m.format is fmt and m.width == 640)
        await cam.set_mode(mode)
        cal = cam.truth_calibration()
        if cal.response is None or cal.fisheye is None or cal.vignetting is None or cal.photometric is None:
            raise ValueError("the simulator's truth calibration is incomplete")
        full_scale = 1.0 if fmt.is_raw else cal.response.inverse[-1]
        fov = field_of_view_mask(cal.fisheye)
        planner = BracketPlanner(cam.capabilities.exposure_range)
        sweep = await capture_burst(cam, planner.plan(None), gain=1.0, timeout=60)
        first = fuse_frames(sweep, cal.response)
        exposures = planner.plan(exposure_rates(first.radiance, full_scale), saturated=first.saturated,
                                 mask=fov)
        frames = await capture_burst(cam, exposures, gain=1.0, timeout=60)
        res = fuse_frames(frames, cal.response)
        truth = cam.render_radiance_image()
    h, w = truth.shape[:2]
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    vig = cal.vignetting.factor(u, v)[..., None]
    est = res.radiance.astype(np.float64) * cal.photometric.scale / vig
    shortest = frames[int(np.argmin([f.meta.exposure_s for f in frames]))]
    unsat = (shortest.data < shortest.white_level).all(axis=-1)
    sel = fov & unsat
    rel = (np.abs(est - truth) / np.maximum(truth, 1e-30))[sel]
    lum = truth.max(axis=-1)[sel]
    return {
        "scene": scene, "format": fmt.value, "exposures_s": [float(t) for t in exposures],
        "n_exposures": len(exposures), "median_rel_err": float(np.median(rel)),
        "p99_rel_err": float(np.percentile(rel, 99)), "pixels": int(sel.sum()),
        "pixels_saturated_in_shortest": int((fov & ~unsat).sum()),
        "truth_dynamic_range": float(lum.max() / max(lum.min(), 1e-30)),
        "flagged_saturated": int(res.saturated[fov].sum()), "flagged_invalid": int(res.invalid[fov].sum()),
        "finite": bool(np.isfinite(res.radiance).all()),
    }


def run_stacks(shared_data: Path, fit_runs: int = 1) -> dict[str, Any]:
    """:func:`score_stack` of every stack in ``shared_data/exposure_stacks`` (with a times file),
    as it is and, where :func:`lightprobe.device.hdr.align.stack_shifts` finds it misregistered, registered
    (``"registered"``: every method fuses the same registered frames); ``fit_runs`` timed fits
    of each (the bench's median of 3, the tests' one)."""
    from lightprobe.device.hdr.align import align_stack

    root = Path(shared_data) / "exposure_stacks"
    names = sorted(d.name for d in root.iterdir() if (d / "exposure_times_seconds.txt").is_file())
    out = {}
    for name in names:
        frames, times = load_stack(shared_data, name)
        out[name] = {"frames": len(frames), "size": list(frames[0].shape[1::-1]),
                     **score_stack(frames, times, fit_runs)}
        registered, shifts = align_stack(frames)
        out[name]["shifts"] = [list(s) for s in shifts]
        if any(s != (0, 0) for s in shifts):  # every method given the same registered frames
            out[name]["registered"] = score_stack(registered, times, fit_runs)
    return out
