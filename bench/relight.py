"""``lightprobe bench relight [--quick]``: cut relighting against a brute-force reference, then the SG
method (``lightprobe.bench.relight_sg``) on the same scenes and ``relight_pareto.png``, both methods' error
against frame time.

Scenes: ``../shared/data/meshes/spot.obj`` on a ground plane.
* A (accuracy): spot static, ground 25 x 25 vertices (3,555 vertices). For each tau: SVC precompute
  time, mean cut size, data size height- vs index-coded, and per-vertex luminance error against the
  independent brute-force reference (:mod:`lightprobe.bench.relight_reference`: its own 2^15-cell
  quadrature of each map, one Embree ray per direction, its own BRDF loop) under the six
  shared maps, with and without the cosine-moment correction (without = the paper's plain Eq. 3).
  Error metric: relative RMS over vertices, sqrt(sum (Y - Y_ref)^2 / sum Y_ref^2), Y = Rec.709
  luminance of the outgoing radiance towards the camera; the reference uses every ``stride``-th vertex.
* B (speed, 20k vertices): ground 131 x 131 + spot = 20,091 vertices; spot movable with a VCF
  (paper: 32 spheres, 6 x 32^2 points; quick: 8 spheres, 6 x 8^2) and, separately, spot static.
  Frame time (wall min / median and process-CPU min over ``reps`` runs, 1-minute load average
  at the time) for light / BRDF / view changes (static scene) and for a moving / rotating
  occluder, shading all 20,091 vertices and rendering 640 x 480 frames (ID-buffer-visible
  vertices; render() re-shades only stale parts: the static radiance after a light change, the
  edited material's after a BRDF edit, the non-Lambertian ones after a view change, the moved
  object's own vertices; the occlusion of vertices within reach of a moved object). Per-stage
  times on all vertices. Errors of the same scenes against brute force (every 10th vertex), split
  into spot / ground and, with the occluder moved, ground inside / outside the innermost VCF
  sphere (1.2 r, where the VCF is clamped). Data sizes with the same value encoding on both sides.
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

import numpy as np

from lightprobe.bench.relight_scenes import MAPS, SHARED, rel_rms, scene_file, timeit


def _sizes(offsets: np.ndarray, kind: str) -> tuple[int, int]:
    from lightprobe.hostlink.relight.cuts.coding import height_coded_nbytes, index_coded_nbytes

    lens = np.diff(offsets)
    uniq, counts = np.unique(lens, return_counts=True)
    return (int(sum(height_coded_nbytes(int(n), kind) * int(c) for n, c in zip(uniq, counts, strict=True))),
            int(sum(index_coded_nbytes(int(n), kind) * int(c) for n, c in zip(uniq, counts, strict=True))))


def _accuracy(d: Path, quick: bool, leaf_lights: np.ndarray, maps: list[np.ndarray]) -> dict[str, Any]:
    from lightprobe.bench.relight_reference import relighter_reference
    from lightprobe.core.sphere import luminance
    from lightprobe.hostlink.relight.cuts.precompute import precompute
    from lightprobe.hostlink.relight.cuts.render import Relighter
    from lightprobe.hostlink.relight.scene import load_scene

    scene = load_scene(scene_file(d, False, 24))
    taus = [1e-4, 2e-5] if quick else [1e-4, 5e-5, 2e-5, 1e-5, 5e-6]
    stride = 9 if quick else 3
    rows: list[dict[str, Any]] = []
    ref = None
    for tau in taus:
        pre = precompute(scene, tau=tau, cache_dir=d / "cache", progress=False)
        rl = Relighter(scene, pre)
        vidx = np.arange(0, len(pre.vertices), stride)
        eye = scene.camera.position
        if ref is None:
            t0 = time.perf_counter()
            ref = relighter_reference(rl, maps, eye, vidx)
            ref_s = time.perf_counter() - t0
        hb, ib = _sizes(pre.svc_offsets, "u8")
        row: dict[str, Any] = {"tau": tau, "precompute_s": round(pre.seconds, 2), "vertices": len(pre.vertices),
                               "mean_svc_nodes": float(np.diff(pre.svc_offsets).mean()),
                               "svc_bytes_height": hb, "svc_bytes_index": ib, "maps": {}}
        for moment in (True, False):
            rl.moment = moment
            for mi, name in enumerate(MAPS):
                rl.set_leaf_light(leaf_lights[mi])
                b, _ = rl.vertex_radiance(eye, vidx)
                y, yr = luminance(b), luminance(ref[mi])
                rel = np.abs(y - yr) / np.maximum(yr, 1e-12)
                row["maps"].setdefault(name, {})["moment" if moment else "plain"] = {
                    "rel_rms": round(rel_rms(y, yr), 5), "median_rel": round(float(np.median(rel)), 5),
                    "p95_rel": round(float(np.percentile(rel, 95)), 5)}
        rows.append(row)
    return {"stride": stride, "reference_s": round(ref_s, 2), "rows": rows}


def _errors(rl, leaf_lights: np.ndarray, maps: list[np.ndarray], eye: np.ndarray,  # type: ignore[no-untyped-def]
            vidx: np.ndarray, groups: dict[str, np.ndarray]) -> dict[str, Any]:
    """Relative RMS luminance error against brute force per map, overall and per vertex group."""
    from lightprobe.bench.relight_reference import relighter_reference
    from lightprobe.core.sphere import luminance

    ref = relighter_reference(rl, maps, eye, vidx)
    out: dict[str, Any] = {}
    for mi, name in enumerate(MAPS):
        rl.set_leaf_light(leaf_lights[mi])
        b, _ = rl.vertex_radiance(eye, vidx)
        y, yr = luminance(b), luminance(ref[mi])
        row = {"all": round(rel_rms(y, yr), 4)}
        row.update({g: round(rel_rms(y[m], yr[m]), 4) for g, m in groups.items() if m.any()})
        out[name] = row
    return out


def _stages(rl, eye: np.ndarray, leaf: np.ndarray, reps: int) -> dict[str, dict[str, float]]:  # type: ignore[no-untyped-def]
    """Per-stage times on all vertices: light tables, static (SVC) shading, occlusion, raster."""
    from lightprobe.hostlink.relight.cuts.lighting import light_tables
    from lightprobe.hostlink.relight.raster import rasterize

    allv = np.arange(len(rl.pre.vertices))
    pos = rl.positions()
    wo = rl._wo(eye, pos, allv)
    st = rl._static(allv, wo)
    out = {"light_tables": timeit(lambda: light_tables(leaf), reps),
           "static_shade_all": timeit(lambda: rl._static(allv, wo), reps),
           "rasterize_640x480": timeit(lambda: rasterize(rl.scene.camera, pos, rl.pre.faces, rays=False), reps)}
    if rl.movable:
        out["occlusion_all"] = timeit(lambda: rl._occlusion(allv, wo, pos, st), reps)
    return out


def _frames(rls, rld, maps: list[np.ndarray], reps: int) -> dict[str, dict[str, float]]:  # type: ignore[no-untyped-def]
    """Frame times (render() at 640 x 480, shading only stale visible vertices)."""
    from lightprobe.hostlink.relight.raster import rasterize
    from lightprobe.hostlink.relight.scene import Camera, Material

    cam = rls.scene.camera
    raster = rasterize(cam, rls.pre.vertices, rls.pre.faces, rays=False)
    eye = cam.position
    allv = np.arange(len(rls.pre.vertices))
    ms: dict[str, dict[str, float]] = {}
    ms["static_all_vertices_shade"] = timeit(lambda: rls.vertex_radiance(eye, allv), reps)
    ms["static_light_change"] = timeit(lambda: (rls.set_equirect(maps[2]), rls.render(raster=raster)), reps)
    ms["static_brdf_change"] = timeit(lambda: (rls.set_material("clay", Material("ward", (0.5, 0.4, 0.3), (0.3, 0.3, 0.3), alpha=0.2)),
                                                rls.render(raster=raster)), reps)
    orbit = iter([Camera(np.array([2.5 * np.sin(a), 1.2, 2.5 * np.cos(a)]), cam.look_at, cam.up, cam.fov_deg,
                         cam.width, cam.height) for a in np.linspace(0.3, 1.2, 1000)])
    ms["static_view_change"] = timeit(lambda: rls.render(next(orbit)), reps)   # raster + glossy re-shade
    step = iter(np.linspace(0, 0.6, 1000))
    ms["moving_all_vertices_shade"] = timeit(lambda: (rld.move("spot", [next(step), 0, 0]),
                                                       rld.vertex_radiance(eye, allv)), reps)
    ms["moving_frame"] = timeit(lambda: (rld.move("spot", [next(step), 0, 0]), rld.render()), reps)
    turn = iter(np.linspace(0, 90, 1000))
    ms["rotating_frame"] = timeit(lambda: (rld.move("spot", [0.3, 0, 0], [0, next(turn), 0]), rld.render()), reps)
    ms["moving_frame_with_light_change"] = timeit(lambda: (rld.move("spot", [next(step), 0, 0]),
                                                            rld.set_equirect(maps[2]), rld.render()), reps)
    rld.move("spot", np.zeros(3))
    return ms


def _speed(d: Path, quick: bool, leaf_lights: np.ndarray, maps: list[np.ndarray]) -> dict[str, Any]:
    from lightprobe.hostlink.relight.cuts.precompute import precompute
    from lightprobe.hostlink.relight.cuts.render import Relighter
    from lightprobe.hostlink.relight.scene import load_scene

    spheres, grid = (8, 8) if quick else (32, 32)
    reps = 3 if quick else 9
    out: dict[str, Any] = {"vcf_spheres": spheres, "vcf_grid": grid, "reps": reps}
    dyn_scene = load_scene(scene_file(d, True, 130, 640, 480))
    dyn = precompute(dyn_scene, spheres=spheres, grid=grid, cache_dir=d / "cache", progress=False)
    st_scene = load_scene(scene_file(d, False, 130, 640, 480))
    st = precompute(st_scene, cache_dir=d / "cache", progress=False)
    out["vertices"] = len(st.vertices)
    out["precompute_static_s"] = round(st.seconds, 1)
    out["precompute_movable_total_s"] = round(dyn.seconds, 1)
    out["precompute_vcf_s"] = round(dyn.vcf_seconds, 1)
    f = dyn.vcf[0]
    out["vcf_points"] = len(f.offsets) - 1
    out["vcf_mean_nodes"] = float(np.diff(f.offsets).mean())
    out["mean_svc_nodes_static"] = float(np.diff(st.svc_offsets).mean())
    out["bytes"] = _data_sizes(dyn)
    rls = Relighter(st_scene, st)
    rls.set_leaf_light(leaf_lights[1])
    rld = Relighter(dyn_scene, dyn)
    rld.set_leaf_light(leaf_lights[1])
    eye = st_scene.camera.position
    out["stage_ms"] = _stages(rld, eye, leaf_lights[1], reps)
    out["frame_ms"] = _frames(rls, rld, maps, reps)
    _, nodes = rld.vertex_radiance(eye, np.arange(len(dyn.vertices)))
    out["moving_mean_occluded_pieces"] = float(nodes.mean())
    # errors of the very scenes timed, against brute force on every stride-th vertex
    stride = 40 if quick else 10
    vidx = np.arange(0, len(st.vertices), stride)
    spot = st.object_id[vidx] == 0
    out["static_error_vs_reference"] = _errors(rls, leaf_lights, maps, eye, vidx, {"spot": spot, "ground": ~spot})
    for label, rot in (("moving", None), ("rotated", [0.0, 40.0, 0.0])):
        rld.move("spot", np.array([0.3, 0, 0]), None if rot is None else np.array(rot))
        dist = np.linalg.norm(rld.positions()[vidx] - rld._centers()[0], axis=1)
        inner = (dyn.object_id[vidx] == 1) & (dist < rld._radii[0, 0])
        out[f"{label}_error_vs_reference"] = _errors(
            rld, leaf_lights, maps, eye, vidx, {"spot": spot, "ground_inside_inner_sphere": inner,
                                          "ground_outside_inner_sphere": (dyn.object_id[vidx] == 1) & ~inner})
    rld.move("spot", np.zeros(3))
    return out


def _data_sizes(pre) -> dict[str, Any]:  # type: ignore[no-untyped-def]
    """Height-coded vs index-coded bytes with the same value encodings on both sides: SVC values
    as 8-bit codes + a float16 scale per cut (what the renderer uses) and as float16; VCF 1 bit."""
    f = pre.vcf[0]
    vh, vi = _sizes(f.offsets, "binary")
    out: dict[str, Any] = {"vcf_height": vh, "vcf_index": vi, "ratio_vcf": round(vh / vi, 4)}
    for kind in ("u8", "f16"):
        sh, si = _sizes(pre.svc_offsets, kind)
        out[kind] = {"svc_height": sh, "svc_index": si, "ratio_svc": round(sh / si, 4),
                     "total_height": sh + vh, "total_index": si + vi,
                     "ratio_total": round((sh + vh) / (si + vi), 4)}
    return out


def _plots(out_dir: Path, acc: dict[str, Any], speed: dict[str, Any]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 2, figsize=(11, 4))
    taus = [r["tau"] for r in acc["rows"]]
    for name in MAPS:
        ax[0].loglog(taus, [r["maps"][name]["moment"]["rel_rms"] for r in acc["rows"]], "o-", label=name[:14])
        ax[0].loglog(taus, [r["maps"][name]["plain"]["rel_rms"] for r in acc["rows"]], "x:", color=ax[0].lines[-1].get_color())
    ax[0].axhline(0.02, color="k", lw=0.8)
    ax[0].set(xlabel="tau (sr)", ylabel="relative RMS luminance error", title="SVC error (o moment, x plain)")
    ax[0].legend(fontsize=7)
    ax[1].loglog(taus, [r["mean_svc_nodes"] for r in acc["rows"]], "o-", label="mean SVC nodes")
    ax[1].loglog(taus, [r["svc_bytes_height"] / 1e6 for r in acc["rows"]], "s-", label="MB height-coded")
    ax[1].loglog(taus, [r["svc_bytes_index"] / 1e6 for r in acc["rows"]], "^-", label="MB index-coded")
    ax[1].set(xlabel="tau (sr)", title="cut size and data size (3,555 vertices)")
    ax[1].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(out_dir / "relight_tau.png", dpi=100)
    plt.close(fig)
    fig, ax = plt.subplots(figsize=(7, 4))
    fm = speed["frame_ms"]
    ax.barh(list(fm), [v["min"] for v in fm.values()], label="min")
    ax.barh(list(fm), [v["median"] - v["min"] for v in fm.values()], left=[v["min"] for v in fm.values()],
            alpha=0.5, label="median")
    ax.axvline(50, color="k", lw=0.8)
    ax.axvline(250, color="k", lw=0.8, ls=":")
    ax.legend(fontsize=7)
    ax.set(xlabel="ms", title=f"frame time, {speed['vertices']} vertices, this machine")
    fig.tight_layout()
    fig.savefig(out_dir / "relight_frame_ms.png", dpi=100)
    plt.close(fig)


def run(out_dir: Path, quick: bool) -> dict[str, Any]:
    import os

    from lightprobe.core.imageio import read_hdr_image
    from lightprobe.hostlink.relight.cuts.directions import cluster_compactness
    from lightprobe.hostlink.relight.cuts.lighting import leaf_light_from_equirect
    from lightprobe.hostlink.relight.cuts.precompute import default_cache_dir

    load_before = os.getloadavg()
    out_dir.mkdir(parents=True, exist_ok=True)
    d = default_cache_dir() / "bench"              # scene files + precompute cache, outside the repo
    d.mkdir(parents=True, exist_ok=True)
    maps = [read_hdr_image(SHARED / "envmaps" / m) for m in MAPS]
    leaf_lights = np.stack([leaf_light_from_equirect(m) for m in maps])
    acc = _accuracy(d, quick, leaf_lights, maps)
    speed = _speed(d, quick, leaf_lights, maps)
    comp = {str(k): round(v, 2) for k, v in cluster_compactness().items()}
    default = next(r for r in acc["rows"] if r["tau"] == 2e-5)
    summary = {
        "quick": quick,
        "default_tau": 2e-5,
        "max_rel_rms_default_tau_moment": max(v["moment"]["rel_rms"] for v in default["maps"].values()),
        "max_rel_rms_default_tau_plain": max(v["plain"]["rel_rms"] for v in default["maps"].values()),
        "frame_ms": speed["frame_ms"],
        "stage_ms": speed["stage_ms"],
        "load_average_before_after": [round(load_before[0], 2), round(os.getloadavg()[0], 2)],
        "max_static_error_20k": max(v["all"] for v in speed["static_error_vs_reference"].values()),
        "max_moving_error_20k_outside_inner_sphere": max(
            v.get("ground_outside_inner_sphere", 0.0) for v in speed["moving_error_vs_reference"].values()),
        "precompute_spot_3555v_svc_s": default["precompute_s"],
        "precompute_20k_static_s": speed["precompute_static_s"],
        "precompute_20k_movable_total_s": speed["precompute_movable_total_s"],
        "precompute_vcf_s": speed["precompute_vcf_s"],
        "bytes": speed["bytes"],
    }
    result = {"summary": summary, "accuracy": acc, "speed": speed, "compactness_deg_per_level": comp}
    from lightprobe.bench import relight_sg

    sg = relight_sg.run(out_dir, quick)         # side by side: the SG method, no precompute
    summary["sg"] = sg["summary"]
    result["sg"] = sg
    (out_dir / "relight.json").write_text(json.dumps(result, indent=1))
    _plots(out_dir, acc, speed)
    relight_sg.pareto_plot(out_dir, sg, result)
    return result
