"""The SG relighting's scene: its objects (posed, deformed, versioned), their bounds and the voxel
grid over them; the state the visibility and the shading read."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from lightprobe.core.errors import InputError
from lightprobe.core.sg import SGLighting
from lightprobe.hostlink.relight.scene import Scene, rotation_matrix, vertex_normals
from lightprobe.hostlink.relight.sg.settings import (
    ZONAL_SAMPLES,
)
from lightprobe.hostlink.relight.sg.tables import (
    TableCache,
    Tables,
)

__all__ = ["SGScene", "SceneObject"]


# ---- scene state -------------------------------------------------------------------------------
@dataclass
class SceneObject:
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


class SGScene:
    """The scene of :class:`.relighter.SGRelighter`: materials, objects and their poses, their
    shapes (planes, rectangles) and bounds, and the voxel grid over them."""

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
        self.objects: list[SceneObject] = []
        base = 0
        for o in scene.objects:
            self.objects.append(SceneObject(o.name, np.array(o.mesh.vertices, np.float64), np.asarray(o.mesh.faces, np.int64), base))
            base += len(o.mesh.vertices)
        self.faces = np.concatenate([ob.faces + ob.base for ob in self.objects])
        self.matid = np.concatenate([np.full(len(ob.rest), names.index(o.material), np.int64)
                                     for ob, o in zip(self.objects, scene.objects, strict=True)])
        self.vertices = np.concatenate([ob.rest for ob in self.objects])
        self._normals = np.concatenate([vertex_normals(o.mesh) for o in scene.objects])
        self._cache = TableCache()
        self._tables: Tables | None = None
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
        from lightprobe.hostlink.relight.scene import Mesh

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

    # ---- bounds, shapes, the grid -------------------------------------------------------------
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

    def _shape(self, k: int) -> tuple[tuple[np.ndarray, float] | None, np.ndarray | None]:
        """Object ``k``'s plane ``(n, c)`` (``n . x = c``) if all its vertices lie on one (to 1e-6
        of its size: a mesh file's six decimals still make a plane), and, if that plane's mesh is
        a rectangle, its row for :func:`~lightprobe.hostlink.relight.sg.kernels.rect_clear` (normal, offset,
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
        :func:`~lightprobe.hostlink.relight.sg.kernels.rect_clear`, their object indices as a set and as an
        array. They occlude the cones exactly, not as voxels: a one-voxel floor sampled by a wide
        cone lets 20-30% through (BENCHMARKS.md); other planar meshes stay voxels."""
        if self._rect_cache is None or self._rect_cache[0] != self._geometry:
            found = [(k, row) for k in range(len(self.objects)) if (row := self._shape(k)[1]) is not None]
            self._rect_cache = (self._geometry, np.array([r for _, r in found], np.float64).reshape(-1, 17),
                                frozenset(k for k, _ in found), np.array([k for k, _ in found], np.int64))
        return self._rect_cache[1], self._rect_cache[2], self._rect_cache[3]
