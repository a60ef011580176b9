"""``lightprobe bench relight_sg [--quick]``: SG relighting (lightprobe.hostlink.relight.sg.relighter) against the brute force,
and frame times with no precompute; ``lightprobe bench relight`` runs it too and draws the Pareto
plot of both methods.

* Accuracy: the scene of ``lightprobe.bench.relight`` (spot.obj on a 25 x 25 ground, 3,555 vertices), each
  shared map fitted to SG lobes as the probe does (``fit_sg``), the cow Lambert or Phong (e = 20),
  visibility by rays or voxel cone tracing. Per-vertex relative RMS luminance error against the
  brute force of the *true* map (2^15 directions, every ray cast), every 5th vertex. A deforming
  cow (squashed and sheared, a new shape each frame): the same error against the brute force of
  each deformed frame.
* Speed: spot on a 131 x 131 ground (20,091 vertices), 640 x 480, per-pixel :meth:`render`:
  the first frame of a scene never seen before (construction, voxelisation, tables, cones,
  shading), a light change whose peaks stay put (a lamp dims: tables and shading only), a light
  change that moves the peaks (the peaks' cones re-traced per pixel), the cow moved rigidly, the
  cow deformed (re-voxelised, every cone re-traced). Wall min / median and process-CPU min.
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

import numpy as np

from lightprobe.bench.relight_scenes import MAPS, SHARED, rel_rms, scene_file, timeit


def _deformed(rest: np.ndarray, f: int) -> np.ndarray:
    v = rest.copy()
    lo = v[:, 1].min()
    v[:, 1] = lo + (v[:, 1] - lo) * (1.0 - 0.12 * (f + 1))
    v[:, 0] += 0.15 * f * (v[:, 1] - lo)
    return v


def _accuracy(d: Path, lobes: list[Any], light: tuple[np.ndarray, np.ndarray]) -> dict[str, Any]:
    from lightprobe.bench.relight_reference import brute_force_radiance
    from lightprobe.core.sphere import luminance
    from lightprobe.hostlink.relight.scene import load_scene
    from lightprobe.hostlink.relight.sg.relighter import SGRelighter

    out: dict[str, Any] = {}
    for clay in ("lambert", "phong"):
        p = scene_file(d, False, 24)
        doc = json.loads(p.read_text())
        doc["materials"]["clay"]["type"] = clay
        p = p.with_name(f"sg_{clay}.json")
        p.write_text(json.dumps(doc))
        scene = load_scene(p)
        eye = scene.camera.position
        probe = SGRelighter(scene, visibility="rays")
        vidx = np.arange(0, len(probe.vertices), 5)
        t0 = time.perf_counter()
        ref = brute_force_radiance(probe.vertices, probe.faces, probe.normals(), probe.matid, probe.mats,
                                   *light, eye, vidx)
        ref_s = time.perf_counter() - t0
        for vis in ("rays", "voxels"):
            rl = SGRelighter(scene, visibility=vis)
            errs, ms = {}, []
            for k, name in enumerate(MAPS):
                rl.set_sg(lobes[k])
                t0 = time.perf_counter()
                b = rl.vertex_radiance(eye)
                ms.append((time.perf_counter() - t0) * 1e3)
                errs[name] = round(rel_rms(luminance(b[vidx]), luminance(ref[k])), 4)
            out[f"{clay}/{vis}"] = {"rel_rms": errs, "max": max(errs.values()),
                                    "shade_all_vertices_ms_median": round(float(np.median(ms)), 1),
                                    "vertices": len(rl.vertices), "reference_s": round(ref_s, 1)}
        if clay == "phong":
            rl = SGRelighter(scene, visibility="voxels")
            rl.set_sg(lobes[1])
            rest = rl.objects[0].rest
            frames = []
            for f in range(3):
                rl.set_vertices("spot", _deformed(rest, f))
                b = rl.vertex_radiance(eye, vidx)
                r = brute_force_radiance(rl.vertices, rl.faces, rl.normals(), rl.matid, rl.mats,
                                         light[0][1:2], light[1][1:2], eye, vidx)[0]
                frames.append(round(rel_rms(luminance(b), luminance(r)), 4))
            out["phong/voxels/deforming_rooitou"] = frames
    return out


def _speed(d: Path, lobes: list[Any], reps: int) -> dict[str, Any]:
    from lightprobe.core.sg import SGLighting
    from lightprobe.hostlink.relight.scene import load_scene

    scene = load_scene(scene_file(d, False, 131, 640, 480))
    out: dict[str, Any] = {"vertices": sum(len(o.mesh.vertices) for o in scene.objects), "width": 640, "height": 480}
    sun, other = lobes[1], lobes[3]            # rooitou (a sun peak), lebombo (no peak)
    dim = SGLighting(sun.axes, sun.sharpness, sun.amplitude * 0.5, list(sun.kinds))
    for vis in ("voxels",) + (("rays",) if reps > 1 else ()):
        out[vis] = _frames(scene, vis, sun, dim, other, reps)
        out["pixels"] = out[vis].pop("pixels")
    return out


def _frames(scene: Any, vis: str, sun: Any, dim: Any, other: Any, reps: int) -> dict[str, Any]:
    from lightprobe.hostlink.relight.sg.relighter import SGRelighter

    rows: dict[str, Any] = {}
    t0, c0 = time.perf_counter(), time.process_time()
    rl = SGRelighter(scene, visibility=vis)
    rl.set_sg(sun)
    _img, stats = rl.render()
    rows["first_frame_new_scene_tables_cached"] = {"ms": round((time.perf_counter() - t0) * 1e3, 1),
                                                   "cpu_ms": round((time.process_time() - c0) * 1e3, 1)}
    rows["pixels"] = int(stats["pixels"])
    state = {"k": 0}
    rest = rl.objects[0].rest

    def light_dim() -> None:
        state["k"] ^= 1
        rl.set_sg(dim if state["k"] else sun)
        rl.render()

    def light_move() -> None:
        state["k"] ^= 1
        rl.set_sg(other if state["k"] else sun)
        rl.render()

    def move() -> None:
        state["k"] += 1
        rl.move("spot", np.array([0.02 * (state["k"] % 5), 0.0, 0.0]), np.array([0.0, 7.0 * (state["k"] % 3), 0.0]))
        rl.render()

    def deform() -> None:
        state["k"] += 1
        rl.set_vertices("spot", _deformed(rest, state["k"] % 3))
        rl.render()

    rows["light_change_peaks_still"] = timeit(light_dim, reps)
    rows["light_change_peaks_moved"] = timeit(light_move, reps)
    rl.set_sg(sun)
    rows["rigid_move"] = timeit(move, reps)
    rows["deform"] = timeit(deform, reps)
    return rows


def _cold_first_frame(d: Path) -> dict[str, float]:
    """A fresh process: import, the kernels from numba's cache, the lobe tables built, one frame."""
    import subprocess
    import sys

    code = ("import time; t=time.perf_counter()\n"
            "from pathlib import Path\nfrom lightprobe.core.imageio import read_hdr_image\n"
            "from lightprobe.device.formats.sgfit import fit_sg\nfrom lightprobe.hostlink.relight.scene import load_scene\n"
            "from lightprobe.hostlink.relight.sg.relighter import SGRelighter\n"
            f"sg = fit_sg(read_hdr_image(Path({str(SHARED / 'envmaps' / MAPS[1])!r})))\nt1=time.perf_counter()\n"
            f"rl = SGRelighter(load_scene(Path({str(scene_file(d, False, 131, 640, 480))!r})))\n"
            "rl.set_sg(sg); rl.render(); t2=time.perf_counter()\n"
            "print(t1-t, t2-t1)\n")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=600,
                       cwd=Path(__file__).resolve().parent.parent, check=True)
    a, b = (float(x) for x in r.stdout.split())
    return {"imports_and_fit_s": round(a, 2), "scene_lobes_first_frame_s": round(b, 2)}


def pareto_plot(out_dir: Path, sg: dict[str, Any], cuts: dict[str, Any] | None) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4.5))
    sp = sg["speed"]
    for vis, mk in (("voxels", "o"), ("rays", "s")):
        if vis not in sp:
            continue
        err = sg["accuracy"][f"phong/{vis}"]["max"]
        for what, col in (("light_change_peaks_still", "C0"), ("light_change_peaks_moved", "C1"),
                          ("rigid_move", "C2"), ("deform", "C3")):
            ax.loglog(sp[vis][what]["median"], err, mk, color=col, label=f"SG {vis}: {what}")
    if cuts is not None:
        fm = cuts["summary"]["frame_ms"]
        err = cuts["summary"]["max_rel_rms_default_tau_moment"]
        for what, v in fm.items():
            ax.loglog(v["median"], err, "x", label=f"cuts: {what}")
        ax.annotate(f"cuts: + {cuts['summary']['precompute_20k_movable_total_s']:.0f} s precompute",
                    (min(v["median"] for v in fm.values()), err), fontsize=7)
    ax.axvline(50, color="k", lw=0.6)
    ax.axvline(250, color="k", lw=0.6, ls=":")
    ax.set(xlabel="frame time, median (ms), 20k vertices 640 x 480", ylabel="max relative RMS vs brute force (6 maps)",
           title="relighting: cuts vs spherical Gaussians (this machine)")
    ax.legend(fontsize=6, loc="best")
    fig.tight_layout()
    fig.savefig(out_dir / "relight_pareto.png", dpi=100)
    plt.close(fig)


def run(out_dir: Path, quick: bool) -> dict[str, Any]:
    import os

    from lightprobe.bench.relight_reference import equirect_quadrature
    from lightprobe.core.imageio import read_hdr_image
    from lightprobe.device.formats.sgfit import fit_sg
    from lightprobe.hostlink.relight.cuts.precompute import default_cache_dir

    out_dir.mkdir(parents=True, exist_ok=True)
    d = default_cache_dir() / "bench"
    d.mkdir(parents=True, exist_ok=True)
    maps = [read_hdr_image(SHARED / "envmaps" / m) for m in MAPS]
    lobes = [fit_sg(m) for m in maps]
    light = equirect_quadrature(maps)
    load0 = os.getloadavg()[0]
    acc = _accuracy(d, lobes, light)
    speed = _speed(d, lobes, 3 if quick else 7)
    cold = _cold_first_frame(d)
    summary = {"max_rel_rms": {k: v["max"] for k, v in acc.items() if isinstance(v, dict)},
               "deforming": acc["phong/voxels/deforming_rooitou"],
               "frame_ms_voxels": {k: (v.get("median", v.get("ms"))) for k, v in speed["voxels"].items()},
               "cold_process": cold, "load_average_before_after": [round(load0, 2), round(os.getloadavg()[0], 2)]}
    result = {"summary": summary, "accuracy": acc, "speed": speed, "cold_process": cold}
    (out_dir / "relight_sg.json").write_text(json.dumps(result, indent=1))
    cuts_json = out_dir / "relight.json"
    pareto_plot(out_dir, result, json.loads(cuts_json.read_text()) if cuts_json.exists() else None)
    return result
