"""The room's lamps from the probes that see them (the issue's "lights for free"): each probe's
peak SG lobes (``GET /api/v1/sg``, with the probe's world ``pose``) placed in ``room.obj``.

Loscos et al. measured their moved lamp's position by hand; a mounted probe sees every lamp
that switches on as a peak in its map, and a probe's peaks plus its pose are rays from a known
point. What is done with them:

- **Lamps per probe**: the peak lobes (``kind == "peak"``; the probe splits a wide peak into up
  to three) are grouped into lamps: a lobe within ``max(3 theta, 2 deg)`` of a brighter lamp's
  axis joins it, ``theta = 2 / sqrt(lambda)`` being a lobe's angular radius (a cap of half-angle
  theta has mean resultant length ``1 - theta^2 / 4``, the sharpness ``lambda`` the probe fitted
  to it). A lamp's energy ``E`` (rgb) is its lobes' integrals, ``sum(amplitude 2 pi / lambda
  (1 - exp(-2 lambda)))``: the irradiance the lamp gives at the probe at normal incidence. A lamp
  needs ``MIN_FRACTION`` of the probe's peak energy and, at its axis, ``MIN_CONTRAST`` times the
  probe's mean radiance (a room's brightest wall patches are peaks too, far dimmer than a lamp).
- **Where**: a lamp seen by two or more probes is where their rays meet (least squares over the
  rays; a pair matches when its rays pass within ``max(d theta, 2% d)`` of each other, in front of
  both probes and short of the walls they hit); a lamp one probe sees is taken to be on the
  surface its ray meets first (a ceiling or wall fitting), its centre one radius back along the
  ray, unless another probe has that point in view and saw no lamp there (then it was a bright
  patch of wall). A ray that leaves the room (an open side, a window) gives no lamp. One probe
  cannot tell a lamp from its glow on a wall right behind it, nor place a lamp it sees at grazing
  incidence to that wall: two probes can.
- **How bright**: a small sphere of power ``Phi`` gives ``E = Phi / (4 pi d^2)`` at distance
  ``d``, so ``Phi = 4 pi d^2 E``, averaged over the probes that see it; its radius
  ``d tan(theta)`` (at least 5 mm: the probe's optics blur a lamp, so this is an upper bound).

The probes' unit is the room camera's only if both are calibrated to the same one; otherwise the
recovered reflectance is off by one global factor (the paper's "emittance arbitrary").
"""

from __future__ import annotations

import json
import math
import urllib.request
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from lightprobe.core.errors import InputError
from lightprobe.core.sg import SGLighting, lobe_integral
from lightprobe.core.sphere import luminance
from lightprobe.hostlink.relight.room.io import Light

__all__ = ["FoundLamp", "lights_from_probes", "load_probe_sg"]

MIN_RADIUS = 0.005          # m: the smallest lamp radius reported
MIN_FRACTION = 0.02         # a probe's lamp needs this share of the energy of all its peaks
MIN_CONTRAST = 20.0         # and a radiance at its axis this many times the probe's mean radiance


@dataclass
class FoundLamp:
    light: Light
    probes: list[int]                   # indices of the probes that saw it
    method: str                         # "triangulated" or "surface"
    gap: float = 0.0                    # triangulated: rms distance of the rays from the point (m)
    notes: list[str] = field(default_factory=list)


@dataclass
class _Lamp:
    probe: int
    origin: np.ndarray
    axis: np.ndarray        # world
    theta: float            # angular radius (rad)
    energy: np.ndarray      # rgb irradiance at normal incidence at the probe
    hit: float              # distance to the first surface along the ray (inf: none)


def load_probe_sg(source: str | Path) -> dict[str, Any]:
    """An SG body with its pose: a file, or a probe's base URL (``http://host:port``; its
    ``/api/v1/sg``)."""
    s = str(source)
    if s.startswith(("http://", "https://")):
        url = s.rstrip("/")
        if not url.endswith("/api/v1/sg"):
            url += "/api/v1/sg"
        try:
            with urllib.request.urlopen(url, timeout=10) as r:
                doc = json.loads(r.read())
        except (OSError, ValueError) as e:
            raise InputError(f"{url}: {e}", param="sg") from e
    else:
        p = Path(s)
        try:
            doc = json.loads(p.read_text())
        except FileNotFoundError as e:
            raise InputError(f"{p}: no such file", param="sg") from e
        except (OSError, ValueError) as e:
            raise InputError(f"{p}: not JSON ({e})", param="sg") from e
    if not isinstance(doc, dict):
        raise InputError(f"{s}: not an SG body", param="sg")
    return doc


def _pose(doc: dict[str, Any], where: str) -> tuple[np.ndarray, np.ndarray]:
    pose = doc.get("pose")
    if not isinstance(pose, dict):
        raise InputError(f"{where}: no \"pose\" (the probe's world pose: rotation, position)", param="pose")
    try:
        R = np.asarray(pose["rotation"], np.float64)
        t = np.asarray(pose["position"], np.float64)
    except (KeyError, TypeError, ValueError) as e:
        raise InputError(f"{where}: pose needs a 3x3 rotation and a position [x, y, z]", param="pose") from e
    if R.shape != (3, 3) or t.shape != (3,) or not (np.isfinite(R).all() and np.isfinite(t).all()) \
            or not np.allclose(R @ R.T, np.eye(3), atol=1e-5) or np.linalg.det(R) < 0:
        raise InputError(f"{where}: pose.rotation must be a rotation matrix and pose.position 3 numbers", param="pose")
    return R, t


def _lamps_of(doc: dict[str, Any], k: int, where: str, min_fraction: float) -> list[_Lamp]:
    R, origin = _pose(doc, where)
    sg = SGLighting.from_json(doc)
    sel = [i for i, kind in enumerate(sg.kinds) if kind == "peak"]
    if not sel:
        return []
    ax = np.asarray(sg.axes, np.float64)[sel]
    ax /= np.linalg.norm(ax, axis=1, keepdims=True)
    lam = np.asarray(sg.sharpness, np.float64)[sel]
    e = np.asarray(sg.amplitude, np.float64)[sel] * lobe_integral(lam)[:, None]
    th = 2.0 / np.sqrt(np.maximum(lam, 1e-9))
    groups: list[list[int]] = []
    for i in np.argsort(-luminance(e)):
        for g in groups:
            a0 = ax[g[0]]
            if math.acos(min(1.0, float(ax[i] @ a0))) < max(3 * th[g[0]], math.radians(2.0)):
                g.append(int(i))
                break
        else:
            groups.append([int(i)])
    total = max(float(luminance(e).sum()), 1e-300)
    mean = float(luminance(np.asarray(doc.get("energy", e.sum(axis=0)), np.float64))) / (4 * math.pi)
    peak = luminance(np.asarray(sg.amplitude, np.float64)[sel])
    out = []
    for g in groups:
        if float(luminance(e[g]).sum()) < min_fraction * total or float(peak[g].max()) < MIN_CONTRAST * mean:
            continue            # a bright patch of wall, not a lamp
        w = np.maximum(luminance(e[g]), 1e-300)
        a = (w[:, None] * ax[g]).sum(axis=0)
        a /= np.linalg.norm(a)
        ang = np.arccos(np.clip(ax[g] @ a, -1, 1))
        theta = float(np.sqrt((w * (th[g] ** 2 + ang ** 2)).sum() / w.sum()))
        out.append(_Lamp(k, origin, R @ a, theta, e[g].sum(axis=0), math.inf))
    return out


def _view(doc: dict[str, Any]) -> tuple[np.ndarray, np.ndarray, bool]:
    """A probe's rotation, position and whether its map covers the whole sphere (a fisheye probe's
    holds the upper hemisphere only: its lobes below the horizon carry no light)."""
    R, t = _pose(doc, "probe")
    sg = SGLighting.from_json(doc)
    ax = np.asarray(sg.axes, np.float64).reshape(-1, 3)
    e = luminance(np.asarray(sg.amplitude, np.float64).reshape(-1, 3)) * lobe_integral(np.asarray(sg.sharpness, np.float64))
    below = float(e[ax[:, 1] < -0.3].sum()) if len(e) else 0.0
    return R, t, below > 0.01 * max(float(e.sum()), 1e-300)


def _would_see(es: Any, view: tuple[np.ndarray, np.ndarray, bool], p: np.ndarray) -> bool:
    """Whether a probe has the point ``p`` in its field of view with nothing of the room between."""
    R, t, sphere = view
    w = p - t
    dist = float(np.linalg.norm(w))
    if dist < 1e-6:
        return False
    w = w / dist
    if not sphere and float((R.T @ w)[1]) < 0.0:
        return False
    res = es.run(t[None].astype(np.float32), w[None].astype(np.float32), output=1)
    return bool(res["primID"][0] < 0 or float(res["tfar"][0]) > dist * 0.97)


def _closest(a: _Lamp, b: _Lamp) -> tuple[float, float, float]:
    """Distances along a's and b's rays of their closest approach, and the gap there."""
    w0 = a.origin - b.origin
    bb = float(a.axis @ b.axis)
    d, e = float(a.axis @ w0), float(b.axis @ w0)
    den = 1.0 - bb * bb
    if den < 1e-9:
        return -1.0, -1.0, math.inf
    s = (bb * e - d) / den
    t = (e - bb * d) / den
    gap = float(np.linalg.norm(a.origin + s * a.axis - b.origin - t * b.axis))
    return s, t, gap


def _triangulate(rays: list[_Lamp]) -> tuple[np.ndarray, float]:
    A = np.zeros((3, 3))
    rhs = np.zeros(3)
    for r in rays:
        P = np.eye(3) - np.outer(r.axis, r.axis)
        A += P
        rhs += P @ r.origin
    p = np.linalg.solve(A, rhs)
    gap = math.sqrt(sum(float(np.sum(((np.eye(3) - np.outer(r.axis, r.axis)) @ (p - r.origin)) ** 2)) for r in rays) / len(rays))
    return p, gap


def lights_from_probes(room: str | Path, probes: Sequence[dict[str, Any] | str | Path], *,
                       min_fraction: float = MIN_FRACTION) -> list[FoundLamp]:
    """The lamps the ``probes`` see, placed in ``room`` (a room folder or its room.obj). Each probe
    is an SG body with its ``pose`` (a dict, a file or a probe URL: :func:`load_probe_sg`); a
    probe's lamp with under ``min_fraction`` of its peaks' energy is left out."""
    from lightprobe.hostlink.relight.rays import build_embree
    from lightprobe.hostlink.relight.scene import load_obj_groups

    obj = Path(room)
    obj = obj / "room.obj" if obj.is_dir() else obj
    mesh, _, _ = load_obj_groups(obj)
    es = build_embree([(mesh.vertices, mesh.faces)])
    docs = [(p, f"probe {k}") if isinstance(p, dict) else (load_probe_sg(p), str(p)) for k, p in enumerate(probes)]
    if not docs:
        raise InputError("no probes given", param="sg")
    per = [_lamps_of(doc, k, where, min_fraction) for k, (doc, where) in enumerate(docs)]
    rays = [lp for lamps in per for lp in lamps]
    if rays:
        o = np.array([r.origin for r in rays], np.float32)
        d = np.array([r.axis for r in rays], np.float32)
        res = es.run(o, d, output=1)
        prim, dist = np.asarray(res["primID"]), np.asarray(res["tfar"], np.float64)
        for r, pr, t in zip(rays, prim, dist, strict=True):
            r.hit = float(t) if pr >= 0 else math.inf
    views = [_view(doc) for doc, _ in docs]
    used: set[int] = set()
    found: list[FoundLamp] = []
    order = sorted(range(len(rays)), key=lambda i: -float(luminance(rays[i].energy)))
    for i in order:
        if i in used:
            continue
        a = rays[i]
        cluster = [i]
        for k in range(len(per)):
            if k == a.probe:
                continue
            best, best_gap = -1, math.inf
            for j, b in enumerate(rays):
                if j in used or b.probe != k or j in cluster:
                    continue
                s, t, gap = _closest(a, b)
                if s <= 0 or t <= 0 or s > a.hit * 1.02 + 0.01 or t > b.hit * 1.02 + 0.01:
                    continue
                tol = max(s * a.theta, t * b.theta, 0.02 * (s + t) / 2)
                if gap <= tol and gap / (s + t) < best_gap:
                    best, best_gap = j, gap / (s + t)
            if best >= 0:
                cluster.append(best)
        used.update(cluster)
        rs = [rays[j] for j in cluster]
        notes: list[str] = []
        if len(rs) >= 2:
            p, gap = _triangulate(rs)
            method = "triangulated"
        else:
            if not math.isfinite(a.hit):
                continue        # a ray out of the room (open side, window): no lamp to place
            r0 = max(a.hit * math.tan(a.theta), MIN_RADIUS)
            p = a.origin + max(a.hit - r0, 0.5 * a.hit) * a.axis
            if any(_would_see(es, views[k], p) for k in range(len(per)) if k != a.probe):
                continue        # another probe has it in view and saw no lamp there: a bright wall patch
            gap, method = 0.0, "surface"
            notes.append("seen by one probe: placed on the surface its ray meets")
        ds = [float(np.linalg.norm(p - r.origin)) for r in rs]
        power = np.mean([4 * math.pi * dd * dd * r.energy for dd, r in zip(ds, rs, strict=True)], axis=0)
        radius = max(float(np.median([dd * math.tan(r.theta) for dd, r in zip(ds, rs, strict=True)])), MIN_RADIUS)
        if method == "surface":
            radius = min(radius, 0.5 * a.hit)
        found.append(FoundLamp(Light(tuple(float(x) for x in p), radius, tuple(float(x) for x in power)),   # type: ignore[arg-type]
                               sorted(r.probe for r in rs), method, gap, notes))
    return found
