"""Fusion benchmark: speed and accuracy of :func:`device.hdr.fuse` against OpenCV's MergeDebevec.

``run(out_dir, quick)`` follows the ``lightprobe bench NAME`` contract (``bench/cli.py``): it writes
``hdr_fusion.json`` and ``hdr_fusion.png`` into ``out_dir`` and returns ``{"summary": {...}, ...}``.

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

from device.core.calibration import Response

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

    from device.hdr.fusion import fuse

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
    result = {"summary": summary, "accuracy": acc, "timings_ms": {"lightprobe": ours_ts, "opencv": cv_ts}}
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
