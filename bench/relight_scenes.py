"""The scenes, maps and helpers the relighting benchmarks share (``lightprobe.bench.relight``, ``lightprobe.bench.relight_sg``)."""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

__all__ = ["MAPS", "ROOT", "SHARED", "rel_rms", "scene_file", "timeit"]

ROOT = Path(__file__).resolve().parent.parent
SHARED = ROOT.parent / "shared" / "data"
MAPS = ["studio_small_03_1k.hdr", "rooitou_park_1k.hdr", "potsdamer_platz_1k.hdr", "lebombo_1k.hdr",
        "dikhololo_night_1k.hdr", "interior_blender.exr"]


def scene_file(d: Path, movable: bool, res: int, width: int = 320, height: int = 240) -> Path:
    doc = {"version": 1,
           "materials": {"clay": {"type": "phong", "kd": [0.6, 0.5, 0.4], "ks": [0.2, 0.2, 0.2], "exponent": 20},
                         "floor": {"type": "lambert", "kd": [0.5, 0.5, 0.5]}},
           "objects": [{"name": "spot", "mesh": str((SHARED / "meshes" / "spot.obj").resolve()),
                        "material": "clay", "movable": movable}],
           "ground": {"y": "auto", "size": 3.0, "resolution": res, "material": "floor"},
           "camera": {"position": [2.0, 1.2, 2.5], "look_at": [0, -0.2, 0.4], "fov_deg": 40,
                      "width": width, "height": height}}
    p = d / f"spot_{'movable' if movable else 'static'}_{res}.json"
    p.write_text(json.dumps(doc))
    return p


def rel_rms(y: np.ndarray, yr: np.ndarray) -> float:
    return float(np.sqrt(((y - yr) ** 2).sum() / max((yr ** 2).sum(), 1e-300)))


def timeit(fn, reps: int) -> dict[str, float]:  # type: ignore[no-untyped-def]
    """Wall-clock min / median and process-CPU min (ms) over ``reps`` runs after one warm-up."""
    import os

    fn()
    ts, cs = [], []
    for _ in range(reps):
        t0, c0 = time.perf_counter(), time.process_time()
        fn()
        ts.append(time.perf_counter() - t0)
        cs.append(time.process_time() - c0)
    return {"min": round(min(ts) * 1e3, 1), "median": round(float(np.median(ts)) * 1e3, 1),
            "cpu_min": round(min(cs) * 1e3, 1), "load1": round(os.getloadavg()[0], 2)}
