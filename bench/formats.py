"""``lightprobe bench formats``: the host formats of #16, run time against error.

1. **Irradiance** per shared map (256-row reduction) and the simulator's ``daylight`` sun: the
   relative RMS error (RMS of the luminance error over RMS of the exact luminance, 512 upward
   Fibonacci normals, exact pixel sums) of order-2 SH alone and of ``ambient SH + primary light``.
2. **SH + primary light per frame** on a probe map (rooitou, upper hemisphere, 256 x 512): the
   estimator as the service runs it, when every pixel changes (sensor noise), when a lamp of 24
   pixels changes, and when nothing changed; median and min of 50 runs (the noise is drawn
   before timing).
3. **Cube map**: GGX prefilter (64 down to 4, 5 mips) time per map, median of 5, and each mip's
   worst error against the brute-force convolution at 64 random texels (the test's metric).

Writes ``formats.json`` and ``formats_irradiance.png``.
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["ggx_reference", "run"]

MAPS = ["studio_small_03_1k.hdr", "rooitou_park_1k.hdr", "potsdamer_platz_1k.hdr", "lebombo_1k.hdr",
        "dikhololo_night_1k.hdr", "interior_blender.exr"]
REC709 = np.array([0.2126, 0.7152, 0.0722])



def ggx_reference(equirect: np.ndarray, roughness: float, dirs: np.ndarray) -> np.ndarray:
    """The GGX-prefiltered radiance of an equirect map at ``dirs`` (k, 3), from the formula over
    every map pixel: the reference the probe's cube maps are checked against (written apart
    from :mod:`lightprobe.device.formats.cubemap`, sharing none of its functions).

    With ``n = v = r`` (the split-sum prefilter), each pixel's direction ``l`` and solid angle,
    ``h = (n + l) / |n + l|`` and ``D(h) = a^2 / (pi ((n.h)^2 (a^2 - 1) + 1)^2)``, ``a`` the
    roughness squared (at least 1e-4): ``sum D (n.l)+ L dOmega`` over the weight's integral on
    the whole sphere (numerical, in the angle from ``n``). Roughness 0 is the map itself,
    bilinear (longitude wraps). Non-finite and negative pixels count as 0."""
    from lightprobe.core.sphere import (
        angles_from_directions,
        equirect_directions,
        equirect_row_solid_angle,
    )

    m = np.where(np.isfinite(equirect) & (equirect > 0), equirect, 0.0).astype(np.float64)
    h, w = m.shape[:2]
    n = np.asarray(dirs, np.float64).reshape(-1, 3)
    if roughness <= 0:
        theta, phi = angles_from_directions(n)
        y = np.clip(theta / np.pi * h - 0.5, 0, h - 1)
        x = (phi / (2 * np.pi) * w - 0.5) % w
        y0, x0 = np.floor(y).astype(int), np.floor(x).astype(int)
        fy, fx = (y - y0)[:, None], (x - x0)[:, None]
        y1, x1 = np.minimum(y0 + 1, h - 1), (x0 + 1) % w
        return ((1 - fy) * ((1 - fx) * m[y0, x0] + fx * m[y0, x1]) + fy * ((1 - fx) * m[y1, x0] + fx * m[y1, x1]))
    a2 = max(roughness * roughness, 1e-4) ** 2

    def d_ggx(nh: np.ndarray) -> np.ndarray:
        return a2 / (np.pi * (nh * nh * (a2 - 1.0) + 1.0) ** 2)

    t = np.geomspace(1e-7, np.pi / 2, 400_001)  # the angle between n and l (the lobe is ~a wide)
    f = d_ggx(np.cos(t / 2)) * np.cos(t) * np.sin(t)
    norm = 2 * np.pi * float(np.sum(0.5 * (f[1:] + f[:-1]) * np.diff(t)))
    ldir = equirect_directions(h).reshape(-1, 3)
    power = m.reshape(-1, 3) * np.repeat(equirect_row_solid_angle(h), w)[:, None]
    out = np.empty((len(n), 3))
    for k, nk in enumerate(n):
        nl = ldir @ nk
        half = ldir + nk
        nh = (half @ nk) / np.maximum(np.linalg.norm(half, axis=1), 1e-300)
        wts = np.where(nl > 0, d_ggx(nh) * nl, 0.0)
        out[k] = wts @ power / norm
    return out

def _fib(n: int) -> np.ndarray:
    i = np.arange(n) + 0.5
    y = i / n
    r = np.sqrt(1 - y * y)
    ph = np.pi * (1 + 5**0.5) * i
    return np.stack([r * np.cos(ph), y, r * np.sin(ph)], 1)


def _exact(m: np.ndarray, n: np.ndarray) -> np.ndarray:
    from lightprobe.core.sphere import equirect_directions, equirect_row_solid_angle

    h = m.shape[0]
    d = equirect_directions(h).reshape(-1, 3)
    p = m.reshape(-1, 3).astype(np.float64) * np.repeat(equirect_row_solid_angle(h), 2 * h)[:, None]
    return np.clip(n @ d.T, 0, None) @ p


def _nrms(a: np.ndarray, b: np.ndarray) -> float:
    ya, yb = a @ REC709, b @ REC709
    return float(np.sqrt(np.mean((ya - yb) ** 2)) / np.sqrt(np.mean(yb**2)))


def _maps(shared: Path) -> dict[str, np.ndarray]:
    from lightprobe.core.imageio import read_hdr_image
    from lightprobe.core.sphere import coarse_equirect
    from lightprobe.sim.scenarios import load_scene

    out = {}
    for name in MAPS:
        m = read_hdr_image(shared / "envmaps" / name)
        out[name] = coarse_equirect(np.where(np.isfinite(m) & (m > 0), m, 0).astype(np.float32), 256)
    sc = load_scene("daylight", shared_data=shared)
    out["sim daylight (sun 0.27 deg)"] = coarse_equirect(np.asarray(sc.radiance_equirect(10.0), np.float32), 256)
    return out


def _timed(fn: Any, n: int) -> dict[str, float]:
    ts = []
    for _ in range(n):
        t = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t)
    return {"median_ms": 1e3 * float(np.median(ts)), "min_ms": 1e3 * float(np.min(ts))}


def run(out_dir: Path, quick: bool = False) -> dict[str, Any]:
    from lightprobe.core.sh import irradiance
    from lightprobe.device.formats.cubemap import CubemapFilter, face_directions
    from lightprobe.device.formats.sh_primary import EnvironmentEstimator
    from lightprobe.sim.scenarios import default_shared_data

    shared = default_shared_data()
    maps = _maps(shared)
    n = _fib(512)
    irr = []
    for name, m in maps.items():
        env = EnvironmentEstimator().estimate(m)
        exact = _exact(m, n)
        approx = irradiance(env.ambient, n)
        if env.primary is not None:
            approx = approx + np.clip(n @ env.primary.direction, 0, None)[:, None] * env.primary.rgb
        irr.append({"map": name, "sh_only": _nrms(irradiance(env.coefficients, n), exact),
                    "ambient_plus_primary": _nrms(approx, exact),
                    "primary_energy_fraction": env.primary.energy_fraction if env.primary else 0.0})

    # per-frame SH + primary light on a probe map
    probe = maps["rooitou_park_1k.hdr"].copy()
    probe[128:] = 0
    rng = np.random.default_rng(0)
    reps = 10 if quick else 50
    noisy = [probe * np.concatenate([1 + 0.01 * rng.standard_normal((128, 512, 3)), np.ones((128, 512, 3))]).astype(np.float32)
             for _ in range(8)]
    est = EnvironmentEstimator()
    est.estimate(probe)
    k = iter(range(10**9))
    dense = _timed(lambda: est.estimate(noisy[next(k) % 8]), reps)
    lamp_maps = []
    m = probe.copy()
    for _ in range(reps + 1):
        r, c = rng.integers(0, 120), rng.integers(0, 500)
        m = m.copy()
        m[r:r + 4, c:c + 6] += 1.0
        lamp_maps.append(m)
    est.estimate(lamp_maps[0])
    j = iter(range(1, 10**9))
    lamp = _timed(lambda: est.estimate(lamp_maps[next(j)]), reps)
    same = _timed(lambda: est.estimate(lamp_maps[-1]), reps)

    # cube maps
    flt = CubemapFilter(64)
    cubes = []
    for name in ("studio_small_03_1k.hdr", "rooitou_park_1k.hdr", "interior_blender.exr"):
        for hemi in (False, True):
            mm = maps[name].copy()
            if hemi:
                mm[128:] = 0
            flt.filter(mm)
            t = _timed(lambda mm=mm: flt.filter(mm), 2 if quick else 5)
            cm = flt.filter(mm)
            g = np.random.default_rng(7)
            errs = []
            for mip in range(len(cm.mips)):
                s = cm.mips[mip].shape[1]
                f, i, jj = g.integers(0, 6, 64), g.integers(0, s, 64), g.integers(0, s, 64)
                ref = ggx_reference(mm, cm.roughness[mip], face_directions(s)[f, i, jj]) @ REC709
                got = cm.mips[mip][f, i, jj].astype(np.float64) @ REC709
                errs.append(float(np.max(np.abs(got - ref) / np.maximum(ref, 0.05 * ref.mean()))))
            cubes.append({"map": name, "hemisphere": hemi, **t, "mip_max_rel_error": errs})

    # spherical Gaussians (#17): the fit on every map, sphere and probe hemisphere
    from lightprobe.core.lightset import LightSet
    from lightprobe.core.sg import SGLighting
    from lightprobe.core.sphere import (
        equirect_directions,
        equirect_integral,
        equirect_row_solid_angle,
    )
    from lightprobe.device.formats.sgfit import fit_sg
    from lightprobe.device.sampling.metrics import ErrorReference

    def sg_lights(sg: SGLighting, h: int = 256) -> LightSet:
        peak = np.array([k == "peak" for k in sg.kinds], bool)
        d = equirect_directions(h).reshape(-1, 3)
        om = np.repeat(equirect_row_solid_angle(h), 2 * h)
        res = SGLighting(sg.axes[~peak], sg.sharpness[~peak], sg.amplitude[~peak], [k for k in sg.kinds if k != "peak"])
        return LightSet(np.concatenate([d, sg.axes[peak]]), np.concatenate([res.radiance(d) * om[:, None], sg.energy()[peak]]),
                        np.concatenate([om, np.zeros(int(peak.sum()))]))

    sgs = []
    for name, m0 in maps.items():
        for hemi in (False, True):
            mm = m0.copy()
            if hemi:
                mm[128:] = 0
            fit_sg(mm)
            t = _timed(lambda mm=mm: fit_sg(mm), 3 if quick else 10)
            sg = fit_sg(mm)
            ref = ErrorReference(mm)
            ls = sg_lights(sg)
            sgs.append({"map": name, "hemisphere": hemi, **t, "lobes": len(sg), "peak_lobes": sg.kinds.count("peak"),
                        "energy_error": float(sg.energy().sum(axis=0) @ REC709 / (equirect_integral(mm) @ REC709) - 1),
                        "diffuse": ref.error("diffuse", ls), "glossy": ref.error("glossy", ls),
                        "residual_l2": [lv["residual_l2"] for lv in sg.levels]})

    result = {"irradiance": irr, "sg": sgs, "sh_primary_per_frame": {"all_pixels_change": dense, "lamp_24_px": lamp,
                                                          "unchanged": same},
              "cubemap_64": cubes, "roughness": flt.roughness}
    (out_dir / "formats.json").write_text(json.dumps(result, indent=1))
    _plot(out_dir, irr)
    return result


def _plot(out_dir: Path, irr: list[dict[str, Any]]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 3.6))
    x = np.arange(len(irr))
    ax.bar(x - 0.2, [100 * r["sh_only"] for r in irr], 0.4, label="order-2 SH alone")
    ax.bar(x + 0.2, [100 * r["ambient_plus_primary"] for r in irr], 0.4, label="ambient SH + primary light")
    ax.axhline(2.0, color="k", lw=0.8, ls="--")
    ax.set_xticks(x, [r["map"].replace("_1k.hdr", "").replace(".exr", "") for r in irr], rotation=20, fontsize=8)
    ax.set_ylabel("irradiance RMS error (%)")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(out_dir / "formats_irradiance.png", dpi=110)
    plt.close(fig)
