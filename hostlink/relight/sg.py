"""Relighting with spherical Gaussians (Michiels, Put, Bekaert 2015): no precompute, so meshes may
move or deform every frame.

The lighting is the probe's SG lobes (:class:`device.core.sg.SGLighting`: ``GET /api/v1/sg``, or
fitted here from a map with :func:`device.core.sgfit.fit_sg`): a few *peak* lobes (lamps,
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
- **Visibility of the residual: 20 cones** (the paper packs 7 circles; 7 wide cones left 8.6%
  per vertex on dikhololo_night even with exactly traced transmittances, BENCHMARKS.md): the
  cones' axes a cosine-distributed Fibonacci pattern about ``n``, so each stands for an equal
  share of the unshadowed irradiance, half-angle ``acos(1 - 1/20)`` (18 deg: twenty such caps
  hold the hemisphere's solid angle). Each cone is a visibility SG ``S_c`` (sharpness from the
  half-angle by paper eq. 5-6, ``ln 2 / (1 - cos alpha)``); the light arriving through cone
  ``c`` is the lighting filtered by ``S_c`` at its axis (one table), so ``V_res`` is the cones'
  transmittances weighted by the light each carries. Unoccluded points get ``V_res = 1`` exactly.
- **Peaks** (1-3 SGs per lamp): each with its own visibility ``v_p``, the cosine exact
  (``C_p``: the zonal clamped-cosine integral of that lobe), the Phong term by the closed-form
  product of the peak with the BRDF lobe, the cosine taken at the product's axis ``q_p``.
- **Phong as one SG** of sharpness ``e`` about the reflection ``r`` of ``w_o``, ``cos^e x ~
  exp(e (cos x - 1))``; the residual's Phong term takes the cosine at ``r`` and one cone about
  ``r`` of the lobe's half-angle (paper eq. 5-6: ``acos(1 - ln 2 / e)``). Blinn-Phong and Ward
  are not offered (their SG warps vary per point): :class:`SGRelighter` refuses them by name.
- **Visibility**, two ways. ``"voxels"`` (the paper's, for the residual and the reflection
  cone): the scene voxelised (every triangle's voxels, per object, re-voxelised only for objects
  that moved or deformed: dirty flags), per-axis occupancy mip pyramids, cones traced front to
  back (:func:`~hostlink.relight.sgkernels.trace_cones`, a sample every 1.5 sampled cells), each
  sample's opacity raised to ``cone_gain`` = 0.8 (compositing samples as independent occluders
  over-occludes: a cone's samples through one opaque object are correlated). **Rectangles** (a
  floor, a wall, a table top: planar objects whose area is their bounding rectangle's) are no
  voxels: each cone's share of rays that meet one is counted exactly
  (:func:`~hostlink.relight.sgkernels.rect_clear`, 32 rays per cone), since a one-voxel floor
  sampled by a wide cone lets 20-30% through (the cow's belly was lit through the floor). The
  grid holds the other objects only (1.25 x their longest side, so a 3 m floor does not coarsen
  a 1.7 m object's voxels) and is refitted, all re-voxelised, when one leaves it. The peaks'
  shadows are Embree rays even here, not cones: a lamp's cone (0.2-4 deg) marched through the
  grid is a voxel-wide blur that over-occludes near surfaces (9.9% per vertex on studio_small_03
  with peak cones, 4.0% with rays): one ray along the axis for a peak under 2 voxels across the
  grid (the sun), else ``PEAK_RAYS`` = 8 drawn from the lobe; in :meth:`SGRelighter.render` the
  hard ones per pixel, the soft ones per vertex of the visible triangles, interpolated.
  ``"rays"`` (the exact baseline): Embree rays, 16 per cone uniformly within it and 32 per peak
  drawn from the lobe's own distribution, cosine-weighted; the residual's visibility by 112
  cosine-distributed rays weighted by its radiance.
"""

from __future__ import annotations

import functools
import hashlib
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from device.core.errors import InputError
from device.core.sg import SGLighting
from hostlink.relight.scene import Camera, Scene, rotation_matrix, vertex_normals
from hostlink.relight.sgkernels import (
    cone_frame,
    interpolate,
    pyramid_levels,
    rect_clear,
    residual_visibility,
    scatter_pixels,
    sg_matrix,
    shade_points,
    trace_cones,
    voxelize,
)

__all__ = ["SGRelighter", "zonal_cosine"]

DIFFUSE_CONES = 20         # the residual's cones, cosine-distributed over the hemisphere
CONE_HALF = math.acos(1.0 - 1.0 / DIFFUSE_CONES)   # equal caps: together the hemisphere's solid angle
LAM_CONE = math.log(2.0) / (1.0 - math.cos(CONE_HALF))          # paper eq. 5-6 inverted
REFLECTION = DIFFUSE_CONES       # the cone layout: diffuse cones, the reflection cone, the peaks
PEAK0 = DIFFUSE_CONES + 1
RECT_RAYS = 32             # rays per cone against the rectangles (exact occluders, not voxels)
RADIANCE_GRID = 17         # cube-face side of the residual radiance table (ray weights)
DIFFUSE_GRID = 13          # cube-face side of the diffuse tables (smooth kernels: ~7 deg texels)
ZONAL_SAMPLES = 1025
RAYS_PER_CONE = 16         # rays uniform within the reflection cone, with rays
RESIDUAL_RAYS = 112        # cosine-distributed rays for the residual's visibility, with rays
RAYS_PER_PEAK = 32
THIN_PEAK_VOXELS = 2.0     # peaks narrower than this across the grid: one shadow ray each
PEAK_RAYS = 8              # rays per broader peak, with voxels (drawn from the lobe)


# ---- kernels over the sphere -------------------------------------------------------------------
def _fibonacci(m: int) -> tuple[np.ndarray, np.ndarray]:
    """Stratified fractions ``(k + 1/2) / m`` and golden-angle azimuths of an ``m``-point
    Fibonacci pattern."""
    return (np.arange(m) + 0.5) / m, np.arange(m) * math.pi * (3 - math.sqrt(5))


def _diffuse_pattern(K: int) -> np.ndarray:
    """(K, 3) cone axes in a normal's frame (tangent, bitangent, normal): a cosine-distributed
    Fibonacci pattern, so each cone stands for an equal share of the unshadowed irradiance."""
    g, phi = _fibonacci(K)
    st = np.sqrt(g)
    return np.stack([st * np.cos(phi), st * np.sin(phi), np.sqrt(1 - g)], axis=1)


_PATTERN = _diffuse_pattern(DIFFUSE_CONES)
_RECT_G, _rect_phi = _fibonacci(RECT_RAYS)
_RECT_COS, _RECT_SIN = np.cos(_rect_phi), np.sin(_rect_phi)


def _grid_dirs(N: int) -> np.ndarray:
    """(6 N N, 3) texel directions of a cube map (layout of :mod:`hostlink.relight.sgkernels`):
    face ``f`` on axis ``f // 2`` (sign + for even f), texel ``[i, j]`` at ``u_j, v_i`` on the next
    two axes; N odd puts a texel on each axis (normals cluster there: up, the walls)."""
    u = -1 + (2 * np.arange(N) + 1) / N
    V, U = np.meshgrid(u, u, indexing="ij")
    out = np.empty((6, N, N, 3))
    for f in range(6):
        a = f // 2
        out[f, ..., a] = 1.0 if f % 2 == 0 else -1.0
        out[f, ..., (a + 1) % 3] = U
        out[f, ..., (a + 2) % 3] = V
    out /= np.linalg.norm(out, axis=-1, keepdims=True)
    return out.reshape(-1, 3)


@functools.cache
def _gauss_legendre(n: int) -> tuple[np.ndarray, np.ndarray]:
    x, w = np.polynomial.legendre.leggauss(n)
    x.flags.writeable = w.flags.writeable = False
    return x, w


def zonal_cosine(lam: float, samples: int = ZONAL_SAMPLES) -> np.ndarray:
    """``C(t) = integral exp(lam (p . w - 1)) max(a . w, 0) dw`` on ``t = a . p`` in
    ``linspace(-1, 1, samples)``. In coordinates about ``p`` the azimuthal integral of the clamped
    cosine is closed form (``2 (A sin f + B f)``, ``f = acos(-B / A)``); the polar one is
    Gauss-Legendre in ``u = 1 - cos theta`` over where the lobe is above 1e-22 of its peak."""
    t = np.linspace(-1.0, 1.0, samples)
    umax = min(2.0, 50.0 / max(lam, 1e-9))
    x, w = _gauss_legendre(256)
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


def _table_lookup(tab: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Bilinear lookup of a (6, N, N) cube-map table at unit directions ``d`` (n, 3)."""
    N = tab.shape[1]
    a = np.argmax(np.abs(d), axis=1)
    m = np.abs(d[np.arange(len(d)), a])
    f = 2 * a + (d[np.arange(len(d)), a] < 0)
    u = d[np.arange(len(d)), (a + 1) % 3] / m
    v = d[np.arange(len(d)), (a + 2) % 3] / m
    fj = np.clip((u + 1) * 0.5 * N - 0.5, 0, N - 1)
    fi = np.clip((v + 1) * 0.5 * N - 0.5, 0, N - 1)
    j0 = np.minimum(fj.astype(np.int64), N - 2)
    i0 = np.minimum(fi.astype(np.int64), N - 2)
    wj, wi = fj - j0, fi - i0
    return ((1 - wi) * ((1 - wj) * tab[f, i0, j0] + wj * tab[f, i0, j0 + 1])
            + wi * ((1 - wj) * tab[f, i0 + 1, j0] + wj * tab[f, i0 + 1, j0 + 1]))


def anisotropic_pyramid(occ: np.ndarray, out: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Three occupancy mip pyramids of an (R, R, R) [z, y, x] grid, one per axis: level l + 1 of
    the axis-``k`` pyramid combines each pair of children along axis k as one occluder after the
    other (``1 - (1 - a)(1 - b)``) and averages across the other two axes, so a cell holds about
    the probability that a ray crossing it along k is blocked (a floor stays opaque to rays through
    it at every level, and thin to rays along it). Returned flat, (3, total) float32, with the
    level offsets (:func:`~hostlink.relight.sgkernels.pyramid_levels` fills them); into ``out``
    when it has the shape (a deforming scene's frames reuse one buffer: 24 MB at 128^3, whose
    fresh pages cost more than the levels)."""
    R = occ.shape[0]
    sizes = [(R >> lv) ** 3 for lv in range(R.bit_length())]
    offs = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)
    shape = (3, int(offs[-1]))
    flat = out if out is not None and out.shape == shape and out.dtype == np.float32 else np.empty(shape, np.float32)
    flat[:, :sizes[0]] = np.asarray(occ, np.float32).reshape(1, -1)
    pyramid_levels(flat, offs, R)
    return flat, offs


@dataclass
class _Tables:
    E: np.ndarray           # (6, N, N, 3) cube maps
    W: np.ndarray           # the residual through one diffuse cone's visibility SG
    G: np.ndarray           # (slots, 6, N, N, 3)
    L: np.ndarray | None = None   # (6, N, N) the residual's luminance (ray visibility weights)


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
            m = np.empty((len(d), len(lam)), np.float32)
            uniq, slot = np.unique(lam, return_inverse=True)
            zon = np.stack([self.zonal(float(u)) for u in uniq]) if kind == "cos" else np.zeros((1, ZONAL_SAMPLES))
            sg_matrix({"sg": 0, "cos": 1, "radiance": 2}[kind], float(lam_k), d, np.ascontiguousarray(axes, np.float64),
                      np.ascontiguousarray(lam, np.float64), zon,
                      slot.astype(np.int64) if kind == "cos" else np.zeros(len(lam), np.int64), m)
            self._mats[mk] = m
        return m


# ---- scene state -------------------------------------------------------------------------------
@dataclass
class _Object:
    name: str
    rest: np.ndarray        # (V, 3) vertices as loaded
    faces: np.ndarray       # (F, 3) local indices
    base: int               # first global vertex index
    shape: np.ndarray | None = None                 # the current shape (set_vertices), unposed
    rotation: np.ndarray = field(default_factory=lambda: np.eye(3))   # the pose (move)
    translation: np.ndarray = field(default_factory=lambda: np.zeros(3))
    version: int = 0        # bumped whenever its vertices change (_place)
    # its plane (n, c) and rectangle row (rect_clear's 17 numbers), of ``version`` (_shape)
    shape_info: tuple[int, tuple[np.ndarray, float] | None, np.ndarray | None] | None = None
    # its bounding box (lo, hi) and sphere (centre, radius), of ``version`` (_object_bounds)
    bound_info: tuple[int, np.ndarray, np.ndarray, np.ndarray, float] | None = None


class SGRelighter:
    """SG relighting of a :class:`~hostlink.relight.scene.Scene`: no precompute.

    ``visibility``: ``"voxels"`` (voxel cone tracing, ``voxels`` cells along the scene's longest
    side) or ``"rays"`` (Embree). Lights: :meth:`set_sg` / :meth:`set_equirect`. Geometry:
    :meth:`set_vertices` (deform an object: new vertex positions, same faces), :meth:`move`
    (rigid, relative to the loaded pose). Shading: :meth:`vertex_radiance`, :meth:`render`
    (per pixel)."""

    def __init__(self, scene: Scene, *, visibility: str = "voxels", voxels: int = 128,
                 cone_gain: float = 0.8, cone_start: float = 2.0, cone_lift: float = 1.5,
                 cone_footprint: float = 0.2) -> None:
        if visibility not in ("voxels", "rays"):
            raise InputError(f"visibility must be 'voxels' or 'rays', got {visibility!r}", param="visibility")
        if voxels < 8 or voxels > 1024 or voxels & (voxels - 1):
            raise InputError(f"voxels must be a power of two in [8, 1024], got {voxels!r}", param="voxels")
        self.scene, self.visibility, self.R = scene, visibility, int(voxels)
        self.cone_gain, self.cone_start, self.cone_lift = cone_gain, cone_start, cone_lift
        self.cone_footprint = cone_footprint
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
        self._pyr: tuple[np.ndarray, np.ndarray] | None = None
        self._embree: Any = None
        self._rect_cache: tuple[int, np.ndarray, frozenset[int], np.ndarray] | None = None
        self._bound_cache: tuple[int, np.ndarray, np.ndarray] | None = None
        self.owner = np.concatenate([np.full(len(ob.rest), k, np.int64) for k, ob in enumerate(self.objects)])
        self._geometry = 0          # bumped by every deformation or move
        self.vox, self.origin = 0.0, np.zeros(3)    # no grid yet (_fit_grid)
        self._fit_grid()
        self._frame: dict[str, Any] | None = None   # render()'s per-pixel cache
        self._lighting = 0          # bumped by every set_sg

    # ---- lighting ----------------------------------------------------------------------------
    def set_equirect(self, img: np.ndarray) -> None:
        """Fit SG lobes to an (H, 2H, 3) map (as the probe does) and use them."""
        from device.core.sgfit import WORK_HEIGHT, fit_sg

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
        Ng = [self._gloss_grid(e) for e in self._gloss]
        G = max(Ng)
        D = DIFFUSE_GRID
        a32 = amp.astype(np.float32)
        tabs = _Tables(
            (c.matrix(ax, lam, "cos", 0.0, D) @ a32).reshape(6, D, D, 3),
            (c.matrix(ax, lam, "sg", LAM_CONE, D) @ a32).reshape(6, D, D, 3),
            np.zeros((len(self._gloss), 6, G, G, 3), np.float32))
        for s, (e, n) in enumerate(zip(self._gloss, Ng, strict=True)):
            t = (c.matrix(ax, lam, "sg", e, n) @ a32).reshape(6, n, n, 3)
            if n != G:
                import cv2

                t = np.stack([cv2.resize(t[f], (G, G), interpolation=cv2.INTER_LINEAR) for f in range(6)])
            tabs.G[s] = t
        if self.visibility == "rays":  # the residual's radiance, to weight each cone's rays by
            lum = amp @ np.array([0.2126, 0.7152, 0.0722])
            R = RADIANCE_GRID
            tabs.L = (c.matrix(ax, lam, "radiance", 0.0, R) @ lum.astype(np.float32)).reshape(6, R, R)
        self._tables = tabs
        pl = sg.sharpness[peak]
        pF = np.stack([c.zonal(float(x)) for x in pl]) if len(pl) else np.zeros((0, ZONAL_SAMPLES))
        self._peaks = (sg.axes[peak].copy(), pl.copy(), sg.amplitude[peak].copy(), pF)
        self.sg = sg
        self._lighting += 1

    @staticmethod
    def _gloss_grid(e: float) -> int:
        return 17 if e <= 32 else 33 if e <= 128 else 65   # cube-face texels: ~5.3, 2.7, 1.4 deg

    # ---- geometry ----------------------------------------------------------------------------
    def _index(self, name: str) -> int:
        for k, ob in enumerate(self.objects):
            if ob.name == name:
                return k
        raise InputError(f"no object named {name!r} (objects: {', '.join(o.name for o in self.objects)})", param="object")

    def set_vertices(self, name: str, vertices: np.ndarray) -> None:
        """Deform object ``name``: its shape now (same vertex count and faces), posed by the
        object's current :meth:`move`."""
        k = self._index(name)
        ob = self.objects[k]
        v = np.asarray(vertices, np.float64)
        if v.shape != ob.rest.shape or not np.isfinite(v).all():
            raise InputError(f"object {name!r}: expected {ob.rest.shape} finite vertices, got {v.shape}",
                             param="vertices")
        ob.shape = v.copy()
        self._place(k)

    def _place(self, k: int) -> None:
        from hostlink.relight.scene import Mesh

        ob = self.objects[k]
        shape = ob.rest if ob.shape is None else ob.shape
        c = ob.rest.mean(axis=0)
        v = (shape - c) @ ob.rotation.T + c + ob.translation
        self.vertices[ob.base:ob.base + len(v)] = v
        self._normals[ob.base:ob.base + len(v)] = vertex_normals(Mesh(v, ob.faces))
        self._dirty.add(k)
        ob.version += 1
        self._geometry += 1

    def set_frame(self, k: int) -> None:
        """Every deforming object of the scene file (``"frames"``) takes its shape ``k``."""
        deforming = [o for o in self.scene.objects if o.frames]
        if not deforming:
            raise InputError("no object of the scene lists 'frames'", param="frame")
        for o in deforming:
            if not 0 <= k < len(o.frames):
                raise InputError(f"frame {k} out of range: object {o.name!r} has {len(o.frames)} frames", param="frame")
            self.set_vertices(o.name, o.frames[k])

    def move(self, name: str, translation: np.ndarray, rotation: np.ndarray | None = None) -> None:
        """Pose object ``name`` rigidly: rotation (XYZ Euler degrees, or a 3x3 matrix) about its
        loaded centroid, then ``translation``, both relative to the loaded pose; its shape
        (:meth:`set_vertices`, :meth:`set_frame`) is kept."""
        k = self._index(name)
        ob = self.objects[k]
        r = np.asarray(rotation if rotation is not None else np.zeros(3), np.float64)
        R = rotation_matrix(r) if r.shape == (3,) else r
        t = np.asarray(translation, np.float64)
        if R.shape != (3, 3) or t.shape != (3,) or not (np.isfinite(R).all() and np.isfinite(t).all()):
            raise InputError(f"object {name!r}: a move needs a finite translation (3,) and rotation (3,) or (3, 3)",
                             param="move")
        ob.rotation, ob.translation = R, t
        self._place(k)

    def positions(self) -> np.ndarray:
        return self.vertices

    def normals(self) -> np.ndarray:
        return self._normals

    # ---- visibility --------------------------------------------------------------------------
    def _object_bounds(self, k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
        """Object ``k``'s bounding box (lo, hi) and sphere (centre, radius), computed again only
        when its vertices changed."""
        ob = self.objects[k]
        if ob.bound_info is None or ob.bound_info[0] != ob.version:
            v = self.vertices[ob.base:ob.base + len(ob.rest)]
            lo, hi = v.min(axis=0), v.max(axis=0)
            ck = (lo + hi) / 2
            ob.bound_info = (ob.version, lo, hi, ck, float(np.linalg.norm(v - ck, axis=1).max()))
        return ob.bound_info[1], ob.bound_info[2], ob.bound_info[3], ob.bound_info[4]

    def _voxel_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Bounds of the objects the voxels hold (all but the rectangles; all if none)."""
        rect = self._rects()[1]
        keep = [k for k in range(len(self.objects)) if k not in rect] or list(range(len(self.objects)))
        boxes = [self._object_bounds(k) for k in keep]
        return np.min([b[0] for b in boxes], axis=0), np.max([b[1] for b in boxes], axis=0)

    def _fit_grid(self) -> None:
        """Fit the voxel grid to the voxelised objects (1.25 x their longest side, so a floor's
        extent does not coarsen the voxels of what stands on it); refitted, and everything
        re-voxelised, when one leaves it."""
        lo, hi = self._voxel_bounds()
        if self.vox > 0 and np.all(lo >= self.origin) and np.all(hi <= self.origin + self.vox * self.R):
            return
        c, side = (lo + hi) / 2, float((hi - lo).max()) * 1.25 + 1e-9
        self.vox = side / self.R
        self.origin = c - side / 2
        self._dirty = set(range(len(self.objects)))

    def _pyramid(self) -> tuple[np.ndarray, np.ndarray]:
        R = self.R
        if self._dirty:
            self._fit_grid()
        if self._dirty or self._pyr is None:
            rect = self._rects()[1]
            for k in sorted(self._dirty):
                ob = self.objects[k]
                if k in rect:   # an exact occluder of the cones (rect_clear), not voxels
                    self._occ[k] = None
                    continue
                occ = np.zeros(R ** 3, np.uint8)
                voxelize(self.vertices[ob.base:ob.base + len(ob.rest)], ob.faces, self.origin, self.vox, R, occ)
                # surfaces only (filling closed meshes' interiors was tried: worse, self-occlusion)
                self._occ[k] = occ
            self._dirty.clear()
            tot = np.zeros(R ** 3, np.uint8)
            for o in self._occ:
                if o is not None:
                    np.bitwise_or(tot, o, out=tot)
            self._pyr = anisotropic_pyramid(tot.reshape(R, R, R), None if self._pyr is None else self._pyr[0])
        return self._pyr

    def _cone_dirs(self, pos: np.ndarray, nrm: np.ndarray, wo: np.ndarray,
                   matid: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(n, PEAK0 + P, 3) axes and (n, PEAK0 + P) tan(half-angle): the DIFFUSE_CONES diffuse
        cones, the reflection cone (its Phong lobe's half-angle, per material), one per peak lobe."""
        pax, plam = self._peaks[0], self._peaks[1]
        n = len(pos)
        dirs = np.zeros((n, PEAK0 + len(plam), 3))
        cones = np.zeros((n, DIFFUSE_CONES, 3))
        cone_frame(nrm, _PATTERN, cones)
        dirs[:, :REFLECTION] = cones
        cn = np.einsum("ij,ij->i", nrm, wo)
        dirs[:, REFLECTION] = 2 * cn[:, None] * nrm - wo
        dirs[:, PEAK0:] = pax[None]
        tan = np.empty((n, PEAK0 + len(plam)))
        tan[:, :REFLECTION] = math.tan(CONE_HALF)
        e = self.mats[np.asarray(matid, np.int64), 7]
        tan[:, REFLECTION] = np.tan(np.arccos(np.clip(1 - math.log(2) / np.maximum(e, 1.0), -1, 1)))
        tan[:, PEAK0:] = self._peak_half_tan()[None]
        return dirs, tan

    def _thin(self) -> np.ndarray:
        """(P,) bool: peaks narrower than THIN_PEAK_VOXELS across the whole grid (the sun: 0.4 deg),
        whose shadow is one ray along the axis; the broader ones get PEAK_RAYS lobe-distributed rays."""
        return np.asarray(2 * self.R * self._peak_half_tan() < THIN_PEAK_VOXELS, bool)

    def _bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Per object its bounding sphere: centres (K, 3), radii (K,)."""
        if self._bound_cache is None or self._bound_cache[0] != self._geometry:
            c = np.zeros((len(self.objects), 3))
            r = np.zeros(len(self.objects))
            for k in range(len(self.objects)):
                _, _, c[k], r[k] = self._object_bounds(k)
            self._bound_cache = (self._geometry, c, r)
        return self._bound_cache[1], self._bound_cache[2]

    def _needs_cone(self, pos: np.ndarray, dirs: np.ndarray, tan: np.ndarray,
                    owner: np.ndarray | None) -> np.ndarray:
        """(n, k) uint8: 1 where cone ``dirs[:, j]`` (half-angle ``atan(tan)``) from a point meets
        some object's bounding sphere, other than the planar object the point lies on (a plane
        cannot hide anything above it from its own points). The others are clear: not traced, and
        free of the voxels' self-occlusion."""
        need = np.zeros(tan.shape, bool)
        centres, radii = self._bounds()
        planes = self._planes()
        rect = self._rects()[1]
        half = np.arctan(tan)
        for j in range(len(self.objects)):
            if j in rect:   # not in the voxels (rect_clear)
                continue
            v = centres[j] - pos
            dist = np.linalg.norm(v, axis=1)
            inside = dist <= radii[j] * (1 + 1e-9)
            u = v / np.maximum(dist, 1e-300)[:, None]
            ang = np.arccos(np.clip(np.einsum("nkc,nc->nk", dirs, u), -1, 1))
            reach = np.arcsin(np.clip(radii[j] / np.maximum(dist, 1e-300), 0, 1))
            hit = inside[:, None] | (ang <= half + reach[:, None] + 1e-6)
            if owner is not None and planes[j] is not None:
                hit[owner == j] = False
            need |= hit
        return need.astype(np.uint8)

    def _trace(self, pos: np.ndarray, nrm: np.ndarray, dirs: np.ndarray, tan: np.ndarray, first: int = 0,
               owner: np.ndarray | None = None, matid: np.ndarray | None = None) -> np.ndarray:
        """Transmittance of the cones ``dirs[:, j]`` (cone ``first + j`` of the layout: diffuse
        below REFLECTION, then the reflection cone, peaks from PEAK0) by the instance's visibility
        method; ``owner``: the object each point lies on, if known (its own plane is then no
        occluder); ``matid``: the points' materials, if known (a Lambert point's reflection cone
        is not traced: 1)."""
        if self.visibility == "voxels":
            pyr, offs = self._pyramid()
            out = np.empty(tan.shape)
            # the peaks' shadows are Embree rays, not cones: a lamp's cone (0.2-4 deg) marched
            # through the grid is a voxel-wide blur that over-occludes near surfaces (studio_small_03,
            # Lambert: 9.9% per vertex with peak cones, 4.0% with 8 rays per broad peak)
            peak = first + np.arange(tan.shape[1]) >= PEAK0
            cones = np.flatnonzero(~peak)
            if len(cones):
                sub = np.empty((len(pos), len(cones)))
                cd, ct = np.ascontiguousarray(dirs[:, cones]), np.ascontiguousarray(tan[:, cones])
                used = np.ones(ct.shape, np.uint8)
                if matid is not None and first + cones[-1] >= REFLECTION:   # the reflection cone: Phong only
                    used[self.mats[np.asarray(matid, np.int64), 0] != 1, REFLECTION - first] = 0
                need = self._needs_cone(pos, cd, ct, owner) & used
                trace_cones(np.ascontiguousarray(pos), np.ascontiguousarray(nrm), cd, ct, pyr, offs, self.R,
                            self.origin, self.vox, self.cone_start, self.cone_lift, self.cone_gain,
                            self.cone_footprint, need, sub)
                rects, _, robj = self._rects()
                if len(rects):
                    side = pos @ rects[:, :3].T - rects[:, 3]           # (n, Q): each point's side of each plane
                    rect_clear(np.ascontiguousarray(pos), cd, ct, np.ascontiguousarray(side), rects, robj,
                               np.full(len(pos), -1, np.int64) if owner is None else np.asarray(owner, np.int64),
                               _RECT_G, _RECT_COS, _RECT_SIN, used, sub)
                out[:, cones] = sub
            thin = self._thin()
            for j in np.flatnonzero(peak):
                p = first + j - PEAK0
                if thin[p]:
                    out[:, j] = self._shadow_rays(pos, nrm, dirs[:, j])
                else:
                    out[:, j] = self._lobe_rays(pos, nrm, self._peaks[0][p], float(self._peaks[1][p]), PEAK_RAYS)
            return out
        return self._ray_visibility(pos, nrm, dirs, tan, first)

    def _lobe_rays(self, pos: np.ndarray, nrm: np.ndarray, axis: np.ndarray, lam: float, m: int) -> np.ndarray:
        """Visibility of one peak lobe from each point: ``m`` rays drawn from the lobe's own
        distribution (a stratified vMF inverse CDF, Fibonacci azimuths), each weighted by its cosine
        at the point; the fraction of that light that escapes."""
        from hostlink.relight.precompute import occluded, scene_eps

        eps = scene_eps(self.scene)
        n = len(pos)
        g, phi = _fibonacci(m)
        ct = np.clip(1 + np.log(g + (1 - g) * math.exp(-2 * min(lam, 700.0))) / max(lam, 1e-9), -1, 1)
        st = np.sqrt(1 - ct * ct)
        ax = np.asarray(axis, np.float64)
        t1 = np.cross(ax, [1.0, 0, 0] if abs(ax[0]) < 0.9 else [0, 1.0, 0])
        t1 /= np.linalg.norm(t1)
        t2 = np.cross(ax, t1)
        d = ct[:, None] * ax + (st * np.cos(phi))[:, None] * t1 + (st * np.sin(phi))[:, None] * t2   # (m, 3)
        cos = nrm @ d.T
        up = cos > 0
        occ = np.ones((n, m), bool)
        vi, ri = np.nonzero(up)
        if len(vi):
            o = pos[vi] + eps * nrm[vi]
            es = self._occluders(o, d)
            occ[vi, ri] = False if es is None else occluded(es, o, d[ri])
        w = np.where(up, cos, 0.0)
        tot = w.sum(axis=1)
        return np.where(tot > 0, (w * ~occ).sum(axis=1) / np.where(tot > 0, tot, 1), 0.0)

    def _embree_scene(self, skip: frozenset[int] = frozenset()) -> Any:
        """The Embree scene of every object but ``skip`` (None when nothing is left), rebuilt
        after a deformation or move."""
        from hostlink.relight.precompute import build_embree

        if self._embree is None or self._embree[0] != self._geometry:
            self._embree = (self._geometry, {})
        scenes = self._embree[1]
        if skip not in scenes:
            meshes = [(self.vertices[ob.base:ob.base + len(ob.rest)], ob.faces)
                      for k, ob in enumerate(self.objects) if k not in skip]
            scenes[skip] = build_embree(meshes) if meshes else None
        return scenes[skip]

    def _shape(self, k: int) -> tuple[tuple[np.ndarray, float] | None, np.ndarray | None]:
        """Object ``k``'s plane ``(n, c)`` (``n . x = c``) if all its vertices lie on one (to 1e-6
        of its size: a mesh file's six decimals still make a plane), and, if that plane's mesh is
        a rectangle, its row for :func:`~hostlink.relight.sgkernels.rect_clear` (normal, offset,
        corner origin, two in-plane unit axes, extents): a planar mesh is a rectangle when its area
        is that of its bounding rectangle in its plane (along one of its triangles' edges) to
        1e-5. Computed again only when the object changed (a deforming cow does not recount the
        floor's 34k triangles every frame)."""
        ob = self.objects[k]
        if ob.shape_info is not None and ob.shape_info[0] == ob.version:
            return ob.shape_info[1], ob.shape_info[2]
        v = self.vertices[ob.base:ob.base + len(ob.rest)]
        tri = v[ob.faces]
        cr = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        n = cr.sum(axis=0)
        ln = float(np.linalg.norm(n))
        ext = float(np.ptp(v, axis=0).max()) if len(v) else 0.0
        plane, row = None, None
        if ln > 0 and ext > 0:
            n = n / ln
            c = float(v[0] @ n)
            if float(np.abs(v @ n - c).max()) <= 1e-6 * ext:
                plane = (n, c)
                row = self._rect_row(v, ob.faces, n, c, 0.5 * float(np.linalg.norm(cr, axis=1).sum()))
        ob.shape_info = (ob.version, plane, row)
        return plane, row

    @staticmethod
    def _rect_row(v: np.ndarray, faces: np.ndarray, n: np.ndarray, c: float, area: float) -> np.ndarray | None:
        """The rectangle row of a planar mesh (see :meth:`_shape`), or None if it is no rectangle."""
        o = v.mean(axis=0)
        a1 = np.cross(n, [1.0, 0, 0] if abs(n[0]) < 0.9 else [0, 1.0, 0])
        a1 /= np.linalg.norm(a1)
        xy = (v - o) @ np.stack([a1, np.cross(n, a1)], axis=1)
        # a rectangle's sides lie along some of its triangles' edges: try each edge direction
        ed = xy[faces[:, [1, 2, 0]]] - xy[faces]
        ang = np.unique(np.round(np.arctan2(ed[..., 1], ed[..., 0]).ravel() % (math.pi / 2), 9))
        rot = np.stack([np.cos(ang), np.sin(ang)], axis=1)          # candidate e1 per angle
        pu = xy @ rot.T
        pv = xy @ np.stack([-rot[:, 1], rot[:, 0]], axis=1).T
        boxes = np.ptp(pu, axis=0) * np.ptp(pv, axis=0)
        best = int(np.argmin(boxes))
        box = float(boxes[best])
        if box <= 0 or abs(area - box) > 1e-5 * box:
            return None
        c1, s1 = rot[best]
        e1 = c1 * a1 + s1 * np.cross(n, a1)
        e2 = np.cross(n, e1)
        uv = (v - o) @ np.stack([e1, e2], axis=1)
        lo, hi = uv.min(axis=0), uv.max(axis=0)
        return np.concatenate([n, [c], o, e1, e2, [lo[0], hi[0], lo[1], hi[1]]])

    def _planes(self) -> list[tuple[np.ndarray, float] | None]:
        """Per object, its plane ``(n, c)`` or None (:meth:`_shape`)."""
        return [self._shape(k)[0] for k in range(len(self.objects))]

    def _rects(self) -> tuple[np.ndarray, frozenset[int], np.ndarray]:
        """The planar objects that are rectangles (a floor, a wall, a table top): (Q, 17) rows for
        :func:`~hostlink.relight.sgkernels.rect_clear`, their object indices as a set and as an
        array. They occlude the cones exactly, not as voxels: a one-voxel floor sampled by a wide
        cone lets 20-30% through (BENCHMARKS.md); other planar meshes stay voxels."""
        if self._rect_cache is None or self._rect_cache[0] != self._geometry:
            found = [(k, row) for k in range(len(self.objects)) if (row := self._shape(k)[1]) is not None]
            self._rect_cache = (self._geometry, np.array([r for _, r in found], np.float64).reshape(-1, 17),
                                frozenset(k for k, _ in found), np.array([k for k, _ in found], np.int64))
        return self._rect_cache[1], self._rect_cache[2], self._rect_cache[3]

    def _occluders(self, origins: np.ndarray, dirs: np.ndarray) -> Any:
        """The Embree scene for rays from ``origins`` along any of ``dirs``, without the planar
        objects none of them can reach (every origin on one side, every direction pointing away:
        a floor under a sun's shadow rays). None: nothing can occlude them."""
        skip = []
        for k, pl in enumerate(self._planes()):
            if pl is None or not len(origins):
                continue
            n, c = pl
            side = origins @ n - c
            away = dirs @ n
            if (side.min() > 0 and away.min() > 0) or (side.max() < 0 and away.max() < 0):
                skip.append(k)
        return self._embree_scene(frozenset(skip))

    def _shadow_rays(self, pos: np.ndarray, nrm: np.ndarray, d: np.ndarray) -> np.ndarray:
        """1 where the ray from each point along ``d`` escapes (and ``d`` is above its horizon), else 0."""
        from hostlink.relight.precompute import occluded, scene_eps

        d = np.ascontiguousarray(np.broadcast_to(d, pos.shape))
        up = np.einsum("ij,ij->i", d, nrm) > 0
        out = np.zeros(len(pos))
        rows = np.flatnonzero(up)
        eps = scene_eps(self.scene)
        o = pos[rows] + eps * nrm[rows]
        es = self._occluders(o, d[rows])
        out[rows] = 1.0 if es is None else ~occluded(es, o, d[rows])
        return out

    def _ray_visibility(self, pos: np.ndarray, nrm: np.ndarray, dirs: np.ndarray, tan: np.ndarray,
                        first: int = 0) -> np.ndarray:
        from hostlink.relight.precompute import occluded, scene_eps

        es = self._embree_scene()
        eps = scene_eps(self.scene)
        n, k = tan.shape
        out = np.empty((n, k))
        pax, plam = self._peaks[0], self._peaks[1]
        diffuse = [j for j in range(k) if first + j < REFLECTION]
        if diffuse:   # the residual's visibility, measured: one light-weighted fraction for all cones
            out[:, diffuse] = self._residual_ray_visibility(es, eps, pos, nrm)[:, None]
        for j in range(k):
            c = first + j
            if c >= PEAK0:
                out[:, j] = self._lobe_rays(pos, nrm, pax[c - PEAK0], float(plam[c - PEAK0]), RAYS_PER_PEAK)
            elif c == REFLECTION:   # the reflection cone: rays uniform within it
                m = RAYS_PER_CONE
                g, phi = _fibonacci(m)
                ca = 1 / np.sqrt(1 + tan[:, j] ** 2)
                ct = np.clip(1 - g[None] * (1 - ca[:, None]), -1, 1)
                st = np.sqrt(1 - ct * ct)
                ax = dirs[:, j]
                t1 = np.cross(ax, np.where(np.abs(ax[:, :1]) < 0.9, [[1.0, 0, 0]], [[0, 1.0, 0]]))
                t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
                t2 = np.cross(ax, t1)
                d = (ct[..., None] * ax[:, None] + (st * np.cos(phi))[..., None] * t1[:, None]
                     + (st * np.sin(phi))[..., None] * t2[:, None])
                up = np.einsum("nmk,nk->nm", d, nrm) > 0
                occ = np.ones((n, m), bool)
                vi, ri = np.nonzero(up)
                occ[vi, ri] = occluded(es, pos[vi] + eps * nrm[vi], d[vi, ri])
                out[:, j] = (~occ).mean(axis=1)
        return out

    def _residual_ray_visibility(self, es: Any, eps: float, pos: np.ndarray, nrm: np.ndarray) -> np.ndarray:
        """``V_res`` by rays: RESIDUAL_RAYS cosine-distributed rays over each point's
        hemisphere (a Fibonacci pattern, turned per point), each weighted by the residual's
        radiance along it; the fraction of that light that escapes. The cones' partition is the
        voxel method's approximation; with rays the residual's visibility needs none."""
        from hostlink.relight.precompute import occluded

        n = len(pos)
        m = RESIDUAL_RAYS
        g, phi = _fibonacci(m)
        ct = np.sqrt(1 - g)                       # cosine-weighted: pdf cos / pi
        st = np.sqrt(g)
        t1 = np.cross(nrm, np.where(np.abs(nrm[:, :1]) < 0.9, [[1.0, 0, 0]], [[0, 1.0, 0]]))
        t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
        t2 = np.cross(nrm, t1)
        turn = (np.arange(n) * 0.618034 % 1.0)[:, None] * 2 * math.pi   # decorrelate neighbours
        cp, sp = np.cos(phi[None] + turn), np.sin(phi[None] + turn)
        d = (ct[None, :, None] * nrm[:, None] + (st[None] * cp)[..., None] * t1[:, None]
             + (st[None] * sp)[..., None] * t2[:, None])
        L = self._tables.L if self._tables is not None else None
        w = np.ones((n, m)) if L is None else np.maximum(_table_lookup(L, d.reshape(-1, 3)).reshape(n, m), 0.0)
        free = ~occluded(es, np.repeat(pos + eps * nrm, m, axis=0), d.reshape(-1, 3)).reshape(n, m)
        tot = w.sum(axis=1)
        return np.where(tot > 0, (w * free).sum(axis=1) / np.where(tot > 0, tot, 1), free.mean(axis=1))

    # ---- shading -----------------------------------------------------------------------------
    def shade(self, pos: np.ndarray, nrm: np.ndarray, matid: np.ndarray, eye: np.ndarray,
              vis: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None) -> np.ndarray:
        """Outgoing radiance (n, 3) at points ``pos`` with unit normals ``nrm`` and materials
        ``matid`` towards ``eye``; ``vis`` = (``V_res`` (n, 3), reflection cone (n,), peaks (n, P))
        from :meth:`_visibility_rows` (traced when ``None``)."""
        if self._tables is None:
            raise InputError("no lighting yet: call set_sg or set_equirect first", param="lights")
        wo = np.asarray(eye, np.float64) - pos
        wo /= np.maximum(np.linalg.norm(wo, axis=1, keepdims=True), 1e-12)
        if vis is None:
            vis = self._visibility_rows(matid, pos, nrm, wo)
        vres, vspec, vpeak = vis
        t = self._tables
        pax, plam, pamp, pF = self._peaks
        out = np.zeros((len(pos), 3))
        shade_points(np.ascontiguousarray(nrm), wo, np.asarray(matid, np.int64), self.mats, self.gloss_slot,
                     t.E, t.G, pax, plam, pamp, pF, np.ascontiguousarray(vres), vspec, vpeak, out)
        return out

    def _residual_weights(self, cones: np.ndarray, vis: np.ndarray) -> np.ndarray:
        """``V_res`` (n, 3): the cones' transmittances weighted by the light each carries now."""
        assert self._tables is not None
        out = np.empty((len(cones), 3))
        residual_visibility(np.ascontiguousarray(cones), np.ascontiguousarray(vis), self._tables.W, out)
        return out

    def _visibility_rows(self, matid: np.ndarray, pos: np.ndarray, nrm: np.ndarray, wo: np.ndarray,
                         owner: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(``V_res`` (n, 3), reflection cone (n,), peaks (n, P)) of points (on objects ``owner``)."""
        if self._tables is None:
            raise InputError("no lighting yet: call set_sg or set_equirect first", param="lights")
        dirs, tan = self._cone_dirs(pos, nrm, wo, matid)
        out = self._trace(pos, nrm, dirs, tan, owner=owner, matid=matid)
        return (self._residual_weights(dirs[:, :REFLECTION], out[:, :REFLECTION]), out[:, REFLECTION].copy(),
                out[:, PEAK0:].copy())

    def vertex_radiance(self, eye: np.ndarray, vidx: np.ndarray | None = None) -> np.ndarray:
        """(n, 3) outgoing radiance of vertices ``vidx`` (all by default) towards ``eye``."""
        vidx = np.arange(len(self.vertices)) if vidx is None else np.asarray(vidx, np.int64)
        pos, nrm, matid = self.vertices[vidx], self._normals[vidx], self.matid[vidx]
        wo = np.asarray(eye, np.float64) - pos
        wo /= np.maximum(np.linalg.norm(wo, axis=1, keepdims=True), 1e-12)
        return self.shade(pos, nrm, matid, eye, self._visibility_rows(matid, pos, nrm, wo, self.owner[vidx]))

    def _peak_half_tan(self) -> np.ndarray:
        """tan of each peak cone's half-angle (paper eq. 5-6; 89 deg for lobes too broad for it)."""
        plam = self._peaks[1]
        with np.errstate(divide="ignore", invalid="ignore"):
            ca = np.where(plam >= math.log(2) / 2, 1 + math.log(0.5) / np.maximum(plam, 1e-9), -1.0)
        return np.asarray(np.tan(np.minimum(np.arccos(np.clip(ca, -1, 1)), math.radians(89))))

    def _peak_visibility(self, pos: np.ndarray, nrm: np.ndarray,
                         which: np.ndarray | None = None) -> tuple[np.ndarray, float]:
        """(n, len(which)) visibility of peaks ``which`` (all by default) from each point, and the
        number of peak visibilities traced: a peak wholly below a point's horizon is not traced
        there (it lights nothing: 0)."""
        pax = self._peaks[0]
        ids = np.arange(len(pax)) if which is None else np.asarray(which, np.int64)
        out = np.zeros((len(pos), len(ids)))
        tan = self._peak_half_tan()
        sin_half = tan / np.sqrt(1 + tan * tan)
        count = 0.0
        for j, p in enumerate(ids):
            rows = np.flatnonzero(nrm @ pax[p] > -sin_half[p])
            if len(rows):
                out[rows, j] = self._trace(pos[rows], nrm[rows], np.broadcast_to(pax[p], (len(rows), 1, 3)),
                                           np.full((len(rows), 1), tan[p]), first=PEAK0 + int(p))[:, 0]
            count += len(rows)
        return out, count

    @staticmethod
    def _at_pixels(f: dict[str, Any], at: np.ndarray) -> np.ndarray:
        """Per-vertex values (V, C) interpolated at the frame's covered pixels (P, C)."""
        out = np.empty((len(f["bary"]), at.shape[1]))
        interpolate(f["bary"], f["fv"], np.ascontiguousarray(at, np.float64), out)
        return out

    def render(self, cam: Camera | None = None, background: np.ndarray | None = None) -> tuple[np.ndarray, dict[str, float]]:
        """Image (H, W, 3) float32 linear, shaded per pixel: position, normal and reflection per
        pixel, the peaks' cones traced from every covered pixel (their shadows are the sharp
        ones); the wide cones (7 diffuse, 30 deg, and the reflection cone) from the vertices of
        the visible triangles, interpolated (their visibility is smooth across a triangle).

        Cached between calls: the raster and the wide cones until the geometry or the camera
        changes, the peaks' cones until a peak's axis or sharpness changes; a light change whose
        peaks stay put costs the direction tables and the per-pixel shading only (with voxels; the
        rays weight the residual's visibility by its light, so with rays it re-traces the wide cones)."""
        from hostlink.relight.raster import lookup_equirect, rasterize, view_rays, visible_vertices

        cam = cam or self.scene.camera
        # rays weight the residual's visibility by its light: with rays a light change re-traces too
        key = (self._geometry, tuple(np.asarray(cam.position, float)), tuple(np.asarray(cam.look_at, float)),
               tuple(np.asarray(cam.up, float)), float(cam.fov_deg), int(cam.width), int(cam.height),
               self._lighting if self.visibility == "rays" else 0)
        eye = np.asarray(cam.position, np.float64)
        f = self._frame
        traced = {"wide_cones": 0.0, "peak_cones": 0.0}
        if f is None or f["key"] != key:
            ras = rasterize(cam, self.vertices, self.faces, rays=False)
            cov = ras.tri >= 0
            tri = ras.tri[cov]
            b = ras.bary[cov].astype(np.float64)
            fv = self.faces[tri]
            fv = np.ascontiguousarray(fv, np.int64)
            pos, nrm = np.empty((len(b), 3)), np.empty((len(b), 3))
            interpolate(b, fv, self.vertices, pos)
            interpolate(b, fv, self._normals, nrm)
            nrm /= np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-12)
            matid = self.matid[fv[:, 0]]
            vis_v = visible_vertices(ras.tri, self.faces, len(self.vertices))
            vp, vn = self.vertices[vis_v], self._normals[vis_v]
            wo = eye - vp
            wo /= np.maximum(np.linalg.norm(wo, axis=1, keepdims=True), 1e-12)
            dirs, tan = self._cone_dirs(vp, vn, wo, self.matid[vis_v])
            wide = np.zeros((len(self.vertices), PEAK0))
            wide[vis_v] = self._trace(vp, vn, dirs[:, :PEAK0], tan[:, :PEAK0], owner=self.owner[vis_v],
                                      matid=self.matid[vis_v])
            traced["wide_cones"] = float(PEAK0 * len(vis_v))
            f = self._frame = {"key": key, "cov": cov, "pos": pos, "nrm": nrm, "matid": matid,
                               "vis_v": vis_v, "fv": fv, "bary": b, "cones": dirs[:, :REFLECTION].copy(),
                               "vis_d": wide[vis_v, :REFLECTION].copy(),
                               "pix": np.flatnonzero(cov),
                               "peaks": None, "vpeak": None, "lighting": None, "vres": None}
            f["vspec"] = self._at_pixels(f, wide[:, REFLECTION:PEAK0])[:, 0]
        pax, plam = self._peaks[0], self._peaks[1]
        pkey = (pax.tobytes(), plam.tobytes())
        if f["peaks"] != pkey:
            # hard shadows per pixel; with voxels a broad peak's soft shadow (its rays) is traced
            # from the vertices of the visible triangles and interpolated, like the wide cones
            per_vertex = ~self._thin() if self.visibility == "voxels" else np.zeros(len(pax), bool)
            vpeak = np.zeros((len(f["pos"]), len(pax)))
            thin = np.flatnonzero(~per_vertex)
            vpeak[:, thin], n_pix = self._peak_visibility(f["pos"], f["nrm"], thin)
            broad = np.flatnonzero(per_vertex)
            n_vert = 0.0
            if len(broad):
                vv = f["vis_v"]
                at = np.zeros((len(self.vertices), len(broad)))
                at[vv], n_vert = self._peak_visibility(self.vertices[vv], self._normals[vv], broad)
                vpeak[:, broad] = self._at_pixels(f, at)
            f["vpeak"], f["peaks"] = vpeak, pkey
            traced["peak_cones"] = n_pix + n_vert
        if f["lighting"] != self._lighting:
            # the residual's visibility weighs each cone by the light it carries: per vertex of the
            # visible triangles (their cones), interpolated (the cones' transmittances are anyway)
            at = np.zeros((len(self.vertices), 3))
            vv = f["vis_v"]
            at[vv] = self._residual_weights(f["cones"], f["vis_d"])
            f["vres"], f["lighting"] = self._at_pixels(f, at), self._lighting
        rad = self.shade(f["pos"], f["nrm"], f["matid"], eye, (f["vres"], f["vspec"], f["vpeak"]))
        img = np.zeros((*f["cov"].shape, 3), np.float32)
        scatter_pixels(f["pix"], rad, img.reshape(-1, 3))
        if background is not None:
            rays = view_rays(cam)
            img[~f["cov"]] = lookup_equirect(background, rays[~f["cov"]])
        return img, {"pixels": float(f["cov"].sum()), **traced}
