"""Relighting with spherical Gaussians (Michiels, Put, Bekaert 2015): no precompute, so meshes may
move or deform every frame.

The lighting is the probe's SG lobes (:class:`device.core.sg.SGLighting`: ``GET /api/v1/sg``, or
fitted here from a map with :func:`device.sampling.sgfit.fit_sg`): a few *peak* lobes (lamps,
the sun) and many *residual* lobes on fixed HEALPix grids. Outgoing radiance at a point with
normal ``n`` towards ``w_o`` (paper eq. 1-2, the BRDF as SGs, visibility by cones)::

    B = kd / pi [E_res(n) V_res + sum_p mu_p C_p(n . p_p) v_p]
      + ks (e + 2) / (2 pi) [(n . r) G_e(r) v_r + sum_p mu_p <G_p, S(r, e)> (n . q_p)+ v_p]

Choices the paper leaves open, and why:

- **Residual lobes through tables.** Per light change the residual lobes are summed into
  direction tables, each a closed-form integral of every lobe against one kernel: ``E_res``
  against the exact clamped cosine (a zonal function of ``a . p`` per lobe sharpness, integrated
  numerically once per sharpness, so an unshadowed Lambert point is exact up to the fit), and SG
  kernels (paper eq. 4's product in closed form) for the visibility weights and the Phong lobe.
  The residual grids are fixed, so each table is one matrix-vector product with a matrix cached
  by the lobes' axes and sharpness; the cost of a light change does not depend on the mesh.
- **Visibility of the residual: 7 cones** (paper: circle packing): one along ``n`` and six tilted
  60 deg, half-angle 30 deg. Each cone is a visibility SG ``S_c`` (sharpness from the half-angle
  by paper eq. 5-6, ``ln 2 / (1 - cos alpha)``); the light arriving through cone ``c`` is the
  triple product (cosine SG, ``S_c``, lighting), so ``V_res`` is the cones' transmittances
  weighted by the light each carries. Unoccluded points get ``V_res = 1`` exactly.
- **Peaks** (1-3 SGs per lamp): each with its own visibility ``v_p``, the cosine exact
  (``C_p``: the zonal clamped-cosine integral of that lobe), the Phong term by the closed-form
  product of the peak with the BRDF lobe, the cosine taken at the product's axis ``q_p``.
- **Phong as one SG** of sharpness ``e`` about the reflection ``r`` of ``w_o``, ``cos^e x ~
  exp(e (cos x - 1))``; the residual's Phong term takes the cosine at ``r`` and one cone about
  ``r`` of the lobe's half-angle (paper eq. 5-6: ``acos(1 - ln 2 / e)``). Blinn-Phong and Ward
  are not offered (their SG warps vary per point): :class:`SGRelighter` refuses them by name.
- **Visibility**, two ways. ``"voxels"`` (the paper's): the scene voxelised (every triangle's
  voxels, per object, re-voxelised only for objects that moved or deformed: dirty flags), an
  occupancy mip pyramid, cones traced front to back (:func:`~hostlink.relight.sgkernels.trace_cones`).
  ``"rays"`` (the exact baseline): Embree rays, 16 per cone uniformly within it and 32 per peak
  drawn from the lobe's own distribution, cosine-weighted.
"""

from __future__ import annotations

import hashlib
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from device.core.errors import InputError
from device.core.sg import SGLighting
from hostlink.relight.scene import Camera, Scene, rotation_matrix, vertex_normals
from hostlink.relight.sgkernels import (
    LAM_COS,
    MU_COS,
    cone_frame,
    shade_points,
    trace_cones,
    voxelize,
)

__all__ = ["SGRelighter", "zonal_cosine"]

RING_TILT = math.radians(60.0)
CONE_HALF = math.radians(30.0)
LAM_CONE = math.log(2.0) / (1.0 - math.cos(CONE_HALF))          # paper eq. 5-6 inverted
RADIANCE_GRID = 32         # rows of the residual radiance table (ray weights)
DIFFUSE_GRID = 24          # rows of the diffuse tables (smooth kernels: 7.5 deg cells)
ZONAL_SAMPLES = 1025
RAYS_PER_CONE = 16
RAYS_PER_PEAK = 32


# ---- kernels over the sphere -------------------------------------------------------------------
def _grid_dirs(H: int) -> np.ndarray:
    th = np.arange(H) * np.pi / (H - 1)          # rows on both poles: exact where normals cluster
    ph = (np.arange(2 * H) + 0.5) * np.pi / H
    st, ct = np.sin(th)[:, None], np.cos(th)[:, None]
    d = np.stack([st * np.cos(ph)[None], np.broadcast_to(ct, (H, 2 * H)), st * np.sin(ph)[None]], -1)
    return d.reshape(-1, 3)


def zonal_cosine(lam: float, samples: int = ZONAL_SAMPLES) -> np.ndarray:
    """``C(t) = integral exp(lam (p . w - 1)) max(a . w, 0) dw`` on ``t = a . p`` in
    ``linspace(-1, 1, samples)``. In coordinates about ``p`` the azimuthal integral of the clamped
    cosine is closed form (``2 (A sin f + B f)``, ``f = acos(-B / A)``); the polar one is
    Gauss-Legendre in ``u = 1 - cos theta`` over where the lobe is above 1e-22 of its peak."""
    t = np.linspace(-1.0, 1.0, samples)
    umax = min(2.0, 50.0 / max(lam, 1e-9))
    x, w = np.polynomial.legendre.leggauss(256)
    u = (x + 1) * 0.5 * umax
    wu = w * 0.5 * umax * np.exp(-lam * u)
    ct = 1 - u
    stt = np.sqrt(np.clip(1 - ct * ct, 0, None))
    cb, sb = t[:, None], np.sqrt(np.clip(1 - t * t, 0, None))[:, None]
    A, B = sb * stt[None], cb * ct[None]
    with np.errstate(divide="ignore", invalid="ignore"):
        c = np.where(A > 1e-12, -B / np.where(A > 1e-12, A, 1), np.where(B > 0, -2.0, 2.0))
    f = np.arccos(np.clip(c, -1, 1))
    g = np.where(c <= -1, 2 * np.pi * B, np.where(c >= 1, 0.0, 2 * (A * np.sin(f) + B * f)))
    return np.asarray(g @ wu)


def _sg_dot(lam_k: float, a: np.ndarray, lam: np.ndarray, p: np.ndarray) -> np.ndarray:
    """``integral exp(lam_k (a . w - 1)) exp(lam (p . w - 1)) dw`` for table directions ``a``
    (D, 3) and lobes (M,): (D, M), overflow-free."""
    r = np.sqrt(np.maximum(lam_k ** 2 + lam[None] ** 2 + 2 * lam_k * lam[None] * (a @ p.T), 0.0))
    s = lam_k + lam[None]
    safe = np.where(r > 1e-9, r, 1.0)
    return np.where(r > 1e-9, 2 * np.pi * (np.exp(r - s) - np.exp(-r - s)) / safe, 4 * np.pi * np.exp(-s))


def _table_lookup(tab: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Bilinear lookup of an (H, 2H) direction table (the layout of :mod:`hostlink.relight.sgkernels`)."""
    H = tab.shape[0]
    th = np.arccos(np.clip(d[:, 1], -1, 1))
    ph = np.mod(np.arctan2(d[:, 2], d[:, 0]), 2 * np.pi)
    fi, fj = th * (H - 1) / np.pi, ph * H / np.pi - 0.5
    i0, j0 = np.floor(fi).astype(np.int64), np.floor(fj).astype(np.int64)
    wi, wj = fi - i0, fj - j0
    i1, i0 = np.clip(i0 + 1, 0, H - 1), np.clip(i0, 0, H - 1)
    j1, j0 = (j0 + 1) % (2 * H), j0 % (2 * H)
    return ((1 - wi) * ((1 - wj) * tab[i0, j0] + wj * tab[i0, j1]) + wi * ((1 - wj) * tab[i1, j0] + wj * tab[i1, j1]))


def anisotropic_pyramid(occ: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Three occupancy mip pyramids of an (R, R, R) [z, y, x] grid, one per axis: level l + 1 of
    the axis-``k`` pyramid combines each pair of children along axis k as one occluder after the
    other (``1 - (1 - a)(1 - b)``) and averages across the other two axes, so a cell holds the
    probability that a ray crossing it along k is blocked (a floor stays opaque to rays through
    it at every level, and thin to rays along it). Returned flat, (3, total) float32, with the
    level offsets."""
    levels: list[list[np.ndarray]] = [[occ, occ, occ]]
    while levels[-1][0].shape[0] > 1:
        nxt = []
        for k, a in enumerate(levels[-1]):   # k = 0: x (array axis 2), 1: y (axis 1), 2: z (axis 0)
            r = a.shape[0] // 2
            b = a.reshape(r, 2, r, 2, r, 2)
            ax = {0: 5, 1: 3, 2: 1}[k]
            lo, hi = np.take(b, 0, axis=ax), np.take(b, 1, axis=ax)
            over = 1 - (1 - lo) * (1 - hi)
            nxt.append(over.mean(axis=_other(ax)))
        levels.append(nxt)
    offs = np.concatenate([[0], np.cumsum([lv[0].size for lv in levels])]).astype(np.int64)
    flat = np.stack([np.concatenate([lv[k].ravel() for lv in levels]) for k in range(3)]).astype(np.float32)
    return flat, offs


def _other(ax: int) -> tuple[int, int]:
    """After removing pair axis ``ax`` from the (r, 2, r, 2, r, 2) view, the two remaining pair axes."""
    rest = [x for x in (1, 3, 5) if x != ax]
    return tuple(x - (1 if x > ax else 0) for x in rest)  # type: ignore[return-value]


@dataclass
class _Tables:
    E: np.ndarray
    Wc: np.ndarray
    Wr: np.ndarray
    G: np.ndarray           # (slots, H, 2H, 3)
    L: np.ndarray | None = None   # (H, 2H) the residual's luminance (ray visibility weights)


class _TableCache:
    """Per lobe set (axes, sharpness) and kernel: the (D, M) float32 matrix mapping the lobes'
    amplitudes to a direction table. A probe's residual grids are fixed, so after the first
    frame every light change is matrix-vector products only."""

    def __init__(self) -> None:
        self._key: bytes | None = None
        self._mats: dict[tuple[str, float, int], np.ndarray] = {}
        self._zonal: dict[float, np.ndarray] = {}

    def zonal(self, lam: float) -> np.ndarray:
        key = float(np.float32(lam))
        z = self._zonal.get(key)
        if z is None:
            if len(self._zonal) > 4096:
                self._zonal.clear()
            z = self._zonal[key] = zonal_cosine(key)
        return z

    def matrix(self, axes: np.ndarray, lam: np.ndarray, kind: str, lam_k: float, H: int) -> np.ndarray:
        key = hashlib.blake2b(np.ascontiguousarray(axes).tobytes() + np.ascontiguousarray(lam).tobytes(),
                              digest_size=16).digest()
        if key != self._key:
            self._key, self._mats = key, {}
        mk = (kind, float(lam_k), H)
        m = self._mats.get(mk)
        if m is None:
            d = _grid_dirs(H)
            if kind == "radiance":
                m = np.exp(lam[None] * (d @ axes.T - 1.0)).astype(np.float32)
            elif kind == "cos":
                m = np.zeros((len(d), len(lam)), np.float32)
                tk = np.linspace(-1, 1, ZONAL_SAMPLES)
                for u in np.unique(lam):
                    sel = np.flatnonzero(lam == u)
                    m[:, sel] = np.interp(d @ axes[sel].T, tk, self.zonal(float(u)))
            else:
                m = _sg_dot(lam_k, d, lam, axes).astype(np.float32)
            self._mats[mk] = m
        return m


# ---- scene state -------------------------------------------------------------------------------
@dataclass
class _Object:
    name: str
    rest: np.ndarray        # (V, 3) vertices as loaded
    faces: np.ndarray       # (F, 3) local indices
    base: int               # first global vertex index


class SGRelighter:
    """SG relighting of a :class:`~hostlink.relight.scene.Scene`: no precompute.

    ``visibility``: ``"voxels"`` (voxel cone tracing, ``voxels`` cells along the scene's longest
    side) or ``"rays"`` (Embree). Lights: :meth:`set_sg` / :meth:`set_equirect`. Geometry:
    :meth:`set_vertices` (deform an object: new vertex positions, same faces), :meth:`move`
    (rigid, relative to the loaded pose). Shading: :meth:`vertex_radiance`, :meth:`render`
    (per pixel)."""

    def __init__(self, scene: Scene, *, visibility: str = "voxels", voxels: int = 128,
                 cone_gain: float = 1.0, cone_start: float = 2.0, cone_lift: float = 1.5,
                 cone_footprint: float = 0.2, solid: bool = False) -> None:
        if visibility not in ("voxels", "rays"):
            raise InputError(f"visibility must be 'voxels' or 'rays', got {visibility!r}", param="visibility")
        if voxels < 8 or voxels > 1024 or voxels & (voxels - 1):
            raise InputError(f"voxels must be a power of two in [8, 1024], got {voxels!r}", param="voxels")
        self.scene, self.visibility, self.R = scene, visibility, int(voxels)
        self.cone_gain, self.cone_start, self.cone_lift = cone_gain, cone_start, cone_lift
        self.cone_footprint, self.solid = cone_footprint, solid
        names = list(scene.materials)
        for n in names:
            if scene.materials[n].type not in ("lambert", "phong"):
                raise InputError(f"material {n!r}: the SG method shades lambert and phong, not "
                                 f"{scene.materials[n].type!r}", param="material")
        self.mats = np.stack([scene.materials[n].row() for n in names])
        exps = sorted({float(scene.materials[n].exponent) for n in names if scene.materials[n].type == "phong"})
        self._gloss = exps or [1.0]
        self.gloss_slot = np.array([self._gloss.index(float(scene.materials[n].exponent))
                                    if scene.materials[n].type == "phong" else 0 for n in names], np.int64)
        self.objects: list[_Object] = []
        base = 0
        for o in scene.objects:
            self.objects.append(_Object(o.name, np.array(o.mesh.vertices, np.float64), np.asarray(o.mesh.faces, np.int64), base))
            base += len(o.mesh.vertices)
        self.faces = np.concatenate([ob.faces + ob.base for ob in self.objects])
        self.matid = np.concatenate([np.full(len(ob.rest), names.index(o.material), np.int64)
                                     for ob, o in zip(self.objects, scene.objects, strict=True)])
        self.vertices = np.concatenate([ob.rest for ob in self.objects])
        self._normals = np.concatenate([vertex_normals(o.mesh) for o in scene.objects])
        self._cache = _TableCache()
        self._tables: _Tables | None = None
        self._peaks = (np.zeros((0, 3)), np.zeros(0), np.zeros((0, 3)), np.zeros((0, ZONAL_SAMPLES)))
        self.sg: SGLighting | None = None
        self._dirty = set(range(len(self.objects)))
        self._occ: list[np.ndarray | None] = [None] * len(self.objects)
        lo, hi = self.vertices.min(axis=0), self.vertices.max(axis=0)
        c, side = (lo + hi) / 2, float((hi - lo).max()) * 1.25 + 1e-9
        self.vox = side / self.R
        self.origin = c - side / 2
        self._pyr: tuple[np.ndarray, np.ndarray] | None = None
        self._embree: Any = None
        self._geometry = 0          # bumped by every deformation or move
        self.stats: dict[str, float] = {}

    # ---- lighting ----------------------------------------------------------------------------
    def set_equirect(self, img: np.ndarray) -> None:
        """Fit SG lobes to an (H, 2H, 3) map (as the probe does) and use them."""
        from device.sampling.sgfit import WORK_HEIGHT, fit_sg

        a = np.asarray(img, np.float32)
        if a.ndim != 3 or a.shape[2] != 3 or a.shape[1] != 2 * a.shape[0]:
            raise InputError(f"expected an (H, 2H, 3) equirect map, got shape {a.shape}", param="lights")
        h = a.shape[0]
        if h > WORK_HEIGHT and h % WORK_HEIGHT:
            import cv2

            h = max(WORK_HEIGHT, h // WORK_HEIGHT * WORK_HEIGHT)
            a = np.asarray(cv2.resize(a, (2 * h, h), interpolation=cv2.INTER_AREA), np.float32)
        self.set_sg(fit_sg(a))

    def set_sg(self, sg: SGLighting) -> None:
        """Use these lobes: residual lobes go into the direction tables, peaks stay lobes."""
        peak = np.array([k == "peak" for k in sg.kinds], bool)
        res = ~peak
        ax, lam, amp = sg.axes[res], sg.sharpness[res], sg.amplitude[res]
        c = self._cache
        Hg = [self._gloss_grid(e) for e in self._gloss]
        G = max(Hg)
        tabs = _Tables(
            (c.matrix(ax, lam, "cos", 0.0, DIFFUSE_GRID) @ amp.astype(np.float32)).reshape(DIFFUSE_GRID, -1, 3),
            (c.matrix(ax, lam, "sg", self._lam_center, DIFFUSE_GRID) @ amp.astype(np.float32)).reshape(DIFFUSE_GRID, -1, 3),
            (c.matrix(ax, lam, "sg", self._lam_ring, DIFFUSE_GRID) @ amp.astype(np.float32)).reshape(DIFFUSE_GRID, -1, 3),
            np.zeros((len(self._gloss), G, 2 * G, 3), np.float32))
        for s, (e, h) in enumerate(zip(self._gloss, Hg, strict=True)):
            t = (c.matrix(ax, lam, "sg", e, h) @ amp.astype(np.float32)).reshape(h, 2 * h, 3)
            if h != G:
                import cv2

                t = cv2.resize(t, (2 * G, G), interpolation=cv2.INTER_LINEAR)
            tabs.G[s] = t
        if self.visibility == "rays":  # the residual's radiance, to weight each cone's rays by
            lum = amp @ np.array([0.2126, 0.7152, 0.0722])
            tabs.L = (c.matrix(ax, lam, "radiance", 0.0, RADIANCE_GRID) @ lum.astype(np.float32)).reshape(RADIANCE_GRID, -1)
        self._tables = tabs
        pl = sg.sharpness[peak]
        pF = np.stack([c.zonal(float(x)) for x in pl]) if len(pl) else np.zeros((0, ZONAL_SAMPLES))
        self._peaks = (sg.axes[peak].copy(), pl.copy(), sg.amplitude[peak].copy(), pF)
        self.sg = sg

    @staticmethod
    def _gloss_grid(e: float) -> int:
        return 32 if e <= 32 else 64 if e <= 128 else 128

    @property
    def _lam_center(self) -> float:
        return LAM_COS + LAM_CONE

    @property
    def _lam_ring(self) -> float:
        return math.sqrt(LAM_COS ** 2 + LAM_CONE ** 2 + 2 * LAM_COS * LAM_CONE * math.cos(RING_TILT))

    # ---- geometry ----------------------------------------------------------------------------
    def _index(self, name: str) -> int:
        for k, ob in enumerate(self.objects):
            if ob.name == name:
                return k
        raise InputError(f"no object named {name!r} (objects: {', '.join(o.name for o in self.objects)})", param="object")

    def set_vertices(self, name: str, vertices: np.ndarray) -> None:
        """Deform object ``name``: its vertices now (same count and faces)."""
        k = self._index(name)
        ob = self.objects[k]
        v = np.asarray(vertices, np.float64)
        if v.shape != ob.rest.shape or not np.isfinite(v).all():
            raise InputError(f"object {name!r}: expected {ob.rest.shape} finite vertices, got {v.shape}",
                             param="vertices")
        self.vertices[ob.base:ob.base + len(v)] = v
        from hostlink.relight.scene import Mesh

        self._normals[ob.base:ob.base + len(v)] = vertex_normals(Mesh(v, ob.faces))
        self._dirty.add(k)
        self._geometry += 1

    def move(self, name: str, translation: np.ndarray, rotation: np.ndarray | None = None) -> None:
        """Pose object ``name`` rigidly: rotation (XYZ Euler degrees, or a 3x3 matrix) about its
        loaded centroid, then ``translation``, both relative to the loaded pose."""
        k = self._index(name)
        ob = self.objects[k]
        r = np.asarray(rotation if rotation is not None else np.zeros(3), np.float64)
        R = rotation_matrix(r) if r.shape == (3,) else r
        c = ob.rest.mean(axis=0)
        self.set_vertices(name, (ob.rest - c) @ R.T + c + np.asarray(translation, np.float64))

    def positions(self) -> np.ndarray:
        return self.vertices

    def normals(self) -> np.ndarray:
        return self._normals

    # ---- visibility --------------------------------------------------------------------------
    def _pyramid(self) -> tuple[np.ndarray, np.ndarray]:
        R = self.R
        if self._dirty or self._pyr is None:
            for k in sorted(self._dirty):
                ob = self.objects[k]
                occ = np.zeros(R ** 3, np.uint8)
                voxelize(self.vertices[ob.base:ob.base + len(ob.rest)], ob.faces, self.origin, self.vox, R, occ)
                # closed meshes are solid: a cone through a shell must see the body, not two walls
                from scipy.ndimage import binary_fill_holes

                if self.solid:
                    occ = binary_fill_holes(occ.reshape(R, R, R)).astype(np.uint8).ravel()
                self._occ[k] = occ
            self._dirty.clear()
            tot = np.zeros(R ** 3, np.uint8)
            for o in self._occ:
                if o is not None:
                    np.maximum(tot, o, out=tot)
            self._pyr = anisotropic_pyramid(tot.reshape(R, R, R).astype(np.float32))
        return self._pyr

    def _cone_dirs(self, pos: np.ndarray, nrm: np.ndarray, wo: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(n, 7 + 1 + P, 3) axes and (n, 8 + P) tan(half-angle): 7 diffuse cones, the
        reflection cone (its Phong lobe's half-angle, per material), one per peak lobe."""
        pax, plam = self._peaks[0], self._peaks[1]
        n = len(pos)
        dirs = np.zeros((n, 8 + len(plam), 3))
        cones = np.zeros((n, 7, 3))
        cone_frame(nrm, math.cos(RING_TILT), math.sin(RING_TILT), cones)
        dirs[:, :7] = cones
        cn = np.einsum("ij,ij->i", nrm, wo)
        dirs[:, 7] = 2 * cn[:, None] * nrm - wo
        dirs[:, 8:] = pax[None]
        tan = np.empty((n, 8 + len(plam)))
        tan[:, :7] = math.tan(CONE_HALF)
        e = self.mats[self._matid_rows, 7]
        tan[:, 7] = np.tan(np.arccos(np.clip(1 - math.log(2) / np.maximum(e, 1.0), -1, 1)))
        with np.errstate(divide="ignore", invalid="ignore"):
            ca = np.where(plam >= math.log(2) / 2, 1 + math.log(0.5) / np.maximum(plam, 1e-9), -1.0)
        tan[:, 8:] = np.tan(np.minimum(np.arccos(np.clip(ca, -1, 1)), math.radians(89)))[None]
        return dirs, tan

    _matid_rows: np.ndarray = np.zeros(0, np.int64)

    def _ray_visibility(self, pos: np.ndarray, nrm: np.ndarray, dirs: np.ndarray, tan: np.ndarray) -> np.ndarray:
        from hostlink.relight.precompute import build_embree, occluded, scene_eps

        if self._embree is None or self._embree[1] != self._geometry:
            self._embree = (build_embree([(self.vertices, self.faces)]), self._geometry)
        es = self._embree[0]
        eps = scene_eps(self.scene)
        n, k = tan.shape
        out = np.empty((n, k))
        plam = self._peaks[1]
        for c in range(k):
            peak = c >= 8
            m = RAYS_PER_PEAK if peak else RAYS_PER_CONE
            g = (np.arange(m) + 0.5) / m
            phi = np.arange(m) * math.pi * (3 - math.sqrt(5))
            if peak:
                lam = float(plam[c - 8])
                ct = 1 + np.log(g + (1 - g) * math.exp(-2 * min(lam, 700.0))) / max(lam, 1e-9)  # vMF inverse CDF
            else:
                ca = 1 / np.sqrt(1 + tan[:, c] ** 2)
                ct = 1 - g[None] * (1 - ca[:, None])  # uniform in the cone
            ct = np.clip(ct, -1, 1)
            st = np.sqrt(1 - ct * ct)
            ax = dirs[:, c]
            t1 = np.cross(ax, np.where(np.abs(ax[:, :1]) < 0.9, [[1.0, 0, 0]], [[0, 1.0, 0]]))
            t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
            t2 = np.cross(ax, t1)
            ctb = np.broadcast_to(ct, (n, m))
            stb = np.broadcast_to(st, (n, m))
            d = (ctb[..., None] * ax[:, None] + (stb * np.cos(phi))[..., None] * t1[:, None]
                 + (stb * np.sin(phi))[..., None] * t2[:, None])
            cos = np.einsum("nmk,nk->nm", d, nrm)
            up = cos > 0
            occ = np.ones((n, m), bool)
            vi, ri = np.nonzero(up)
            occ[vi, ri] = occluded(es, pos[vi] + eps * nrm[vi], d[vi, ri])
            w = np.where(up, cos, 0.0)
            if not peak and c < 7 and self._tables is not None and self._tables.L is not None:
                w = w * np.maximum(_table_lookup(self._tables.L, d.reshape(-1, 3)).reshape(n, m), 0.0)
            if peak or c < 7:   # the light the cone's rays carry: cosine x residual radiance
                tot = w.sum(axis=1)
                out[:, c] = np.where(tot > 0, (w * ~occ).sum(axis=1) / np.where(tot > 0, tot, 1),
                                     (~occ).mean(axis=1))
            else:
                out[:, c] = (~occ).mean(axis=1)
        return out

    # ---- shading -----------------------------------------------------------------------------
    def shade(self, pos: np.ndarray, nrm: np.ndarray, matid: np.ndarray, eye: np.ndarray,
              vis: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None = None) -> np.ndarray:
        """Outgoing radiance (n, 3) at points ``pos`` with unit normals ``nrm`` and materials
        ``matid`` towards ``eye``; ``vis`` from :meth:`_visibility_rows` (traced when ``None``)."""
        if self._tables is None:
            raise InputError("no lighting yet: call set_sg or set_equirect first", param="lights")
        wo = np.asarray(eye, np.float64) - pos
        wo /= np.maximum(np.linalg.norm(wo, axis=1, keepdims=True), 1e-12)
        if vis is None:
            vis = self._visibility_rows(matid, pos, nrm, wo)
        cones, vis7, vspec, vpeak = vis
        t = self._tables
        pax, plam, pamp, pF = self._peaks
        out = np.zeros((len(pos), 3))
        kc = MU_COS
        kr = MU_COS * math.exp(self._lam_ring - LAM_COS - LAM_CONE)
        shade_points(np.ascontiguousarray(nrm), wo, np.asarray(matid, np.int64), self.mats, self.gloss_slot,
                     t.E, t.Wc, t.Wr, kc, kr, LAM_COS, LAM_CONE, t.G, pax, plam, pamp, pF,
                     cones, vis7, vspec, vpeak, out)
        return out

    def _visibility_rows(self, matid: np.ndarray, pos: np.ndarray, nrm: np.ndarray,
                         wo: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        self._matid_rows = np.asarray(matid, np.int64)
        dirs, tan = self._cone_dirs(pos, nrm, wo)
        if self.visibility == "voxels":
            pyr, offs = self._pyramid()
            out = np.empty(tan.shape)
            trace_cones(pos, nrm, dirs, tan, pyr, offs, self.R, self.origin, self.vox,
                        self.cone_start, self.cone_lift, self.cone_gain, self.cone_footprint, out)
        else:
            out = self._ray_visibility(pos, nrm, dirs, tan)
        return dirs[:, :7].copy(), out[:, :7].copy(), out[:, 7].copy(), out[:, 8:].copy()

    def vertex_radiance(self, eye: np.ndarray, vidx: np.ndarray | None = None) -> np.ndarray:
        """(n, 3) outgoing radiance of vertices ``vidx`` (all by default) towards ``eye``."""
        vidx = np.arange(len(self.vertices)) if vidx is None else np.asarray(vidx, np.int64)
        return self.shade(self.vertices[vidx], self._normals[vidx], self.matid[vidx], eye)

    def render(self, cam: Camera | None = None, background: np.ndarray | None = None) -> tuple[np.ndarray, dict[str, float]]:
        """Image (H, W, 3) float32, shaded per pixel (position and normal interpolated from the
        triangle's vertices; cones traced from each covered pixel)."""
        from hostlink.relight.raster import lookup_equirect, rasterize, view_rays

        cam = cam or self.scene.camera
        ras = rasterize(cam, self.vertices, self.faces, rays=False)
        cov = ras.tri >= 0
        tri = ras.tri[cov]
        b = ras.bary[cov].astype(np.float64)
        f = self.faces[tri]
        pos = np.einsum("pk,pkj->pj", b, self.vertices[f])
        nrm = np.einsum("pk,pkj->pj", b, self._normals[f])
        nrm /= np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-12)
        rad = self.shade(pos, nrm, self.matid[f[:, 0]], np.asarray(cam.position, np.float64))
        img = np.zeros((*ras.tri.shape, 3), np.float32)
        img[cov] = rad
        if background is not None:
            rays = view_rays(cam)
            img[~cov] = lookup_equirect(background, rays[~cov])
        return img, {"pixels": float(cov.sum())}
