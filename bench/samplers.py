"""``lightprobe bench samplers [--quick]``: run time against error for every registered sampler.

Static part: on the six shared maps, for N in ``COUNTS``, each sampler's full-build time (fresh
state), its update time (next frame of a slowly changing stream, state kept: what a stateful
sampler saves) and its exact map-based errors (:mod:`lightprobe.device.sampling.metrics`: diffuse,
occluded, glossy). Pareto plot of error against build time (medians over the maps).

Nikodym et al. 2013 table: build time on a 360 x 90 hemisphere map (the top half of a 360 x 180
equirect, lower half black) at 200 / 1000 / 10000 lights, beside their N900 figures.

Temporal part (``lightprobe.sim.scenarios``: flashlight, flicker, switch, swing at 30 fps): at 512 fixed
Fibonacci normals, with the true irradiance computed exactly (base map once, plus each dynamic
disc's rasterised pixels per frame),

* flicker = RMS over frames and normals of ``dE_approx - dE_true`` (frame-to-frame changes),
  relative to the RMS true irradiance;
* lag (switch) = frames after a toggle until the per-frame diffuse error falls below twice its
  steady (median) value; mean and max over toggles;
* displacement = power-weighted angle (degrees) from each light to the nearest light of the
  previous frame (method-agnostic: needs no ids).

Plus the effect of Hemigon's filter parameters on those figures, and the Q2-Tree's incremental
update against its full build end to end and for the tree alone (:func:`incremental_bench`:
local, gain, noise and still sequences on the 1k maps and on the device's 512 x 256 equirect and
nside-64 HEALPix inputs). Times are ``min`` over repetitions (the box is shared; min is the
least disturbed run; medians are kept beside them), in milliseconds; the load average at the
start and end of the run is recorded (``summary.load_average``). ``--quick`` (3 maps, 3 counts,
one repetition, short sequences) takes about 20 s.
"""

from __future__ import annotations

import json
import os
import time
from collections.abc import Callable
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np

from lightprobe.core.imageio import read_hdr_image
from lightprobe.core.lightset import LightSet
from lightprobe.core.sphere import equirect_row_solid_angle, luminance
from lightprobe.device.sampling.metrics import ErrorReference, fibonacci_normals, light_arrays
from lightprobe.device.sampling.registry import available_samplers, make_sampler

__all__ = ["SceneTruth", "run", "temporal_metrics", "temporal_run"]

ROOT = Path(__file__).resolve().parent.parent
MAP_NAMES = ["studio_small_03_1k.hdr", "rooitou_park_1k.hdr", "potsdamer_platz_1k.hdr",
             "lebombo_1k.hdr", "dikhololo_night_1k.hdr", "interior_blender.exr"]
COUNTS = (16, 64, 200, 256, 1000, 4096, 10000)
QUICK_COUNTS = (64, 256, 1000)
NIKODYM_COUNTS = (200, 1000, 10000)
NIKODYM_N900_MS = {"pharr": (10, 10, 80), "hemigon": (150, 150, 170), "q2tree": (30, 50, 430)}
SCENARIOS = ("flashlight", "flicker", "switch", "swing")
FPS = 30.0
KINDS = ("diffuse", "occluded", "glossy")


def _shared_data() -> Path:
    return ROOT.parent / "shared" / "data"


def _min_time(fn: Callable[[], object], reps: int) -> tuple[float, float, float]:
    """``(wall, cpu, median wall)`` seconds: the minima over ``reps`` calls and the median wall
    time. On a shared box the minimum (and the process CPU time) is the best estimate of the
    unloaded time (single-threaded code)."""
    walls, best_cpu = [], np.inf
    for _ in range(max(1, reps)):
        t, c = time.perf_counter(), time.process_time()
        fn()
        best_cpu = min(best_cpu, time.process_time() - c)
        walls.append(time.perf_counter() - t)
    return float(np.min(walls)), float(best_cpu), float(np.median(walls))


# -- static: error and time on the shared maps -----------------------------------------------
def static_bench(maps: dict[str, np.ndarray], methods: list[str], counts: tuple[int, ...],
                 reps: int) -> list[dict[str, Any]]:
    rows = []
    for map_name, img in maps.items():
        ref = ErrorReference(img)
        img2 = img * np.float32(1.002)  # the next frame of a slowly changing stream
        for method in methods:
            for n in counts:
                s = make_sampler(method)
                s.sample(img, n)  # warm up (JIT, caches)
                lights: list[LightSet] = []

                def build(s: Any = s, n: int = n, lights: list[LightSet] = lights,
                          img: np.ndarray = img) -> None:
                    s.reset()
                    lights[:] = [s.sample(img, n)]

                t_build = _min_time(build, reps)
                frames = [img2, img]
                k = [0]

                def update(s: Any = s, n: int = n, k: list[int] = k,
                           frames: list[np.ndarray] = frames) -> None:
                    s.sample(frames[k[0] % 2], n)
                    k[0] += 1

                t_update = _min_time(update, reps)
                ls = lights[0]
                rows.append({"map": map_name, "method": method, "count": n, "lights": len(ls),
                             "build_ms": 1e3 * t_build[0], "update_ms": 1e3 * t_update[0],
                             "build_cpu_ms": 1e3 * t_build[1],
                             "update_cpu_ms": 1e3 * t_update[1],
                             "build_median_ms": 1e3 * t_build[2],
                             "update_median_ms": 1e3 * t_update[2], **ref.errors(ls)})
    return rows


def medians(rows: list[dict[str, Any]]) -> dict[str, dict[int, dict[str, float]]]:
    out: dict[str, dict[int, dict[str, float]]] = {}
    for r in rows:
        out.setdefault(r["method"], {}).setdefault(r["count"], {})
    for method, per_n in out.items():
        for n in per_n:
            sel = [r for r in rows if r["method"] == method and r["count"] == n]
            per_n[n] = {k: float(np.median([r[k] for r in sel]))
                        for k in ("build_ms", "update_ms", "build_cpu_ms", "update_cpu_ms",
                                  "build_median_ms", "update_median_ms", "lights", *KINDS)}
    return out


def nikodym_map(shared: Path) -> np.ndarray:
    """A 360 x 90 hemisphere map (lebombo, area-averaged) as the top of a 360 x 180 equirect."""
    import cv2

    img = read_hdr_image(shared / "envmaps" / "lebombo_1k.hdr")
    small = cv2.resize(img, (360, 180), interpolation=cv2.INTER_AREA).astype(np.float32)
    small[90:] = 0.0
    return small


def nikodym_table(img: np.ndarray, methods: list[str], reps: int) -> dict[str, Any]:
    ours: dict[str, list[list[float]]] = {}
    for method in methods:
        s = make_sampler(method)
        times = []
        for n in NIKODYM_COUNTS:
            s.sample(img, n)

            def build(s: Any = s, n: int = n) -> None:
                s.reset()
                s.sample(img, n)

            times.append([1e3 * x for x in _min_time(build, reps)[:2]])
        ours[method] = times
    return {"counts": list(NIKODYM_COUNTS), "map": "360x90 (top half of 360x180 lebombo)",
            "ours_ms_is": "[wall, cpu] min over repetitions",
            "nikodym_2013_n900_ms": NIKODYM_N900_MS, "ours_ms": ours}


# -- Q2-Tree: incremental update against full build, end to end ------------------------------
INCREMENTAL_KINDS = ("local", "gain", "noise", "still")


def change_sequence(img: np.ndarray, kind: str, frames: int, seed: int = 0) -> list[np.ndarray]:
    """Frames of a slowly changing stream: ``local`` (a lamp-sized block, 1/8 of the height
    square, brightens 2% a frame and moves 1/256 of the width: the rest of the map is
    unchanged, as in a still room or the simulator), ``gain`` (every pixel x 1.002 every other
    frame), ``noise`` (1% multiplicative noise on every pixel, like a camera) or ``still`` (the
    same pixels every frame, each frame a new array). ``img`` is an (H, W, 3) equirect map or
    a (P, 3) NESTED one."""
    h, w = img.shape[:2]
    rng = np.random.default_rng(seed)
    out = []
    for k in range(frames):
        if kind == "local" and img.ndim == 2:  # NESTED map: a quad of 1/768 of the sphere
            f = img.copy()
            b = max(1, h // 768)
            a = h // 5 + k * max(1, b // 4)
            f[a:a + b] *= np.float32(1.0 + 0.02 * k)
        elif kind == "local":
            f = img.copy()
            b, r0, c0 = max(1, h // 8), h // 5, w // 3 + k * max(1, w // 256)
            f[r0:r0 + b, c0:c0 + b] *= np.float32(1.0 + 0.02 * k)
        elif kind == "gain":
            f = img * np.float32(1.0 + 0.002 * (k % 2))
        elif kind == "still":
            f = img.copy()
        else:
            f = img * (1.0 + 0.01 * rng.standard_normal((*img.shape[:-1], 1))).astype(np.float32)
        out.append(np.ascontiguousarray(f, np.float32))
    return out


def _q2_times(sample: Callable[[Any, np.ndarray], Any], frames: list[np.ndarray], reps: int
              ) -> dict[str, float]:
    """Full build (``reset`` then the frame) and update (the frame after its predecessor) of a
    Q2TreeSampler over ``frames``: min and median wall ms over frames x reps, the tree's own
    time (``stats["tree_s"]``, us) for both, and the update's stages (minima, us): pyramid
    (``pyramid_s``: compare with the previous frame, re-sum changed runs, coarse levels),
    tree, lights (``emit_s``) and the rest of the call (checks, Python)."""
    from lightprobe.device.sampling.q2tree import Q2TreeSampler

    s = Q2TreeSampler()
    sample(s, frames[0])  # warm up (JIT, tables)
    full, tfull, upd, tupd, changed = [], [], [], [], []
    pyr, emit, rest = [], [], []
    for _ in range(max(1, reps)):
        for f in frames:
            s.reset()
            t = time.perf_counter()
            sample(s, f)
            full.append(time.perf_counter() - t)
            tfull.append(s.stats["tree_s"])
        s.reset()
        sample(s, frames[0])
        for f in frames[1:]:
            t = time.perf_counter()
            sample(s, f)
            upd.append(time.perf_counter() - t)
            st = s.stats
            tupd.append(st["tree_s"])
            changed.append(st["changed_quads"])
            pyr.append(st["pyramid_s"])
            emit.append(st["emit_s"])
            rest.append(upd[-1] - st["pyramid_s"] - st["tree_s"] - st["emit_s"])
    out = {"full_ms": 1e3 * min(full), "full_median_ms": 1e3 * float(np.median(full)),
           "update_ms": 1e3 * min(upd), "update_median_ms": 1e3 * float(np.median(upd)),
           "tree_full_us": 1e6 * min(tfull), "tree_update_us": 1e6 * min(tupd),
           "changed_quads_median": float(np.median(changed)),
           "pyramid_update_us": 1e6 * min(pyr), "emit_update_us": 1e6 * min(emit),
           "rest_update_us": 1e6 * min(rest)}
    out["ratio"] = out["update_ms"] / out["full_ms"]
    out["ratio_median"] = out["update_median_ms"] / out["full_median_ms"]
    out["tree_ratio"] = out["tree_update_us"] / out["tree_full_us"]
    return out


def _call(s: Any, f: np.ndarray, n: int) -> Any:
    """``sample`` for an equirect frame, ``sample_healpix`` (nside 64) for a NESTED one."""
    return s.sample_healpix(f, 64, n) if f.ndim == 2 else s.sample(f, n)


def incremental_bench(maps: dict[str, np.ndarray], counts: tuple[int, ...], frames: int,
                      reps: int) -> dict[str, Any]:
    """Q2-Tree update / full build, end to end (``sample()``, map -> pyramid -> tree -> lights)
    and tree only, on the 1k maps and on the device's inputs: the pipeline's 512 x 256 equirect
    (lower half black, ``sample``) and its NESTED nside-64 map (``sample_healpix``)."""
    import cv2

    from lightprobe.core.healpix import equirect_to_healpix

    rows = []
    for name, img in maps.items():
        small = cv2.resize(img, (512, 256), interpolation=cv2.INTER_AREA).astype(np.float32)
        small[128:] = 0.0
        hp = equirect_to_healpix(small, 64).astype(np.float32)
        inputs = {"1k equirect": img, "device 512x256 equirect": small,
                  "device nside-64 healpix": hp}
        for path, base in inputs.items():
            for kind in INCREMENTAL_KINDS:
                seq = change_sequence(base, kind, frames)
                for n in counts:
                    t = _q2_times(partial(_call, n=n), seq, reps)
                    rows.append({"map": name, "input": path, "sequence": kind, "count": n, **t})
    summary: dict[str, Any] = {}
    for r in rows:
        key = f"{r['input']} / {r['sequence']} / N={r['count']}"
        summary.setdefault(key, {"ratio": [], "ratio_median": [], "tree_ratio": [],
                                 "full_ms": [], "update_ms": [], "pyramid_update_us": [],
                                 "tree_update_us": [], "emit_update_us": [],
                                 "rest_update_us": []})
        for k in summary[key]:
            summary[key][k].append(r[k])
    med = {k: {m: float(np.median(v)) for m, v in d.items()} for k, d in summary.items()}
    return {"rows": rows, "medians_over_maps": med,
            "note": "ratio = min update / min full build, wall; tree_ratio from stats['tree_s']"}


# -- temporal ---------------------------------------------------------------------------------
class SceneTruth:
    """Exact diffuse irradiance of a ``sim`` scene at fixed normals, cheaply per frame.

    The base map's response is computed once (pixel sums); each dynamic disc adds
    ``sum frac x Y x k x Omega x max(0, n.w)`` over its rasterised pixels, exactly what
    ``Scene.radiance_equirect`` adds to the map.
    """

    def __init__(self, scene: Any, normals: np.ndarray) -> None:
        from lightprobe.sim.scene import rasterize_disc

        self._raster = rasterize_disc
        self.scene = scene
        self.normals = normals
        self.ref = ErrorReference(scene.base * np.float32(scene.scale), normals)
        self.base = self.ref.truth("diffuse")
        h = scene.height
        self.h = h
        self.omega = equirect_row_solid_angle(h)

    def diffuse(self, t: float) -> np.ndarray:
        out = self.base.copy()
        h, w = self.h, 2 * self.h
        for light in self.scene.lights:
            k = light.mean_intensity(t, 0.0) * self.scene.scale
            if k <= 0:
                continue
            rows, cols, frac = self._raster(h, light.direction_at(t), light.radius_rad)
            theta = np.pi * (rows + 0.5) / h
            phi = 2 * np.pi * (cols + 0.5) / w
            d = np.stack([np.sin(theta) * np.sin(phi), np.cos(theta),
                          -np.sin(theta) * np.cos(phi)], axis=1)
            y = float(luminance(np.asarray(light.rgb, np.float64))) * k
            out += (frac * self.omega[rows] * y) @ np.maximum(d @ self.normals.T, 0.0)
        return out


def _displacement_deg(prev: LightSet, cur: LightSet) -> float:
    """Power-weighted angle from each light of ``cur`` to the nearest light of ``prev``."""
    if len(prev) == 0 or len(cur) == 0:
        return 0.0
    cos = np.clip(cur.directions @ prev.directions.T, -1.0, 1.0).max(axis=1)
    p = luminance(cur.rgb)
    return float(np.degrees(np.sum(p * np.arccos(cos)) / max(np.sum(p), 1e-300)))


class _Scenario:
    """A scenario's scene and its per-frame truth (computed once, shared by every sampler)."""

    def __init__(self, name: str, frames: int, shared: Path | None = None, seed: int = 0) -> None:
        from lightprobe.sim.scenarios import load_scene

        self.scene = load_scene(name, seed=seed, shared_data=shared or _shared_data())
        self.normals = fibonacci_normals(512)
        truth = SceneTruth(self.scene, self.normals)
        self.times = np.arange(frames) / FPS
        self.truth = np.array([truth.diffuse(t) for t in self.times])
        self.total = np.array([float(luminance(self.scene.analytic_integral(t)))
                               for t in self.times])


def temporal_run(scene: str | _Scenario, sampler: Any, count: int, frames: int = 0,
                 shared: Path | None = None, seed: int = 0, noise: float = 0.0
                 ) -> dict[str, np.ndarray]:
    """Run ``sampler`` over the frames of a scenario at 30 fps: per-frame approximate and true
    irradiance (frames, M), displacement (frames,), true total luminance (frames,).

    ``noise`` > 0 feeds the sampler a noisy map (per-pixel multiplicative Gaussian, seeded per
    frame) while the truth stays clean: what camera input looks like to the filters.
    """
    sc = scene if isinstance(scene, _Scenario) else _Scenario(scene, frames, shared, seed)
    normals = sc.normals
    sampler.reset()
    e_a, disp = [], []
    prev: LightSet | None = None
    for k, t in enumerate(sc.times):
        img = sc.scene.radiance_equirect(float(t))
        if noise > 0:
            rng = np.random.default_rng(1000 + k)
            img = img * (1.0 + noise * rng.standard_normal((*img.shape[:2], 1))).astype(np.float32)
        ls = sampler.sample(img, count)
        dirs, power = light_arrays(ls)
        e_a.append(power @ np.maximum(dirs @ normals.T, 0.0) if len(dirs) else
                   np.zeros(len(normals)))
        disp.append(_displacement_deg(prev, ls) if prev is not None else 0.0)
        prev = ls
    return {"approx": np.array(e_a), "truth": sc.truth, "displacement": np.array(disp),
            "total": sc.total}


def temporal_metrics(run_data: dict[str, np.ndarray]) -> dict[str, float]:
    """Flicker, per-frame error, lag after abrupt changes and displacement of one run."""
    a, t = run_data["approx"], run_data["truth"]
    scale = float(np.sqrt(np.mean(t**2)))
    flicker = float(np.sqrt(np.mean((np.diff(a, axis=0) - np.diff(t, axis=0)) ** 2))) / scale
    err = np.sqrt(np.mean((a - t) ** 2, axis=1)) / np.sqrt(np.mean(t**2, axis=1))
    steady = float(np.median(err))
    tot = run_data["total"]
    jumps = np.flatnonzero(np.abs(np.diff(tot)) > 0.05 * np.maximum(tot[:-1], tot[1:])) + 1
    lags = []
    for j in jumps:
        below = np.flatnonzero(err[j:] < 2 * steady)
        lags.append(int(below[0]) if len(below) else int(len(err) - j))
    return {"flicker": flicker, "error_mean": float(err.mean()), "error_steady": steady,
            "lag_mean": float(np.mean(lags)) if lags else 0.0,
            "lag_max": float(np.max(lags)) if lags else 0.0, "toggles": len(lags),
            "displacement_deg": float(np.mean(run_data["displacement"][1:]))}


def temporal_bench(methods: list[str], count: int, frames: dict[str, int]
                   ) -> dict[str, dict[str, dict[str, float]]]:
    out: dict[str, dict[str, dict[str, float]]] = {}
    for scen in SCENARIOS:
        sc = _Scenario(scen, frames[scen])
        out[scen] = {m: temporal_metrics(temporal_run(sc, make_sampler(m), count))
                     for m in methods}
    return out


HEMIGON_VARIANTS: dict[str, dict[str, float]] = {
    "no filters (default)": {},
    "filters on": {"energy_alpha": 0.3, "trajectory_alpha": 0.5},
    "strong": {"energy_alpha": 0.1, "trajectory_alpha": 0.2},
    "filters on, no reset": {"energy_alpha": 0.3, "trajectory_alpha": 0.5,
                             "energy_jump": 1e9, "trajectory_jump": 1e9},
}


def filter_bench(count: int, frames: dict[str, int]) -> dict[str, dict[str, dict[str, float]]]:
    """Hemigon's filter variants on clean input and on noisy input (10% per-pixel noise)."""
    out: dict[str, dict[str, dict[str, float]]] = {}
    for scen, noise in (("flashlight", 0.0), ("flicker", 0.0), ("switch", 0.0),
                        ("flashlight", 0.1)):
        sc = _Scenario(scen, frames[scen])
        key = scen + (f" (input noise {noise:g})" if noise else "")
        out[key] = {label: temporal_metrics(temporal_run(sc, make_sampler("hemigon", **p), count,
                                                         noise=noise))
                    for label, p in HEMIGON_VARIANTS.items()}
    return out


# -- plots and entry point --------------------------------------------------------------------
def _plots(out_dir: Path, med: dict[str, dict[int, dict[str, float]]],
           temporal: dict[str, dict[str, dict[str, float]]]) -> list[str]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(15, 4.5))
    for ax, kind in zip(axes, KINDS, strict=True):
        for method, per_n in med.items():
            ns = sorted(per_n)
            ax.loglog([per_n[n]["build_cpu_ms"] for n in ns],
                      [max(per_n[n][kind], 1e-6) for n in ns], "o-", label=method)
            for n in ns:
                ax.annotate(str(n), (per_n[n]["build_cpu_ms"], max(per_n[n][kind], 1e-6)),
                            fontsize=6)
        ax.set_xlabel("build CPU time per frame (ms, median over maps)")
        ax.set_ylabel(f"{kind} error (relative RMSE)")
        ax.set_title(kind)
        ax.grid(True, which="both", alpha=0.3)
    axes[0].legend()
    fig.tight_layout()
    fig.savefig(out_dir / "samplers_pareto.png", dpi=110)
    plt.close(fig)
    fig, ax = plt.subplots(figsize=(8, 4))
    scen = list(temporal)
    methods = sorted({m for s in temporal.values() for m in s})
    width = 0.8 / max(1, len(methods))
    for i, m in enumerate(methods):
        ax.bar(np.arange(len(scen)) + i * width, [temporal[s][m]["flicker"] for s in scen],
               width, label=m)
    ax.set_xticks(np.arange(len(scen)) + 0.4 - width / 2, scen)
    ax.set_ylabel("flicker (relative RMS of irradiance change error)")
    ax.set_yscale("log")
    ax.legend()
    fig.tight_layout()
    fig.savefig(out_dir / "samplers_temporal.png", dpi=110)
    plt.close(fig)
    return ["samplers_pareto.png", "samplers_temporal.png"]


def run(out_dir: Path, quick: bool = False) -> dict[str, Any]:
    """Run the benchmark, write ``samplers.json`` and PNG plots into ``out_dir``."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    shared = _shared_data()
    methods = available_samplers()
    names = MAP_NAMES[:3] if quick else MAP_NAMES
    maps = {n: read_hdr_image(shared / "envmaps" / n) for n in names}
    counts = QUICK_COUNTS if quick else COUNTS
    reps = 1 if quick else 5
    t0 = time.perf_counter()
    load_start = os.getloadavg()
    rows = static_bench(maps, methods, counts, reps)
    med = medians(rows)
    nik = nikodym_table(nikodym_map(shared), methods, reps)
    frames = ({s: 15 for s in SCENARIOS} if quick else
              {s: 90 for s in SCENARIOS} | {"switch": 240})
    temporal = temporal_bench(methods, 256, frames)
    filters = {} if quick else filter_bench(256, {s: 60 for s in SCENARIOS} | {"switch": 240})
    incremental = incremental_bench(
        dict(list(maps.items())[:2]) if quick else maps, (256,) if quick else (256, 1000),
        6 if quick else 12, 1 if quick else 3)
    plots = _plots(out_dir, med, temporal)
    summary = {
        "methods": methods,
        "maps": names,
        "median_diffuse_at_256": {m: med[m][256]["diffuse"] for m in med if 256 in med[m]},
        "median_occluded_at_256": {m: med[m][256]["occluded"] for m in med if 256 in med[m]},
        "median_build_ms_at_1000": {m: med[m][1000]["build_ms"] for m in med if 1000 in med[m]},
        "median_build_cpu_ms_at_1000": {m: med[m][1000]["build_cpu_ms"] for m in med
                                        if 1000 in med[m]},
        "median_update_cpu_ms_at_1000": {m: med[m][1000]["update_cpu_ms"] for m in med
                                         if 1000 in med[m]},
        "nikodym_360x90_ms": nik["ours_ms"],
        "flicker": {s: {m: v["flicker"] for m, v in temporal[s].items()} for s in temporal},
        "switch_lag_max_frames": {m: v["lag_max"] for m, v in temporal["switch"].items()},
        "median_build_min_ms": {m: {n: v["build_ms"] for n, v in per.items()}
                                for m, per in med.items()},
        "median_build_median_ms": {m: {n: v["build_median_ms"] for n, v in per.items()}
                                   for m, per in med.items()},
        "q2tree_incremental_at_256": {k: v for k, v in incremental["medians_over_maps"].items()
                                      if k.endswith("N=256")},
        "load_average": {"start": list(load_start), "end": list(os.getloadavg())},
        "wall_s": round(time.perf_counter() - t0, 1),
    }
    result = {"summary": summary, "static": rows,
              "medians": {m: {str(n): v for n, v in per.items()} for m, per in med.items()},
              "nikodym_table": nik, "temporal": temporal, "hemigon_filters": filters,
              "q2tree_incremental": incremental,
              "frames": frames, "fps": FPS, "plots": plots, "quick": quick}
    (out_dir / "samplers.json").write_text(json.dumps(result, indent=1))
    return result
