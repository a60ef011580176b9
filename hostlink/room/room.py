"""Relighting a real, photographed room (Loscos, Frasson, Drettakis, Walter, Granier, Poulin 1999).

Input, a folder a user can make::

    room.obj                 approximate geometry, one ``o`` / ``g`` group per surface or object
    camera.json              {"K": 3x3, "R": 3x3, "t": [3], "width": W, "height": H}: world to
                             camera, OpenCV's convention (x right, y down, z forward; pixel
                             centres at integer coordinates)
    captures/NAME.exr        linear HDR photographs from that camera (e.g. ``lightprobe fuse``)
    captures/NAME.json       {"lights": [{"position": [x, y, z], "radius": r, "rgb": [r, g, b]}]}:
                             small spherical lights, emitted power per colour (W) in world units

What it does (the paper's steps; the choices it leaves open, and ours):

- **Item buffer**: ``room.obj`` split into patches (triangles no longer than ``patch_size``,
  default the room's diagonal / 16) and rasterised from the camera: per pixel the 3D point,
  the patch, its normal (towards the camera) and its group. A pixel whose footprint crosses an
  edge (another group, a fold, a depth step) is the camera's box-filtered mean of several
  surfaces: it gets ``SUBPIXEL`` x ``SUBPIXEL`` camera rays, its reflectance is solved against
  the mean of their shading and it is rendered as that mean. A patch no pixel sees faces the
  side from which more of the seen patches are visible (``room.obj`` windings are arbitrary).
- **Direct light**: each spherical light as ``light_samples`` points on the cap facing the
  receiver, each a point light of 1 / n of the sphere's intensity ``rgb / (4 pi)`` with its own
  Embree shadow ray (the paper's adaptive rays to an area light, fixed count here).
- **Indirect light: a radiosity solve over the patches** with the captures' own measurements:
  a patch seen by the camera has its measured radiance; the others ``rho / pi (E_direct +
  E_indirect)`` with their group's current reflectance; patch-to-patch form factors with one
  visibility ray between centres. Or (``indirect="ambient"``) the paper's first estimate, with
  one change: the paper takes the image's mean colour times a user-given average reflectance;
  here the room around a pixel is taken to be as bright as the capture's mean colour ``C`` (in a
  closed room the light arriving after a bounce is the room's own radiance, which ``C``
  measures), so ``E_indirect = pi C`` times the share of the pixel's hemisphere the geometry
  covers (its form factors' sum: an open side lets light out). No number to guess.
- **Where the model is off** (ours; the paper's filters only lower such pixels' confidence): a
  pixel's captures under lamps at several positions say which surface it shows, since its
  radiance must be one reflectance times the modelled irradiance in every capture. After the
  first pass, a pixel whose own modelled irradiance misfits its captures (over ``SNAP_MIN``,
  relative, squared) while a pixel's within ``SNAP_RADIUS`` fits at least ``1 / SNAP_GAIN``
  times better is shaded with that pixel's geometry, in the recovery and in every edit
  (:meth:`Room._snap`): a silhouette the model puts a pixel off (the block where the photographs
  show the wall) then takes a new lamp's light as the wall does.
- **Objects where the captures put them** (ours, opt-in: :meth:`Room.align`, ``Room.aligned``,
  ``lightprobe room recover --align``): an approximate model's objects (groups smaller than the
  room on every axis that own their vertices: :func:`movable_groups`) are moved sideways as the
  camera sees them, at most ``ALIGN_BOUND`` of the room's size (the modelling error the paper
  allows), by coordinate descent (steps ``ALIGN_STEPS`` of that bound) on the captures' misfit
  (the sum over the model's pixels of each pixel's misfit, capped at ``SNAP_CAP``, on a camera at
  most ``ALIGN_WIDTH`` pixels wide, with the indirect light of the model's own recovery held).
  A step is kept when it lowers the misfit by ``ALIGN_STEP_GAIN`` of the model's, the whole
  alignment only when it ends below ``ALIGN_GAIN`` of it, so a model that is right stays. Only
  sideways: silhouettes pin an object across the view, while depth scales a surface's light
  almost uniformly, which a pixel's reflectance absorbs (not observable from one viewpoint), and
  objects stay on their floor. It matters most for a lamp added close to a surface: 6 cm from a
  face placed 1 cm off, the lamp's light on it is off by a third.
- **Reflectance** per capture ``rho_k = pi B_k / (E_direct + E_indirect)`` (eq. 2), merged with
  confidences ``w_k`` = the direct share of the capture's irradiance (eq. 3: lit pixels count,
  shadowed ones barely). The filters (``filters=True``): the paper's confidence filter
  ``K = min(K, kappa)``, ``kappa`` the 5 x 5 mean of the 5 x 5 minimum (confidence falls
  towards a shadow's or a surface's edge, where an approximate model is wrong first); the outlier
  test around the per-pixel median of the captures (``|rho_k - median| > 0.3 median`` rejected;
  the paper's 0.75 / 0.3 thresholds, the 0.3 kept); a 3 x 3 smoothing within each group; then
  (ours) a pixel under ``DOUBT`` of its surface's median confidence is blended, by confidence,
  with a normalised convolution of the surface's confident pixels around it. Pixels where a
  light sphere itself is in view are left out of that capture. Three passes: each refreshes the
  groups' reflectance the unseen patches use.
- **Relighting**: any set of spherical lights (power changes, added or removed lights): the
  same direct term, the radiosity solve with the recovered reflectance for every patch, per
  pixel ``B = rho / pi (E_direct + E_indirect)``. A light's geometry term is cached, so a power
  change is a weighted sum (no rays), an added light traces its own rays only (adaptively: a
  quarter of its sample points first, the rest only where those disagree).
- **Virtual objects** (``EDITS.json`` ``"objects"``, :func:`load_edits`; the paper's section 5):
  Lambertian meshes inserted with their own albedo. They shadow the room's lamps (re-traced only
  inside the shaft from a lamp to the objects' bounding sphere), block the room's own form
  factors (only links passing that sphere re-traced), and join the radiosity solve as clusters
  of their faces, so they reflect light onto the room and take the room's light themselves; an
  object's pixel is shaded with its own normal against its cluster's view of the room. A moved
  object is the same computation with the last frame's radiosity as the start.
- **Real objects removed** (``EDITS.json`` ``"remove"``: room.obj groups): the camera sees what
  they hid; its reflectance, never photographed, is refilled from the same surface around it by
  a normalised convolution (a smooth fill; the paper uses texture synthesis), and their shadows
  and blocked form factors are redone inside the shaft to their bounding sphere.

Lamps can come from the probes instead of the captures' json being measured by hand:
:mod:`hostlink.room.probes` (``lightprobe room lights``). Not built: texture synthesis; objects
turned or moved in depth by the alignment.
"""

from __future__ import annotations

import json
import math
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from device.core.errors import InputError
from device.core.sphere import luminance

__all__ = ["CameraCV", "Light", "Room", "VirtualObject", "load_camera", "load_edits", "load_lights", "movable_groups"]

INDIRECT = ("radiosity", "ambient", "none")   # Room.recover's indirect terms
DOUBT = 0.5            # a pixel under this fraction of its surface's median confidence is blended with its surroundings
SNAP_RADIUS = 2        # a pixel may take the geometry of a pixel this many pixels away ...
SNAP_GAIN = 0.5        # ... whose shading explains its captures this much better (misfit ratio) ...
SNAP_MIN = 0.02        # ... when its own misfit is over this (relative, squared: 14% rms)
SNAP_CAP = 0.2         # a pixel's misfit counts at most this much in an alignment's score
ALIGN_WIDTH = 160      # an alignment scores its candidates at most this many pixels wide
ALIGN_BOUND = 0.02     # objects move at most this share of the room's largest extent (the paper's modelling error) ...
ALIGN_STEPS = (0.75, 0.375, 0.1875, 0.09375)   # ... in steps of these shares of that bound ...
ALIGN_STEP_GAIN = 0.01     # ... each kept when it lowers the captures' misfit by this share of the model's own ...
ALIGN_GAIN = 0.95      # ... and the whole alignment only when it ends below this share of it
OUTLIER = 0.3          # a capture's reflectance further than this fraction from the median is rejected


@dataclass(frozen=True)
class Light:
    position: tuple[float, float, float]
    radius: float
    rgb: tuple[float, float, float]     # emitted power per colour (W)


@dataclass
class CameraCV:
    K: np.ndarray
    R: np.ndarray
    t: np.ndarray
    width: int
    height: int

    @property
    def center(self) -> np.ndarray:
        return np.asarray(-self.R.T @ self.t)

    def scaled(self, s: float) -> CameraCV:
        """The same camera with images ``s`` times the size (pixel centres at integers, as OpenCV)."""
        w, h = max(1, round(self.width * s)), max(1, round(self.height * s))
        sx, sy = w / self.width, h / self.height
        K = np.array(self.K, np.float64, copy=True)
        K[0, 0], K[0, 1], K[0, 2] = K[0, 0] * sx, K[0, 1] * sx, (K[0, 2] + 0.5) * sx - 0.5
        K[1, 1], K[1, 2] = K[1, 1] * sy, (K[1, 2] + 0.5) * sy - 0.5
        return CameraCV(K, self.R, self.t, w, h)


def _read_json(path: Path) -> Any:
    try:
        return json.loads(path.read_text())
    except FileNotFoundError:
        raise InputError(f"{path}: missing", param=path.name) from None
    except OSError as e:
        raise InputError(f"{path}: cannot read ({e.strerror})", param=path.name) from None
    except json.JSONDecodeError as e:
        raise InputError(f"{path}:{e.lineno}: invalid JSON ({e.msg})", param=path.name) from None


def _mat(doc: dict[str, Any], key: str, shape: tuple[int, ...], where: Path) -> np.ndarray:
    try:
        a = np.asarray(doc[key], np.float64)
    except (KeyError, TypeError, ValueError):
        raise InputError(f"{where}: {key!r} must be a {'x'.join(map(str, shape))} array of numbers", param=key) from None
    if a.shape != shape or not np.isfinite(a).all():
        raise InputError(f"{where}: {key!r} must be a finite {'x'.join(map(str, shape))} array, got shape {a.shape}",
                         param=key)
    return a


def load_camera(path: str | Path) -> CameraCV:
    p = Path(path)
    doc = _read_json(p)
    if not isinstance(doc, dict):
        raise InputError(f"{p}: expected an object with K, R, t, width, height", param="camera")
    K, R, t = _mat(doc, "K", (3, 3), p), _mat(doc, "R", (3, 3), p), _mat(doc, "t", (3,), p)
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0:
        raise InputError(f"{p}: 'R' must be a rotation (orthonormal, det +1)", param="R")
    if K[0, 0] <= 0 or K[1, 1] <= 0:
        raise InputError(f"{p}: 'K' needs positive focal lengths", param="K")
    try:
        w, h = int(doc["width"]), int(doc["height"])
    except (KeyError, TypeError, ValueError):
        raise InputError(f"{p}: 'width' and 'height' must be integers", param="width") from None
    if not (0 < w <= 16384 and 0 < h <= 16384):
        raise InputError(f"{p}: width and height must be in 1..16384, got {w} x {h}", param="width")
    return CameraCV(K, R, t, w, h)


def load_lights(path: str | Path) -> list[Light]:
    p = Path(path)
    doc = _read_json(p)
    if not isinstance(doc, dict) or not isinstance(doc.get("lights"), list) or not doc["lights"]:
        raise InputError(f"{p}: expected {{\"lights\": [{{\"position\", \"radius\", \"rgb\"}}, ...]}}", param="lights")
    out = []
    for i, d in enumerate(doc["lights"]):
        if not isinstance(d, dict):
            raise InputError(f"{p}: lights[{i}] must be an object", param="lights")
        pos = _mat(d, "position", (3,), p)
        rgb = _mat(d, "rgb", (3,), p)
        try:
            r = float(d["radius"])
        except (KeyError, TypeError, ValueError):
            raise InputError(f"{p}: lights[{i}].radius must be a number", param="radius") from None
        if not (math.isfinite(r) and r > 0) or (rgb < 0).any():
            raise InputError(f"{p}: lights[{i}] needs radius > 0 and rgb >= 0", param="radius")
        out.append(Light(tuple(pos.tolist()), r, tuple(rgb.tolist())))  # type: ignore[arg-type]
    return out


@dataclass(frozen=True)
class VirtualObject:
    """A virtual mesh inserted into the room: posed vertices (world units), faces, and a
    Lambertian albedo."""

    name: str
    vertices: np.ndarray
    faces: np.ndarray
    albedo: tuple[float, float, float]


def load_edits(path: str | Path) -> tuple[list[Light], list[VirtualObject], list[str]]:
    """EDITS.json: ``{"lights": [...], "objects": [{"mesh": "spot.obj", "albedo": [r, g, b],
    "scale": s, "rotation": [x, y, z], "translation": [x, y, z]}], "remove": ["short_block"]}``:
    the whole edited light set (the captures' format), virtual meshes to insert (OBJ paths
    relative to the file; each scaled about its own origin, rotated by XYZ Euler degrees, then
    translated) and room.obj groups to remove."""
    from hostlink.relight.scene import load_obj, rotation_matrix

    p = Path(path)
    lights = load_lights(p)
    doc = _read_json(p)
    objs = doc.get("objects", [])
    if not isinstance(objs, list):
        raise InputError(f"{p}: 'objects' must be a list", param="objects")
    out = []
    for i, d in enumerate(objs):
        if not isinstance(d, dict) or not isinstance(d.get("mesh"), str):
            raise InputError(f"{p}: objects[{i}] needs a \"mesh\" (an OBJ path)", param="objects")
        alb = _mat(d, "albedo", (3,), p)
        if (alb < 0).any() or (alb > 1).any():
            raise InputError(f"{p}: objects[{i}].albedo must lie in [0, 1]", param="albedo")
        rot = _mat(d, "rotation", (3,), p) if "rotation" in d else np.zeros(3)
        tr = _mat(d, "translation", (3,), p) if "translation" in d else np.zeros(3)
        try:
            sc = float(d.get("scale", 1.0))
        except (TypeError, ValueError):
            raise InputError(f"{p}: objects[{i}].scale must be a number", param="scale") from None
        if not (math.isfinite(sc) and sc > 0):
            raise InputError(f"{p}: objects[{i}].scale must be > 0", param="scale")
        mp = Path(d["mesh"]) if Path(d["mesh"]).is_absolute() else p.parent / d["mesh"]
        mesh = load_obj(mp)
        v = (sc * np.asarray(mesh.vertices, np.float64)) @ rotation_matrix(rot).T + tr
        out.append(VirtualObject(str(d.get("name", mp.stem)), v, np.asarray(mesh.faces, np.int64),
                                 tuple(alb.tolist())))  # type: ignore[arg-type]
    rem = doc.get("remove", [])
    if not isinstance(rem, list) or not all(isinstance(x, str) for x in rem):
        raise InputError(f"{p}: 'remove' must be a list of room.obj group names", param="remove")
    return lights, out, rem


def _clusters(v: np.ndarray, f: np.ndarray, k: int = 4) -> tuple[np.ndarray, ...]:
    """The object's faces grouped for the radiosity solve: a k^3 grid over its bounds times the
    six major directions of the face normal. Returns (label per face, a point on each cluster's
    surface (Q, 3), unit normal (Q, 3), area (Q,))."""
    a, b, c = (v[f[:, j]] for j in range(3))
    cr = np.cross(b - a, c - a)
    area = 0.5 * np.linalg.norm(cr, axis=1)
    n = cr / np.maximum(2 * area, 1e-300)[:, None]
    cen = (a + b + c) / 3
    lo, hi = v.min(axis=0), v.max(axis=0)
    cell = np.clip(((cen - lo) / np.maximum(hi - lo, 1e-12) * k).astype(np.int64), 0, k - 1)
    ax = np.argmax(np.abs(n), axis=1)
    sign = (n[np.arange(len(n)), ax] < 0).astype(np.int64)
    key = ((cell[:, 0] * k + cell[:, 1]) * k + cell[:, 2]) * 6 + 2 * ax + sign
    _, label = np.unique(key, return_inverse=True)
    Q = int(label.max()) + 1
    A = np.bincount(label, area, minlength=Q)
    C = np.stack([np.bincount(label, area * cen[:, j], minlength=Q) for j in range(3)], 1) / np.maximum(A, 1e-300)[:, None]
    Nq = np.stack([np.bincount(label, area * n[:, j], minlength=Q) for j in range(3)], 1).astype(np.float64)
    Nq /= np.maximum(np.linalg.norm(Nq, axis=1, keepdims=True), 1e-300)
    # a curved cluster's centroid may lie inside the mesh: it is represented by the centre of its
    # face nearest that centroid, just off the surface along that face's normal
    gap = np.linalg.norm(cen - C[label], axis=1)
    order = np.lexsort((gap, label))
    first = order[np.r_[0, np.flatnonzero(np.diff(label[order])) + 1]]
    rep = cen[first] + 1e-3 * float(np.ptp(v, axis=0).max()) * n[first]
    return label, rep, Nq, A


def _mv(M: np.ndarray, B: np.ndarray) -> np.ndarray:
    """``M @ B`` in M's float32 (no float64 copy of a (P, P) form-factor matrix per product)."""
    return np.asarray(M @ B.astype(M.dtype), np.float64)


def _near_segment(P: np.ndarray, q: np.ndarray, c: np.ndarray, r: float) -> np.ndarray:
    """Segments ``P[i] -> q`` passing within ``r`` of ``c``."""
    from hostlink.room.kernels import near_to_point

    out = np.zeros(len(P), np.bool_)
    near_to_point(np.ascontiguousarray(P, np.float64), np.asarray(q, np.float64), np.asarray(c, np.float64),
                  float(r), out)
    return out


def _subdivide(v: np.ndarray, f: np.ndarray, fg: np.ndarray, max_edge: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each triangle split on a barycentric grid into n^2 triangles no longer than ``max_edge``."""
    verts, faces, groups = [], [], []
    base = 0
    for t, (a, b, c) in enumerate(f):
        A, B, C = v[a], v[b], v[c]
        e = max(np.linalg.norm(B - A), np.linalg.norm(C - A), np.linalg.norm(C - B))
        n = max(1, math.ceil(e / max_edge))
        idx: dict[tuple[int, int], int] = {}
        pts: list[np.ndarray] = []
        for i in range(n + 1):
            for j in range(n + 1 - i):
                idx[i, j] = len(pts)
                pts.append(A + (B - A) * (i / n) + (C - A) * (j / n))
        tri = []
        for i in range(n):
            for j in range(n - i):
                tri.append((idx[i, j], idx[i + 1, j], idx[i, j + 1]))
                if i + j < n - 1:
                    tri.append((idx[i + 1, j], idx[i + 1, j + 1], idx[i, j + 1]))
        verts.append(np.array(pts))
        faces.append(np.array(tri) + base)
        groups.append(np.full(len(tri), fg[t]))
        base += len(pts)
    return np.concatenate(verts), np.concatenate(faces).astype(np.int64), np.concatenate(groups)


def _raster_cv(cam: CameraCV, v: np.ndarray, f: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    from hostlink.relight.raster import _raster

    xc = v @ cam.R.T + cam.t
    z = xc[:, 2]
    zs = np.where(z > 1e-9, z, 1e-9)
    sx = cam.K[0, 0] * xc[:, 0] / zs + cam.K[0, 1] * xc[:, 1] / zs + cam.K[0, 2]
    sy = cam.K[1, 1] * xc[:, 1] / zs + cam.K[1, 2]
    tri = np.full((cam.height, cam.width), -1, np.int64)
    bary = np.zeros((cam.height, cam.width, 3), np.float32)
    _raster(sx, sy, z, f, cam.width, cam.height, tri, bary, np.zeros((cam.height, cam.width)))
    return tri, bary


def _normalised_fill(shape: tuple[int, int], src: np.ndarray, value: np.ndarray, weight: np.ndarray,
                     todo: np.ndarray, fallback: np.ndarray) -> np.ndarray:
    """Values (len(todo), 3) at flat pixel indices ``todo`` of an image ``shape``, from ``value``
    at ``src`` with confidences ``weight``: a normalised convolution (Knutsson, Westin 1993) at
    each pixel's finest Gaussian scale that reaches it; ``fallback`` where none does."""
    import cv2

    wimg = np.zeros(shape, np.float32)
    wimg.flat[src] = weight
    acc = np.zeros((*shape, 3), np.float32)
    acc.reshape(-1, 3)[src] = value * weight[:, None]
    fill = np.array(fallback, np.float64)
    left = np.ones(len(todo), bool)
    for sigma in (2.0, 4.0, 8.0, 16.0, 32.0, 64.0):
        wb = cv2.GaussianBlur(wimg, (0, 0), sigma).ravel()[todo]
        ab = cv2.GaussianBlur(acc, (0, 0), sigma).reshape(-1, 3)[todo]
        ok = left & (wb > 1e-3)
        fill[ok] = ab[ok] / wb[ok, None]
        left &= ~ok
        if not left.any():
            break
    return fill


def _owned(f: np.ndarray, fg: np.ndarray, g: int) -> tuple[np.ndarray, bool]:
    """Group ``g``'s vertices (indices) and whether it owns them (no other group's face uses one)."""
    mine = np.unique(f[fg == g])
    return mine, not np.intersect1d(mine, np.unique(f[fg != g])).size


def _moved(v: np.ndarray, f: np.ndarray, fg: np.ndarray, names: list[str], offsets: dict[str, tuple[float, ...]],
           where: Path) -> np.ndarray:
    """The model's vertices with each named group's vertices translated by its offset (a group
    must own its vertices: one that shares them with another group cannot move alone)."""
    out = np.array(v, np.float64, copy=True)
    for name, off in offsets.items():
        if name not in names:
            raise InputError(f"{where}: no group {name!r} to move (groups: {', '.join(names)})", param="offsets")
        mine, owns = _owned(f, fg, names.index(name))
        if not owns:
            raise InputError(f"{where}: group {name!r} shares vertices with another group: it cannot move alone",
                             param="offsets")
        out[mine] += np.asarray(off, np.float64)
    return out


def _misfit(b2: np.ndarray, sbs: np.ndarray, sss: np.ndarray, missing: float) -> np.ndarray:
    """How badly one reflectance explains measured radiances ``b_k`` as ``rho s_k`` (modelled
    irradiances) over captures k, given ``b2 = sum b^2``, ``sbs = sum b s``, ``sss = sum s^2``:
    ``min_rho sum (b - rho s)^2 / sum b^2 = 1 - sbs^2 / (b2 sss)``; ``missing`` where a sum is 0."""
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where((sss > 0) & (b2 > 0), (b2 - sbs * sbs / sss) / b2, missing)


def movable_groups(v: np.ndarray, f: np.ndarray, fg: np.ndarray, names: list[str]) -> list[str]:
    """Groups that are objects in the room rather than its shell: smaller than 90% of the room's
    extent along every axis and owning their vertices."""
    ext = np.ptp(v, axis=0)
    out = []
    for g, name in enumerate(names):
        if not (fg == g).any():
            continue
        mine, owns = _owned(f, fg, g)
        if owns and (np.ptp(v[mine], axis=0) < 0.9 * ext).all():
            out.append(name)
    return out


SUBPIXEL = 3           # s x s samples over a pixel whose footprint crosses an edge


@dataclass(frozen=True)
class _Footprints:
    """The camera's pixels that straddle an edge (two groups, a fold, a neighbour off the pixel's
    plane, the border of the geometry): ``SUBPIXEL`` x ``SUBPIXEL`` samples over each such pixel's footprint
    (a camera's box filter: what it records there is the mean of what lands on it, not the
    light at the pixel's centre). ``pix`` indexes the covered pixels, one run of ``k`` entries
    per edge pixel; ``patch`` is -1 where a sample misses the geometry (it counts as black)."""

    edge: np.ndarray         # (e,) covered-pixel indices
    pix: np.ndarray          # (e k,)
    X: np.ndarray            # (m, 3) the samples that hit, ``hit`` of the e k
    N: np.ndarray
    patch: np.ndarray        # (m,) patch per sample that hit
    hit: np.ndarray          # (e k,) bool
    k: int
    n: int                   # covered pixels

    def pixels(self, centre: np.ndarray, sub: np.ndarray) -> np.ndarray:
        """Per covered pixel: ``centre`` (n, ...) with the edge pixels replaced by the mean of
        their samples' ``sub`` (m, ...)."""
        if not len(self.edge):
            return centre
        out = centre.copy()
        full = np.zeros((len(self.pix), *sub.shape[1:]), sub.dtype)
        full[self.hit] = sub
        out[self.edge] = full.reshape((len(self.edge), self.k, *sub.shape[1:])).mean(axis=1)
        return out

    def gather(self, Q: np.ndarray, centre_patch: np.ndarray) -> np.ndarray:
        """A per-patch quantity ``Q`` (P, ...) at each covered pixel, over its footprint."""
        return self.pixels(Q[centre_patch], Q[self.patch])


def _footprints(cam: CameraCV, cover: np.ndarray, X: np.ndarray, N: np.ndarray, group: np.ndarray,
                es: Any, faces: np.ndarray, pn: np.ndarray, s: int = SUBPIXEL) -> _Footprints:
    """Find the edge pixels of a view (covered pixels ``cover``, their points, normals, groups)
    and cast ``s`` x ``s`` camera rays over each one into the Embree scene ``es`` (whose
    primitive ``i`` is patch ``faces[i]``; ``pn`` the patches' normals)."""
    H, W = cover.shape
    idx = np.full((H, W), -1)
    idx[cover] = np.arange(len(X))
    z = np.zeros((H, W))
    z[cover] = (X @ cam.R.T + cam.t)[:, 2]
    ximg = np.zeros((H, W, 3))
    ximg[cover] = X
    nimg = np.zeros((H, W, 3))
    nimg[cover] = N
    gimg = np.full((H, W), -1)
    gimg[cover] = group
    edge = np.zeros((H, W), bool)
    for dy, dx in ((0, 1), (1, 0), (1, 1), (1, -1)):
        a = (slice(max(0, -dy), H - max(0, dy)), slice(max(0, -dx), W - max(0, dx)))
        b = (slice(max(0, dy), H - max(0, -dy)), slice(max(0, dx), W - max(0, -dx)))
        d = (gimg[a] != gimg[b]) | (np.einsum("ijk,ijk->ij", nimg[a], nimg[b]) < 0.99) | \
            (np.abs(np.einsum("ijk,ijk->ij", nimg[a], ximg[b] - ximg[a])) > 0.01 * np.maximum(z[a], z[b]))   # off the plane
        edge[a] |= d
        edge[b] |= d
    edge &= cover
    ei = idx[edge]
    yy, xx = np.nonzero(edge)
    off = (np.arange(s) + 0.5) / s - 0.5
    ox, oy = (g.ravel() for g in np.meshgrid(off, off))
    px = (xx[:, None] + ox[None]).ravel()
    py = (yy[:, None] + oy[None]).ravel()
    d_cam = np.linalg.solve(cam.K, np.stack([px, py, np.ones_like(px)]))
    d = (cam.R.T @ d_cam).T
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    o = np.broadcast_to(cam.center, d.shape)
    if len(d):
        res = es.run(np.ascontiguousarray(o, np.float32), np.ascontiguousarray(d, np.float32), output=1)
        prim, t = np.asarray(res["primID"]), np.asarray(res["tfar"], np.float64)
    else:
        prim, t = np.zeros(0, np.int64), np.zeros(0)
    hit = prim >= 0
    patch = faces[prim[hit]]
    Xs = cam.center + t[hit, None] * d[hit]
    Ns = pn[patch]
    Ns = np.where((np.einsum("ij,ij->i", Ns, cam.center - Xs) < 0)[:, None], -Ns, Ns)
    return _Footprints(ei, np.repeat(ei, s * s), Xs, Ns, patch, hit, s * s, len(X))


class Room:
    """A photographed room: :meth:`recover` its reflectance, then :meth:`render` it under other
    lights. ``directory`` holds room.obj, camera.json and captures/ (see the module notes)."""

    def __init__(self, directory: str | Path, *, patch_size: float | None = None, light_samples: int = 16,
                 offsets: dict[str, Any] | None = None, camera: CameraCV | None = None) -> None:
        from hostlink.relight.precompute import build_embree
        from hostlink.relight.scene import load_obj_groups

        d = Path(directory)
        if not d.is_dir():
            raise InputError(f"{d}: not a folder", param="room")
        mesh, fg, names = load_obj_groups(d / "room.obj")
        self.directory = d
        self.cam = load_camera(d / "camera.json") if camera is None else camera
        self.group_names = names
        self.model_vertices, self.model_faces, self.model_groups = mesh.vertices, mesh.faces, fg
        self.offsets = {str(k): tuple(float(x) for x in np.asarray(o, np.float64).reshape(3))
                        for k, o in (offsets or {}).items()}
        verts = _moved(mesh.vertices, mesh.faces, fg, names, self.offsets, d / "room.obj")
        diag = float(np.linalg.norm(np.ptp(mesh.vertices, axis=0)))
        self.eps = 1e-4 * diag
        self.patch_size = float(patch_size or diag / 16)
        self.light_samples = int(light_samples)
        self.v, self.f, self.fgroup = _subdivide(verts, mesh.faces, fg, self.patch_size)
        a, b, c = (self.v[self.f[:, k]] for k in range(3))
        cr = np.cross(b - a, c - a)
        self.area = 0.5 * np.linalg.norm(cr, axis=1)
        self.pn = cr / np.maximum(2 * self.area, 1e-300)[:, None]
        self.pc = (a + b + c) / 3
        self._es = build_embree([(self.v, self.f)])
        tri, bary = _raster_cv(self.cam, self.v, self.f)
        self.cover = tri >= 0
        if not self.cover.any():
            raise InputError(f"{d / 'camera.json'}: the camera sees no geometry of room.obj", param="camera")
        self.patch = tri[self.cover]
        bw = bary[self.cover].astype(np.float64)
        fv = self.f[self.patch]
        self.X = np.einsum("pk,pkj->pj", bw, self.v[fv])
        n = self.pn[self.patch]
        flip = np.einsum("ij,ij->i", n, self.cam.center - self.X) < 0
        self.N = np.where(flip[:, None], -n, n)
        self.group = self.fgroup[self.patch]
        # patch normals face the camera side where the camera sees them; elsewhere the room's inside
        self._orient_patches()
        self.fp = _footprints(self.cam, self.cover, self.X, self.N, self.group, self._es, np.arange(len(self.f)), self.pn)
        self.src = np.arange(len(self.X))       # the pixel whose geometry shades each pixel (:meth:`_snap`)
        self.snapped = 0                         # pixels shaded by another pixel's geometry
        self.align_misfit: tuple[float, float] | None = None   # (the model's, the aligned model's) (:meth:`align`)
        self.captures = []
        cap = d / "captures"
        files = sorted(cap.glob("*.exr")) if cap.is_dir() else []
        for p in files:
            lights = load_lights(p.with_suffix(".json"))
            for L in lights:
                self._check_light(L, p.with_suffix(".json"))
            self.captures.append((p.stem, p, lights))
        self._geo: dict[tuple[tuple[float, float, float], float], tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]] = {}
        self._F: np.ndarray | None = None
        self._pairs: tuple[np.ndarray, ...] | None = None   # (i, j) with F[i, j] > 0
        self._F_rows: np.ndarray | None = None
        self._last_B: tuple[tuple[Light, ...], np.ndarray] | None = None
        self._tri = np.ascontiguousarray(np.stack([self.v[self.f[:, k]] for k in range(3)], axis=1))   # (P, 3, 3)
        self._unit: dict[Light, np.ndarray] = {}
        self._unit_key: bytes | None = None
        self.reflectance: np.ndarray | None = None
        self.confidence: np.ndarray | None = None
        self.patch_reflectance: np.ndarray | None = None
        self.object_mask: np.ndarray | None = None     # pixels the last render's objects cover
        self.render_cover: np.ndarray = self.cover      # pixels the last render shaded

    # ---- geometry ------------------------------------------------------------------------------
    def _orient_patches(self) -> None:
        seen = np.zeros(len(self.f), bool)
        seen[self.patch] = True
        flip_seen = np.zeros(len(self.f), bool)
        np.logical_or.at(flip_seen, self.patch, np.einsum("ij,ij->i", self.pn[self.patch], self.N) < 0)
        self.pn[seen & flip_seen] *= -1
        # a patch the camera does not see faces the side from which more of the seen patches are
        # in view (a block's top and far sides face out, not into the block); a patch that sees
        # none from either side faces the room's centroid
        unseen = np.flatnonzero(~seen)
        if not len(unseen):
            return
        rng = np.random.default_rng(0)
        seen_idx = np.flatnonzero(seen)
        S = seen_idx if len(seen_idx) <= 128 else rng.choice(seen_idx, 128, replace=False)
        w = self.pc[S][None] - self.pc[unseen][:, None]                 # (u, s, 3)
        dist = np.linalg.norm(w, axis=2)
        wd = w / np.maximum(dist, 1e-300)[..., None]
        cu = np.einsum("usk,uk->us", wd, self.pn[unseen])
        facing = np.einsum("usk,sk->us", wd, self.pn[S]) < 0          # the seen patch's front faces it
        votes = np.zeros((len(unseen), 2))
        for side, sign in enumerate((1.0, -1.0)):
            ui, si = np.nonzero((sign * cu > 1e-3) & facing)
            o = self.pc[unseen[ui]] + sign * self.eps * self.pn[unseen[ui]]
            free = ~self._occluded(o, wd[ui, si], dist[ui, si] - 2 * self.eps)
            votes[:, side] = np.bincount(ui[free], minlength=len(unseen))
        centroid = self.v.mean(axis=0)
        inward = np.einsum("ij,ij->i", self.pn[unseen], centroid - self.pc[unseen]) < 0
        flip = np.where(votes.sum(axis=1) > 0, votes[:, 1] > votes[:, 0], inward)
        self.pn[unseen[flip]] *= -1

    def _check_light(self, L: Light, where: Path) -> None:
        c = np.asarray(L.position)
        # distance from the centre to every patch (point-triangle, via the closest of centre / vertices / plane)
        d_plane = np.abs(np.einsum("ij,ij->i", c - self.pc, self.pn))
        near = np.linalg.norm(self.pc - c, axis=1) < 2 * np.sqrt(self.area) + L.radius
        if (near & (d_plane < L.radius)).any():
            raise InputError(f"{where}: light at {list(L.position)} (radius {L.radius}) is inside a surface of room.obj",
                             param="lights")

    def _geometry(self, L: Light) -> tuple[np.ndarray, np.ndarray]:
        """Irradiance per watt of a light: (pixels,) over each pixel's footprint, (patches,), cached."""
        g = self._geometry_parts(L)
        return g[0], g[1]

    def _geometry_parts(self, L: Light) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(pixels, patches, pixel centres, edge pixels' samples) irradiance per watt, cached."""
        key = (L.position, L.radius)          # the power does not change the geometry
        g = self._geo.get(key)
        if g is None:
            gc = self._irradiance(L, self.X, self.N)
            gs = self._irradiance(L, self.fp.X, self.fp.N)
            g = (self.fp.pixels(gc, gs), self._irradiance(L, self.pc, self.pn), gc, gs)
            self._geo[key] = g
        return g

    def _irradiance(self, L: Light, P: np.ndarray, N: np.ndarray, es: Any = None) -> np.ndarray:
        """Irradiance per watt at points ``P`` with normals ``N``: a uniformly emitting sphere's
        field is its centre's, ``1 / (4 pi d^2)`` at distance d; the cosine and the visibility
        averaged over the points of the cap facing the receiver (of ``light_samples`` x 2
        Fibonacci points on the sphere), one shadow ray each (adaptively: the rest only where the
        first quarter disagree), so a sphere partly below a receiver's horizon or partly hidden
        lights it partly."""
        from hostlink.room.kernels import sphere_light_rays

        m = self.light_samples
        k = np.arange(2 * m) + 0.5
        z = 1 - 2 * k / (2 * m)
        ph = k * math.pi * (3 - math.sqrt(5))
        u = np.stack([np.sqrt(1 - z * z) * np.cos(ph), z, np.sqrt(1 - z * z) * np.sin(ph)], 1)
        c = np.asarray(L.position, np.float64)
        S = c + L.radius * u
        P = np.ascontiguousarray(P, np.float64)
        N = np.ascontiguousarray(N, np.float64)
        dc = np.linalg.norm(c - P, axis=1)
        # adaptive (the paper's adaptive rays to an area light): every 4th point first; a receiver
        # whose first rays all agree (wholly lit or wholly hidden) takes that answer for the rest
        stages = (np.flatnonzero(np.arange(len(u)) % 4 == 0), np.flatnonzero(np.arange(len(u)) % 4 != 0))
        out = np.zeros(len(P))
        for s0 in range(0, len(P), 32768):
            Pc, Nc = P[s0:s0 + 32768], N[s0:s0 + 32768]
            n = len(Pc)
            free, cnt = np.zeros(n), np.zeros(n)
            n_free, n_ray = np.zeros(n, np.int64), np.zeros(n, np.int64)
            for stage, cols in enumerate(stages):
                m_ = len(cols)
                o, d, t = np.empty((n, m_, 3)), np.empty((n, m_, 3)), np.empty((n, m_))
                cos, st = np.zeros((n, m_)), np.empty((n, m_), np.uint8)
                sphere_light_rays(Pc, Nc, S, u, c, float(L.radius), float(self.eps), cols, o, d, t, cos, st)
                ray = st == 1
                occ = np.ones((n, m_), bool)
                if stage == 1:
                    uniform = (n_ray >= 2) & ((n_free == 0) | (n_free == n_ray))
                    guess = ray & uniform[:, None]
                    occ[guess] = np.broadcast_to((n_free == 0)[:, None], occ.shape)[guess]
                    ray &= ~uniform[:, None]
                ri, ki = np.nonzero(ray)
                occ[ri, ki] = self._occluded(o[ri, ki], d[ri, ki], t[ri, ki], es)
                if stage == 0:
                    n_ray += ray.sum(axis=1)
                    n_free += (ray & ~occ).sum(axis=1)
                counted = st > 0
                free += np.where(counted & ~occ, cos, 0.0).sum(axis=1)
                cnt += counted.sum(axis=1)
            out[s0:s0 + n] = np.where(cnt > 0, free / np.maximum(cnt, 1), 0.0)
        # cosine per sample (a sphere across the horizon lights the receiver partly), distance
        # to the centre (the sphere's field; distances to its surface points overstate it)
        return out / (4 * math.pi * np.maximum(dc, 1e-12) ** 2)

    def _occluded(self, o: np.ndarray, d: np.ndarray, tfar: np.ndarray, es: Any = None) -> np.ndarray:
        """Occlusion of the segments ``o + t d``, ``t < tfar`` (two threads: Embree releases the GIL)."""
        n = len(o)
        if not n:
            return np.zeros(0, bool)
        scene = es or self._es
        o32, d32 = np.ascontiguousarray(o, np.float32), np.ascontiguousarray(d, np.float32)
        t32 = np.ascontiguousarray(np.maximum(tfar, 0), np.float32)

        def part(a: int, b: int) -> np.ndarray:
            return np.asarray(scene.run(o32[a:b], d32[a:b], dists=t32[a:b], query="OCCLUDED")) == 0

        if n < 16384:
            return part(0, n)
        from concurrent.futures import ThreadPoolExecutor

        h = n // 2
        with ThreadPoolExecutor(2) as ex:
            lo, hi = ex.submit(part, 0, h), ex.submit(part, h, n)
            return np.concatenate([lo.result(), hi.result()])

    def form_factors(self) -> np.ndarray:
        """(P, P) form factors from each patch centre to every patch: the exact unoccluded polygon
        form factor, zero when the ray between the centres is blocked."""
        if self._F is None:
            pc, pn = self.pc, self.pn
            P = len(pc)
            F = np.zeros((P, P), np.float32)
            for s in range(0, P, 256):
                rows = np.arange(s, min(P, s + 256))
                w = pc[None] - pc[rows, None]                    # (r, P, 3)
                d2 = np.einsum("rpk,rpk->rp", w, w)
                d = np.sqrt(np.maximum(d2, 1e-300))
                wd = w / d[..., None]
                ci = np.einsum("rpk,rk->rp", wd, pn[rows])
                cj = -np.einsum("rpk,pk->rp", wd, pn)
                ff = np.where((ci > 0) & (cj > 0), self._polygon_ff(rows), 0.0)
                ff[np.arange(len(rows)), rows] = 0.0
                ri, ci_ = np.nonzero(ff > 0)
                occ = self._occluded(pc[rows[ri]] + self.eps * pn[rows[ri]], wd[ri, ci_], d[ri, ci_] - 2 * self.eps)
                ff[ri[occ], ci_[occ]] = 0.0       # (4 rays per pair instead of 1: no better on the Cornell box)
                F[rows] = ff
            tot = F.sum(axis=1, keepdims=True)
            self._F = F / np.maximum(tot, 1.0)                    # energy: a patch sees at most its hemisphere
        return self._F

    def _polygon_ff(self, rows: np.ndarray) -> np.ndarray:
        """(r, P) unoccluded form factors from the centres of patches ``rows`` to every patch
        triangle, exact for a triangle above the receiver's horizon (Lambert's contour integral:
        ``1 / 2 pi sum_edges angle_i n . (R_i x R_i+1) / |R_i x R_i+1|``); near patches, where a
        point-to-point form factor fails, get their true share."""
        return self._polygon_ff_at(self.pc[rows], self.pn[rows])

    def _polygon_ff_at(self, x: np.ndarray, n: np.ndarray) -> np.ndarray:
        """(r, P) unoccluded form factors from points ``x`` with normals ``n`` to every patch."""
        return np.abs(np.einsum("rpk,rk->rp", self._polygon_ff_vectors(x), n))

    def _polygon_ff_vectors(self, x: np.ndarray) -> np.ndarray:
        """(r, P, 3) Lambert's vectors ``g`` of every patch seen from points ``x``: the form factor
        to a receiver of normal ``n`` is ``|g . n|`` while the patch lies above its horizon
        (:func:`hostlink.room.kernels.polygon_ff_vectors`)."""
        from hostlink.room.kernels import polygon_ff_vectors

        out = np.empty((len(x), len(self.f), 3))
        polygon_ff_vectors(np.ascontiguousarray(x, np.float64), self._tri, out)
        return out

    def _solve(self, Ed_patch: np.ndarray, rho_patch: np.ndarray, known: np.ndarray | None = None,
               B_known: np.ndarray | None = None, iters: int = 40, F: np.ndarray | None = None) -> np.ndarray:
        """Patch radiance (P, 3) of ``B = rho / pi (E_d + pi F B)``, measured patches held fixed
        (``F``: the room's form factors unless given)."""
        F = self.form_factors() if F is None else F
        B = rho_patch / math.pi * Ed_patch
        if known is not None and B_known is not None:
            B[known] = B_known[known]
        for _ in range(iters):       # Jacobi; stops when a sweep changes B by under 1e-5 of its max
            nb = rho_patch / math.pi * (Ed_patch + math.pi * _mv(F, B))
            if known is not None and B_known is not None:
                nb[known] = B_known[known]
            done = float(np.abs(nb - B).max()) <= 1e-5 * max(float(np.abs(nb).max()), 1e-300)
            B = nb
            if done:
                break
        return B

    def _indirect(self, Ed_patch: np.ndarray, rho_patch: np.ndarray, known: np.ndarray | None = None,
                  B_known: np.ndarray | None = None) -> np.ndarray:
        """Indirect irradiance (pixels, 3) over each pixel's footprint: the room's radiosity under
        the patches' direct irradiance ``Ed_patch`` (:meth:`_solve`, measured patches held),
        gathered through the form factors."""
        Bp = self._solve(Ed_patch, rho_patch, known, B_known)
        return math.pi * self.fp.gather(_mv(self.form_factors(), Bp), self.patch)

    def _pixel_index(self) -> np.ndarray:
        """(H, W): each covered pixel's index into the per-pixel arrays, -1 elsewhere."""
        idx = np.full((self.cam.height, self.cam.width), -1)
        idx[self.cover] = np.arange(len(self.X))
        return idx

    # ---- recovery ------------------------------------------------------------------------------
    def _in_view_of_lights(self, lights: list[Light]) -> np.ndarray:
        """Pixels whose camera ray passes within a pixel and a half of a light sphere in front of
        the surface (its image, antialiased, covers neighbours too)."""
        C = self.cam.center
        ray = self.X - C
        dist = np.linalg.norm(ray, axis=1)
        rd = ray / dist[:, None]
        hit = np.zeros(len(self.X), bool)
        for L in lights:
            oc = np.asarray(L.position) - C
            tc = rd @ oc
            d2 = oc @ oc - tc * tc
            reach = 1.05 * L.radius + 1.5 * tc / self.cam.K[1, 1]   # a pixel and a half of margin
            hit |= (d2 < reach ** 2) & (tc > 0) & (tc < dist)
        return hit

    def recover(self, *, filters: bool = True, passes: int = 3, indirect: str = "radiosity",
                snap: bool = True) -> np.ndarray:
        """Reflectance (H, W, 3) (0 where the camera sees no geometry); sets ``reflectance``
        (pixels, 3), ``confidence`` (pixels,) and ``patch_reflectance``.

        ``indirect``: ``"radiosity"`` (the solve over the patches, measured ones held), or an
        ambient estimate in the spirit of the paper's first one, ``"ambient"``: the room around
        a pixel taken to be as bright as the capture's mean colour ``C`` over the room, so its
        indirect irradiance is ``pi C`` times the share of its hemisphere the room's geometry
        covers (its form factors' sum; one pass, nothing refined), or ``"none"`` (all light
        taken as direct: right only for a room with black walls). ``snap``: after the first
        pass, a pixel whose captures a neighbour's geometry explains far better is shaded with
        that geometry from then on (:meth:`_snap`, ``src``)."""
        from device.core.imageio import read_hdr_image

        if indirect not in INDIRECT:
            raise InputError(f"indirect must be one of {', '.join(INDIRECT)}, not {indirect!r}", param="indirect")
        if not self.captures:
            raise InputError("captures/: no NAME.exr with NAME.json", param="captures")
        if indirect != "radiosity":
            passes = 1
        cover_ff = self.fp.gather(self.form_factors().sum(axis=1).astype(np.float64), self.patch) if indirect == "ambient" else np.zeros(0)
        H, W = self.cam.height, self.cam.width
        shots = []
        for name, p, lights in self.captures:
            img = read_hdr_image(p)
            if img.shape[:2] != (H, W):
                raise InputError(f"{p}: {img.shape[1]} x {img.shape[0]} pixels, camera.json says {W} x {H}", param="captures")
            B = np.nan_to_num(np.asarray(img, np.float64)[self.cover], nan=0.0, posinf=0.0).clip(0, None)
            Ed_pix = np.sum([np.outer(self._geometry(L)[0], L.rgb) for L in lights], axis=0)
            Ed_patch = np.sum([np.outer(self._geometry(L)[1], L.rgb) for L in lights], axis=0)
            shots.append((name, B, Ed_pix, Ed_patch, ~self._in_view_of_lights(lights)))
        P = len(self.f)
        ng = len(self.group_names)
        rho_group = np.full((ng, 3), 0.5)
        cnt = np.bincount(self.patch, minlength=P)
        seen = cnt > 0
        rho = np.zeros((len(self.X), 3))
        conf = np.zeros(len(self.X))
        self.src = np.arange(len(self.X))
        self.snapped = 0
        for pas in range(passes):
            rho_patch = rho_group[self.fgroup]
            if self.patch_reflectance is not None:
                rho_patch = np.where(seen[:, None], self.patch_reflectance, rho_patch)
            est, wts, shade = [], [], []
            for _name, B, Ed_pix, Ed_patch, usable in shots:
                Bm = np.zeros((P, 3))
                for ch in range(3):
                    Bm[:, ch] = np.bincount(self.patch[usable], B[usable, ch], minlength=P)
                cu = np.bincount(self.patch[usable], minlength=P)
                known = cu > 0
                Bm[known] /= cu[known, None]
                if indirect == "radiosity":
                    Ei = self._indirect(Ed_patch, rho_patch, known, Bm)
                elif indirect == "ambient":
                    Ei = math.pi * np.outer(cover_ff, B[usable].mean(axis=0))
                else:
                    Ei = np.zeros_like(Ed_pix)
                shade.append(Ed_pix + Ei)
            if pas == 0 and snap:
                self.src = self._snap([sh[1] for sh in shots], shade, [sh[4] for sh in shots])
            for (_name, B, Ed_pix, _ed_patch, usable), den in zip(shots, shade, strict=True):
                den = den[self.src]
                Ed_pix = Ed_pix[self.src]
                with np.errstate(divide="ignore", invalid="ignore"):
                    rk = np.where(den > 1e-12, math.pi * B / den, 0.0)
                w = luminance(Ed_pix) / np.maximum(luminance(den), 1e-300)
                w = np.where(usable & (luminance(den) > 1e-12), w, 0.0)
                est.append(rk)
                wts.append(w)
            R = np.stack(est)                # (k, n, 3)
            Wt = np.stack(wts)               # (k, n)
            if filters:
                Wt = np.stack([self._filter_confidence(w) for w in Wt])
            if filters and len(R) >= 3:
                lr = np.where(Wt > 0, luminance(R), np.nan)
                n_ok = (Wt > 0).sum(axis=0)
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore", RuntimeWarning)   # pixels no capture lights: NaN
                    lm = np.nanmedian(lr, axis=0)
                with np.errstate(invalid="ignore"):
                    dev = np.abs(luminance(R) - lm[None]) > OUTLIER * np.abs(lm[None])
                Wt = np.where(dev & (n_ok[None] >= 3), 0.0, Wt)       # the median needs 3 votes
            tot = Wt.sum(axis=0)
            rho = np.where(tot[:, None] > 0, (Wt[..., None] * R).sum(axis=0) / np.maximum(tot, 1e-300)[:, None], 0.0)
            conf = tot / len(R)
            if filters:
                rho = self._smooth(rho, conf)
                rho = self._refill_doubtful(rho, conf)
            rho_group = self._group_reflectance(rho, conf, rho_group)
            self._set_patch_reflectance(rho, conf, rho_group)
        self.reflectance, self.confidence = rho, conf
        return self._image(rho)

    def _snap(self, B: list[np.ndarray], S: list[np.ndarray], U: list[np.ndarray]) -> np.ndarray:
        """Which pixel's geometry shades each pixel: itself, unless the model is off there.

        ``B``, ``S``, ``U``: per capture the measured radiance, the modelled irradiance (direct +
        indirect) and the usable pixels. A pixel's captures under lamps at several positions say
        which surface it shows: the measured radiance must be one reflectance times the
        modelled irradiance in every capture. Its misfit with the best reflectance (relative,
        squared) is taken for its own modelled irradiance and for each pixel's within
        ``SNAP_RADIUS``; where its own exceeds ``SNAP_MIN`` and a neighbour's is under
        ``SNAP_GAIN`` of it, the neighbour's geometry shades it, in the recovery and in every
        edit. That fixes a silhouette or an edge the approximate model puts a pixel or two off
        (the model shows the block where the photographs show the wall behind it)."""
        H, W = self.cam.height, self.cam.width
        n = len(self.X)
        idx = self._pixel_index()
        yy, xx = np.nonzero(self.cover)
        Bl = np.stack([luminance(b) for b in B])
        Sl = np.stack([luminance(x) for x in S])
        Uw = np.stack(U).astype(np.float64)
        b2 = (Uw * Bl * Bl).sum(axis=0)
        best_e = np.full(n, np.inf)
        best_j = np.arange(n)
        own_e = np.full(n, np.inf)
        for dy in range(-SNAP_RADIUS, SNAP_RADIUS + 1):
            for dx in range(-SNAP_RADIUS, SNAP_RADIUS + 1):
                y2, x2 = yy + dy, xx + dx
                ok = (y2 >= 0) & (y2 < H) & (x2 >= 0) & (x2 < W)
                j = np.full(n, -1)
                j[ok] = idx[y2[ok], x2[ok]]
                ok = j >= 0
                Sj = Sl[:, np.maximum(j, 0)]
                sbs = (Uw * Bl * Sj).sum(axis=0)
                sss = (Uw * Sj * Sj).sum(axis=0)
                e = np.where(ok, _misfit(b2, sbs, sss, np.inf), np.inf)
                if dy == 0 and dx == 0:
                    own_e = e
                better = e < best_e
                best_e[better] = e[better]
                best_j[better] = j[better]
        switch = (own_e > SNAP_MIN) & (best_e < SNAP_GAIN * own_e)
        self.snapped = int(switch.sum())
        return np.where(switch, best_j, np.arange(n))

    def align(self, *, bound: float | None = None) -> dict[str, tuple[float, float, float]]:
        """Offsets that move the room's objects (:func:`movable_groups`) sideways, as the
        camera sees them, to where the captures put them; ``{}`` when nothing moves the
        captures' misfit below ``ALIGN_GAIN`` of the model's own (see the module notes).

        ``bound``: the largest move, default ``ALIGN_BOUND`` of the room's largest extent (the
        modelling error the paper allows). Every candidate is a room built with the offsets and
        scored by :meth:`_misfit_image` against the captures, with the indirect light of this
        model's recovery held fixed."""
        import cv2

        from device.core.imageio import read_hdr_image

        if not self.captures:
            raise InputError("captures/: no NAME.exr with NAME.json", param="captures")
        groups = movable_groups(self.model_vertices, self.model_faces, self.model_groups, self.group_names)
        if not groups:
            return {}
        size = float(np.ptp(self.model_vertices, axis=0).max())
        bound = ALIGN_BOUND * size if bound is None else float(bound)
        fwd = self.cam.R[2].astype(np.float64).copy()
        fwd[1] = 0.0
        if np.linalg.norm(fwd) < 1e-6:          # looking straight down or up: the camera's x axis
            fwd = np.cross(self.cam.R[0], [0.0, 1.0, 0.0])
        lat = np.cross([0.0, 1.0, 0.0], fwd)
        lat /= np.linalg.norm(lat)
        if self.reflectance is None:
            self.recover(snap=False)
        assert self.patch_reflectance is not None
        H, W = self.cam.height, self.cam.width
        # the candidates are scored on a camera at most ALIGN_WIDTH pixels wide (the indirect
        # light and the captures area-averaged to it): silhouettes move by whole pixels there too
        cam = self.cam.scaled(ALIGN_WIDTH / W) if W > ALIGN_WIDTH else self.cam
        size2 = (cam.width, cam.height)
        B, Ei = [], []
        for _name, p, lights in self.captures:
            b = luminance(np.asarray(read_hdr_image(p), np.float64))
            Ed_patch = np.sum([np.outer(self._geometry(L)[1], L.rgb) for L in lights], axis=0)
            e = np.zeros((H, W))
            e[self.cover] = luminance(self._indirect(Ed_patch, self.patch_reflectance))
            if cam is not self.cam:
                b = np.asarray(cv2.resize(b, size2, interpolation=cv2.INTER_AREA), np.float64)
                e = np.asarray(cv2.resize(e, size2, interpolation=cv2.INTER_AREA), np.float64)
            B.append(b)
            Ei.append(e)
        fine = bound / 96          # positions in units of the finest step, so candidates are found again

        def model(offs: dict[str, Any]) -> Room:
            return Room(self.directory, patch_size=self.patch_size, light_samples=self.light_samples,
                        offsets=offs, camera=cam)

        unmoved = model({})
        scored = unmoved.cover          # the pixels the model itself covers
        pos = dict.fromkeys(groups, 0)
        cache = {tuple(pos.values()): unmoved._misfit_image(B, Ei, scored)}

        def cost(pos: dict[str, int]) -> float:
            key = tuple(pos[g] for g in groups)
            if key not in cache:
                try:
                    cache[key] = model({g: tuple(lat * pos[g] * fine) for g in groups if pos[g]})._misfit_image(
                        B, Ei, scored)
                except InputError:      # a capture's lamp inside a moved object
                    cache[key] = math.inf
            return cache[key]

        # coordinate descent over each object's sideways offset, the step halving
        f0 = best = cost(pos)
        for frac in ALIGN_STEPS:
            k = max(1, round(frac * 96))
            moved = True
            while moved:
                moved = False
                for g in groups:
                    for sgn in (1, -1):
                        trial = dict(pos)
                        trial[g] += sgn * k
                        if abs(trial[g]) > 96:
                            continue
                        c = cost(trial)
                        if c < best - ALIGN_STEP_GAIN * f0:
                            pos, best, moved = trial, c, True
        self.align_misfit = (f0, best)
        if not best <= ALIGN_GAIN * f0:
            return {}
        return {g: (float(lat[0] * pos[g] * fine), float(lat[1] * pos[g] * fine), float(lat[2] * pos[g] * fine))
                for g in groups if pos[g]}

    def _misfit_image(self, B: list[np.ndarray], Ei: list[np.ndarray], scored: np.ndarray) -> float:
        """How badly this model explains the captures ``B`` (luminance images) with the indirect
        light ``Ei`` (images) held: per pixel of ``scored``, the relative squared misfit of the
        best reflectance over the captures (capped at ``SNAP_CAP``; a pixel the model no longer
        covers counts the cap), summed."""
        H, W = self.cam.height, self.cam.width
        b2 = np.zeros((H, W))
        sbs = np.zeros((H, W))
        sss = np.zeros((H, W))
        for (_name, _p, lights), b, ei in zip(self.captures, B, Ei, strict=True):
            s = ei.copy()
            s[self.cover] += luminance(np.sum([np.outer(self._geometry(L)[0], L.rgb) for L in lights], axis=0))
            u = np.ones((H, W), bool)
            u[self.cover] = ~self._in_view_of_lights(lights)
            b2 += np.where(u, b * b, 0.0)
            sbs += np.where(u, b * s, 0.0)
            sss += np.where(u, s * s, 0.0)
        e = np.where(self.cover, np.minimum(_misfit(b2, sbs, sss, SNAP_CAP), SNAP_CAP), SNAP_CAP)
        return float(e[scored].sum())

    @classmethod
    def aligned(cls, directory: str | Path, **kw: Any) -> Room:
        """The room with its objects moved where the captures put them (:meth:`align`)."""
        room = cls(directory, **kw)
        offsets = room.align()
        if not offsets:
            return room
        out = cls(directory, offsets=offsets, **kw)
        out.align_misfit = room.align_misfit
        return out

    def use_reflectance(self, reflectance: np.ndarray, confidence: np.ndarray,
                        source: np.ndarray | None = None) -> None:
        """Take a recovered reflectance (H, W, 3) and confidence (H, W) (``reflectance.exr``,
        ``confidence.exr`` of :meth:`recover`) instead of recovering again, and the pixel whose
        geometry shades each pixel (``source``: (H, W, >= 2) row and column, :meth:`source_image`,
        ``shading_source.exr``; default: each its own)."""
        H, W = self.cam.height, self.cam.width
        r, c = np.asarray(reflectance, np.float64), np.asarray(confidence, np.float64)
        if r.shape[:2] != (H, W) or c.shape[:2] != (H, W):
            raise InputError(f"reflectance and confidence must be {W} x {H} (camera.json), got "
                             f"{r.shape[1]} x {r.shape[0]}", param="reflectance")
        self.src = np.arange(len(self.X))
        if source is not None:
            sr = np.asarray(source, np.float64)
            if sr.shape[:2] != (H, W) or sr.ndim != 3 or sr.shape[2] < 2:
                raise InputError(f"shading source must be {W} x {H} x 2 (camera.json), got {sr.shape}",
                                 param="shading_source")
            idx = self._pixel_index()
            rc = np.rint(np.nan_to_num(sr[self.cover][:, :2], nan=-1.0)).astype(np.int64)
            ok = (rc[:, 0] >= 0) & (rc[:, 0] < H) & (rc[:, 1] >= 0) & (rc[:, 1] < W)
            j = np.full(len(self.X), -1)
            j[ok] = idx[rc[ok, 0], rc[ok, 1]]
            self.src = np.where(j >= 0, j, self.src)
        self.snapped = int((self.src != np.arange(len(self.X))).sum())
        rho = np.nan_to_num(r[self.cover][:, :3]).clip(0, None)
        conf = np.nan_to_num(c[self.cover] if c.ndim == 2 else c[self.cover][:, 0]).clip(0, None)
        rho_group = self._group_reflectance(rho, conf, np.full((len(self.group_names), 3), 0.5))
        self._set_patch_reflectance(rho, conf, rho_group)
        self.reflectance, self.confidence = rho, conf

    def _group_reflectance(self, rho: np.ndarray, conf: np.ndarray, prior: np.ndarray) -> np.ndarray:
        """Each group's median reflectance over its trusted pixels (``prior`` where it has none):
        what the patches the camera does not see take."""
        out = prior.copy()
        for g in range(len(self.group_names)):
            sel = (self.group == g) & (conf > 0)
            if sel.any():
                out[g] = np.median(rho[sel], axis=0)
        return out

    def _set_patch_reflectance(self, rho: np.ndarray, conf: np.ndarray, rho_group: np.ndarray) -> None:
        P = len(self.f)
        pr = np.zeros((P, 3))
        cw = np.bincount(self.patch, conf, minlength=P)
        for ch in range(3):
            pr[:, ch] = np.bincount(self.patch, rho[:, ch] * conf, minlength=P)
        ok = cw > 0
        pr[ok] /= cw[ok, None]
        pr[~ok] = rho_group[self.fgroup[~ok]]
        self.patch_reflectance = pr

    def source_image(self) -> np.ndarray:
        """(H, W, 3) float32: row and column of the pixel whose geometry shades each pixel
        (:meth:`_snap`), then 0; -1 where the camera sees no geometry."""
        img = np.full((self.cam.height, self.cam.width, 3), -1.0, np.float32)
        yy, xx = np.nonzero(self.cover)
        img[self.cover] = np.stack([yy[self.src], xx[self.src], np.zeros(len(self.src))], axis=1)
        return img

    def confidence_image(self) -> np.ndarray:
        img = np.zeros((self.cam.height, self.cam.width), np.float32)
        if self.confidence is not None:
            img[self.cover] = self.confidence
        return img

    def _filter_confidence(self, w: np.ndarray) -> np.ndarray:
        """The paper's confidence filter: ``K = min(K, kappa)``, ``kappa`` the 5 x 5 mean of the
        5 x 5 minimum of ``K`` (over the pixels that see the room), so confidence falls off
        towards a shadow's or a surface's edge, where an approximate model is most likely wrong."""
        from numpy.lib.stride_tricks import sliding_window_view

        H, W = self.cam.height, self.cam.width
        img = np.full((H + 4, W + 4), np.inf)
        img[2:-2, 2:-2][self.cover] = w
        kmin = sliding_window_view(img, (5, 5)).min(axis=(2, 3))          # (H, W)
        val = np.where(np.isfinite(kmin) & self.cover, kmin, 0.0)
        cnt = np.zeros((H + 4, W + 4))
        acc = np.zeros((H + 4, W + 4))
        cnt[2:-2, 2:-2] = self.cover
        acc[2:-2, 2:-2] = val
        s_acc = sliding_window_view(acc, (5, 5)).sum(axis=(2, 3))
        s_cnt = sliding_window_view(cnt, (5, 5)).sum(axis=(2, 3))
        kappa = (s_acc / np.maximum(s_cnt, 1.0))[self.cover]
        return np.asarray(np.minimum(w, kappa))

    def _refill_doubtful(self, rho: np.ndarray, conf: np.ndarray) -> np.ndarray:
        """Pixels whose confidence is under ``DOUBT`` of their surface's median (edges of an
        approximate model, what no capture lit) take the surface's confident reflectance around
        them (a normalised convolution), blended by confidence: ``(c rho + c_ref fill) / (c + c_ref)``."""
        H, W = self.cam.height, self.cam.width
        flat = np.flatnonzero(self.cover)
        out = rho.copy()
        for g in np.unique(self.group):
            sel = self.group == g
            cref = DOUBT * float(np.median(conf[sel]))
            if cref <= 0:
                continue
            low = sel & (conf < cref)
            src = sel & (conf >= cref)
            if not low.any() or not src.any():
                continue
            fill = _normalised_fill((H, W), flat[src], rho[src], conf[src], flat[low], rho[low])
            c = conf[low, None]
            out[low] = (c * rho[low] + cref * fill) / (c + cref)
        return out

    def _smooth(self, rho: np.ndarray, conf: np.ndarray) -> np.ndarray:
        """3 x 3 confidence-weighted smoothing within each group (the paper's last filter)."""
        H, W = self.cam.height, self.cam.width
        img = np.zeros((H, W, 3))
        cf = np.zeros((H, W))
        gr = np.full((H, W), -1)
        img[self.cover], cf[self.cover], gr[self.cover] = rho, conf, self.group
        acc = np.zeros_like(img)
        wsum = np.zeros((H, W))
        for dy in (-1, 0, 1):
            for dx in (-1, 0, 1):
                si = np.roll(np.roll(img, dy, 0), dx, 1)
                sc = np.roll(np.roll(cf, dy, 0), dx, 1)
                sg = np.roll(np.roll(gr, dy, 0), dx, 1)
                w = np.where(sg == gr, sc, 0.0)
                acc += w[..., None] * si
                wsum += w
        out = np.where(wsum[..., None] > 0, acc / np.maximum(wsum, 1e-300)[..., None], img)
        return np.asarray(out[self.cover])

    def _image(self, per_pixel: np.ndarray) -> np.ndarray:
        img = np.zeros((self.cam.height, self.cam.width, 3), np.float32)
        img[self.cover] = per_pixel
        return img

    # ---- relighting ----------------------------------------------------------------------------
    def render(self, lights: list[Light], where: str | Path = "lights",
               objects: list[VirtualObject] | tuple[VirtualObject, ...] = (),
               remove: list[str] | tuple[str, ...] = ()) -> np.ndarray:
        """The room (H, W, 3) radiance under ``lights`` with the recovered reflectance, with
        ``objects`` inserted (their shadows on the room, their light on it and their own shading)
        or the room.obj groups ``remove`` taken out (what they hid refilled); ``where`` names the
        edit's file in errors (EDITS.json). Sets ``render_cover``: the pixels it shaded."""
        if self.reflectance is None or self.patch_reflectance is None:
            self.recover()
        if self.reflectance is None or self.patch_reflectance is None:
            raise InputError("no reflectance: recover() first", param="reflectance")
        for L in lights:
            self._check_light(L, Path(where))
        self.object_mask = None
        self.render_cover = self.cover
        if objects and remove:
            raise InputError(f"{where}: insert objects or remove groups, not both in one edit", param="remove")
        if remove:
            unknown = [n for n in remove if n not in self.group_names]
            if unknown:
                raise InputError(f"{where}: no group {unknown[0]!r} in room.obj (groups: "
                                 f"{', '.join(n for n in self.group_names if n != 'default')})", param="remove")
            return self._render_removed(lights, [self.group_names.index(n) for n in remove])
        if objects:
            img = self._render_with(lights, list(objects))
            assert self.object_mask is not None
            self.render_cover = self.cover | self.object_mask
            return img
        # light is linear: per light geometry (position, radius), the irradiance per watt of each
        # channel, direct + indirect through the radiosity solve, is cached; a power change is a sum
        key = self.patch_reflectance.tobytes()
        if self._unit_key != key:
            self._unit, self._unit_key = {}, key
        acc = np.zeros((len(self.X), 3))
        for L in lights:
            geo = Light(L.position, L.radius, (1.0, 1.0, 1.0))
            u = self._unit.get(geo)
            if u is None:
                gp, gq = self._geometry(geo)
                u = self._unit[geo] = gp[:, None] + self._indirect(np.repeat(gq[:, None], 3, axis=1),
                                                                    self.patch_reflectance)
            acc += u * np.asarray(L.rgb)
        return self._image(self.reflectance / math.pi * acc[self.src])

    def _render_with(self, lights: list[Light], objects: list[VirtualObject]) -> np.ndarray:
        """:meth:`render` with virtual objects (Loscos et al. 1999, section 5: a virtual object
        casts shadows on real surfaces and takes part in the light exchange). Only what the
        objects can change is recomputed (the paper's shaft idea, with the objects' bounding
        sphere as the shaft's end): a pixel's or patch's direct light from a lamp only where the
        segment to the lamp passes the sphere, a form factor only where the ray between patch
        centres does. The objects join the radiosity solve as clusters of their faces (a k^3
        grid times the six normal directions: :func:`_clusters`): the room's patches see them
        (point-to-disc form factors, one visibility ray), they see the room (polygon form
        factors, one ray each); the objects' light on themselves is left out."""
        from hostlink.relight.precompute import build_embree

        assert self.reflectance is not None
        assert self.patch_reflectance is not None
        ov = np.concatenate([o.vertices for o in objects])
        base = np.cumsum([0] + [len(o.vertices) for o in objects])
        of = np.concatenate([o.faces + base[k] for k, o in enumerate(objects)])
        falb = np.concatenate([np.repeat(np.asarray(o.albedo, np.float64)[None], len(o.faces), axis=0) for o in objects])
        if not (np.isfinite(ov).all() and len(of)):
            raise InputError("a virtual object has no faces or non-finite vertices", param="objects")
        es = build_embree([(self.v, self.f), (ov, of)])
        c_o = (ov.min(axis=0) + ov.max(axis=0)) / 2
        r_o = float(np.linalg.norm(ov - c_o, axis=1).max())
        # the camera: which covered pixels now show an object (nearer than the room)
        tri_o, bary_o = _raster_cv(self.cam, ov, of)
        H, W = self.cam.height, self.cam.width
        room_z = np.full((H, W), np.inf)
        room_z[self.cover] = (self.X @ self.cam.R.T + self.cam.t)[:, 2]
        hit = tri_o >= 0
        Xo_all = np.einsum("pk,pkj->pj", bary_o[hit].astype(np.float64), ov[of[tri_o[hit]]])
        zo = (Xo_all @ self.cam.R.T + self.cam.t)[:, 2]
        front = zo < room_z[hit] * (1 - 1e-6)
        obj_mask = np.zeros((H, W), bool)
        obj_mask.flat[np.flatnonzero(hit)[front]] = True
        t_obj = tri_o[obj_mask]
        Xo = np.einsum("pk,pkj->pj", bary_o[obj_mask].astype(np.float64), ov[of[t_obj]])
        a, b, c = (ov[of[:, j]] for j in range(3))
        fn = np.cross(b - a, c - a)
        fn /= np.maximum(np.linalg.norm(fn, axis=1, keepdims=True), 1e-300)
        No = fn[t_obj]
        No = np.where((np.einsum("ij,ij->i", No, self.cam.center - Xo) < 0)[:, None], -No, No)
        label, cc, cn, ca = _clusters(ov, of)
        calb = np.stack([np.bincount(label, falb[:, j] * 1.0, minlength=len(cc)) for j in range(3)], 1) \
            / np.maximum(np.bincount(label, minlength=len(cc)), 1)[:, None]
        # direct light, each lamp: cached unoccluded-by-objects terms, re-traced inside the shaft
        P = len(self.f)
        Ed_pix = np.zeros((len(self.X), 3))
        Ed_patch = np.zeros((P, 3))
        Ed_c = np.zeros((len(cc), 3))
        Ed_o = np.zeros((len(Xo), 3))
        for L in lights:
            _, gq, gp, gs = self._geometry_parts(L)
            gp, gq, gs = gp.copy(), gq.copy(), gs.copy()
            lc, reach = np.asarray(L.position), r_o + L.radius
            sp = np.flatnonzero(_near_segment(self.X, lc, c_o, reach))
            gp[sp] = self._irradiance(L, self.X[sp], self.N[sp], es)
            ss = np.flatnonzero(_near_segment(self.fp.X, lc, c_o, reach))
            gs[ss] = self._irradiance(L, self.fp.X[ss], self.fp.N[ss], es)
            gp = self.fp.pixels(gp, gs)
            sq = np.flatnonzero(_near_segment(self.pc, lc, c_o, reach))
            gq[sq] = self._irradiance(L, self.pc[sq], self.pn[sq], es)
            rgb = np.asarray(L.rgb)
            Ed_pix += np.outer(gp, rgb)
            Ed_patch += np.outer(gq, rgb)
            Ed_c += np.outer(self._irradiance(L, cc, cn, es), rgb)
            Ed_o += np.outer(self._irradiance(L, Xo, No, es), rgb)
        # form factors: the room's own, blocked where an object stands between patch centres
        from hostlink.room.kernels import gather_room_light, near_pairs

        F = self.form_factors()
        if self._pairs is None:
            self._pairs = tuple(np.ascontiguousarray(x, np.int64) for x in np.nonzero(F > 0))
        ri, ci = self._pairs
        near = np.zeros(len(ri), np.bool_)
        near_pairs(self.pc, ri, ci, c_o, r_o, near)
        ri, ci = ri[near], ci[near]
        if len(ri):      # the blocked links, kept apart: F itself is not copied
            w = self.pc[ci] - self.pc[ri]
            dist = np.linalg.norm(w, axis=1)
            blocked = self._occluded(self.pc[ri] + self.eps * self.pn[ri], w / dist[:, None], dist - 2 * self.eps, es)
            ri, ci = ri[blocked], ci[blocked]
        cut = np.asarray(F[ri, ci], np.float64)
        # room patch -> cluster (a disc of the cluster's area) and cluster -> room patch (polygon)
        tgt = cc
        w = tgt[None] - self.pc[:, None]                                   # (P, Q, 3)
        d2 = np.einsum("pqk,pqk->pq", w, w)
        dist = np.sqrt(d2)
        wd = w / dist[..., None]
        cos_i = np.einsum("pqk,pk->pq", wd, self.pn)
        cos_j = -np.einsum("pqk,qk->pq", wd, cn)
        Frc = np.where((cos_i > 0) & (cos_j > 0), ca[None] * cos_i * cos_j / (math.pi * d2 + ca[None]), 0.0)
        pi_, qi = np.nonzero(Frc > 0)
        if len(pi_):
            occ = self._occluded(self.pc[pi_] + self.eps * self.pn[pi_], wd[pi_, qi], dist[pi_, qi] * (1 - 1e-3), es)
            Frc[pi_[occ], qi[occ]] = 0.0
        # each cluster's view of the room: Lambert's vector per patch (the form factor to any
        # normal, for the object's pixels) and one visibility ray per patch facing the cluster
        G = self._polygon_ff_vectors(tgt)                                   # (Q, P, 3)
        vis = cos_i.T > 0
        qj, pj = np.nonzero(vis)
        if len(qj):
            occ = self._occluded(tgt[qj], -wd[pj, qj], dist[pj, qj] * (1 - 1e-3), es)
            vis[qj[occ], pj[occ]] = False
        Fcr = np.where(vis & (cos_j.T > 0), np.maximum(np.einsum("qpk,qk->qp", G, cn), 0.0), 0.0)
        if self._F_rows is None:
            self._F_rows = F.sum(axis=1, dtype=np.float64)
        tot = self._F_rows - np.bincount(ri, cut, minlength=P) + Frc.sum(axis=1)   # a hemisphere at most
        scale = 1.0 / np.maximum(tot, 1.0)
        Frc *= scale[:, None]
        Fcr /= np.maximum(Fcr.sum(axis=1, keepdims=True), 1.0)
        Frc, Fcr = Frc.astype(np.float32), Fcr.astype(np.float32)

        def room_light(B: np.ndarray) -> np.ndarray:     # (F without the blocked links) @ B, scaled
            out = _mv(F, B)
            for ch in range(3):
                out[:, ch] -= np.bincount(ri, cut * B[ci, ch], minlength=P)
            return out * scale[:, None]

        # radiosity over the room's patches and the objects' clusters (Jacobi)
        rho = self.patch_reflectance
        Br = rho / math.pi * Ed_patch
        if self._last_B is not None and self._last_B[0] == tuple(lights):
            Br = self._last_B[1]          # the same lamps: start from the last frame's solution
        Bc = calb / math.pi * Ed_c
        for _ in range(60):
            nr = rho / math.pi * (Ed_patch + math.pi * (room_light(Br) + _mv(Frc, Bc)))
            nc = calb / math.pi * (Ed_c + math.pi * _mv(Fcr, Br))
            done = max(float(np.abs(nr - Br).max()), float(np.abs(nc - Bc).max())) <= \
                1e-5 * max(float(np.abs(nr).max()), float(np.abs(nc).max()), 1e-300)
            Br, Bc = nr, nc
            if done:
                break
        self._last_B = (tuple(lights), Br)
        E_pix = (Ed_pix + math.pi * self.fp.gather(room_light(Br) + _mv(Frc, Bc), self.patch))[self.src]
        img = self._image(self.reflectance / math.pi * E_pix)
        # the object's pixels: their own normals against their cluster's view of the room
        E_o = np.empty((len(No), 3))
        gather_room_light(np.ascontiguousarray(No), np.ascontiguousarray(label[t_obj], np.int64), G, vis,
                          np.ascontiguousarray(Br, np.float64), E_o)
        E_o = Ed_o + math.pi * E_o
        img[obj_mask] = (falb[t_obj] / math.pi * E_o).astype(np.float32)
        self.object_mask = obj_mask
        return img

    def _render_removed(self, lights: list[Light], gids: list[int]) -> np.ndarray:
        """:meth:`render` with the faces of groups ``gids`` taken out of the room (the paper's
        object removal). The camera sees what they hid: a surface the captures never showed
        there, so its reflectance is refilled from the same surface around it (a normalised
        convolution of that surface's confident pixels at the finest scale that reaches the
        hole: a smooth fill, not the paper's texture synthesis). Only what the removal changes is recomputed, with the
        removed faces' bounding sphere as the shaft's end: a lamp's light where its segment to a
        pixel or patch passes the sphere (their shadows go), the form factors of links passing
        it (those the removed faces blocked come back, exact polygon form factors and a ray)."""
        from hostlink.relight.precompute import build_embree

        assert self.reflectance is not None
        assert self.patch_reflectance is not None
        keep = ~np.isin(self.fgroup, gids)
        kidx = np.flatnonzero(keep)
        gone = self.v[np.unique(self.f[~keep])]
        c_b = (gone.min(axis=0) + gone.max(axis=0)) / 2
        r_b = float(np.linalg.norm(gone - c_b, axis=1).max())
        es = build_embree([(self.v, self.f[keep])])
        # the camera's new view: pixels that show the same patch as before keep their reflectance
        tri, bary = _raster_cv(self.cam, self.v, self.f[keep])
        cover = tri >= 0
        patch = kidx[tri[cover]]
        X = np.einsum("pk,pkj->pj", bary[cover].astype(np.float64), self.v[self.f[patch]])
        N = self.pn[patch]
        N = np.where((np.einsum("ij,ij->i", N, self.cam.center - X) < 0)[:, None], -N, N)
        H, W = self.cam.height, self.cam.width
        was = self._pixel_index()[cover]
        same = (was >= 0) & (self.patch[np.maximum(was, 0)] == patch)
        rho = np.zeros((len(patch), 3))
        rho[same] = self.reflectance[was[same]]
        revealed = ~same
        if revealed.any():
            conf = np.zeros(len(patch))
            conf[same] = self.confidence[was[same]] if self.confidence is not None else 1.0
            grp = self.fgroup[patch]
            flat = np.flatnonzero(cover)
            for g in np.unique(grp[revealed]):
                rows = revealed & (grp == g)
                src = same & (grp == g) & (conf > 0)
                if not src.any():      # a surface never seen at all: its group's reflectance
                    rho[rows] = self.patch_reflectance[patch[rows]]
                    continue
                rho[rows] = _normalised_fill((H, W), flat[src], rho[src], conf[src], flat[rows],
                                             self.patch_reflectance[patch[rows]])
        # direct light: the cached terms, re-traced inside the shafts to the removed faces
        fp = _footprints(self.cam, cover, X, N, self.fgroup[patch], es, kidx, self.pn)
        Ed_pix = np.zeros((len(patch), 3))
        Ed_patch = np.zeros((len(kidx), 3))
        for L in lights:
            _, gq, gc, _ = self._geometry_parts(L)
            g_pix = np.where(same, gc[np.maximum(was, 0)], 0.0)
            lc, reach = np.asarray(L.position), r_b + L.radius
            redo = np.flatnonzero(~same | _near_segment(X, lc, c_b, reach))
            g_pix[redo] = self._irradiance(L, X[redo], N[redo], es)
            g_pix = fp.pixels(g_pix, self._irradiance(L, fp.X, fp.N, es))   # the new view's edges
            g_q = gq[kidx].copy()
            sq = np.flatnonzero(_near_segment(self.pc[kidx], lc, c_b, reach))
            g_q[sq] = self._irradiance(L, self.pc[kidx[sq]], self.pn[kidx[sq]], es)
            Ed_pix += np.outer(g_pix, L.rgb)
            Ed_patch += np.outer(g_q, L.rgb)
        # form factors among the kept patches; links passing the removed faces' sphere redone
        F = self.form_factors()[np.ix_(kidx, kidx)].astype(np.float32)
        pc, pn = self.pc[kidx], self.pn[kidx]
        for s0 in range(0, len(kidx), 256):
            rows = np.arange(s0, min(len(kidx), s0 + 256))
            w = pc[None] - pc[rows, None]
            d = np.linalg.norm(w, axis=-1)
            t = np.clip(np.einsum("rpk,rk->rp", w, c_b - pc[rows]) / np.maximum(d * d, 1e-300), 0, 1)
            near = np.linalg.norm(pc[rows, None] + t[..., None] * w - c_b, axis=-1) <= r_b
            wd = w / np.maximum(d, 1e-300)[..., None]
            near &= (np.einsum("rpk,rk->rp", wd, pn[rows]) > 0) & (np.einsum("rpk,pk->rp", wd, pn) < 0)
            near[np.arange(len(rows)), rows] = False
            ri, ci = np.nonzero(near)
            if not len(ri):
                continue
            ff = self._polygon_ff_at(pc[rows], pn[rows])[:, kidx][ri, ci]
            occ = self._occluded(pc[rows[ri]] + self.eps * pn[rows[ri]], wd[ri, ci], d[ri, ci] - 2 * self.eps, es)
            F[rows[ri], ci] = np.where(occ, 0.0, ff)
        F /= np.maximum(F.sum(axis=1, dtype=np.float64), 1.0).astype(np.float32)[:, None]
        B = self._solve(Ed_patch, self.patch_reflectance[kidx], iters=60, F=F)
        Q = np.zeros((len(self.f), 3))
        Q[kidx] = _mv(F, B)
        E = Ed_pix + math.pi * fp.gather(Q, patch)
        # pixels that showed the same patch before keep the geometry that explained their captures
        # (:meth:`_snap`) where that pixel is still shown as before
        new_of_old = np.full(len(self.X), -1)
        new_of_old[was[same]] = np.flatnonzero(same)
        take = new_of_old[self.src[was[same]]]
        rows = np.flatnonzero(same)[take >= 0]
        E[rows] = E[take[take >= 0]]
        out = np.zeros((H, W, 3), np.float32)
        out[cover] = rho / math.pi * E
        self.render_cover = cover
        return out

    def true_groups(self) -> np.ndarray:
        """(H, W) group index per pixel, -1 where there is no geometry (for tests and tools)."""
        g = np.full((self.cam.height, self.cam.width), -1, np.int64)
        g[self.cover] = self.group
        return g
