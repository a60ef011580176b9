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
:mod:`lightprobe.hostlink.relight.room.probes` (``lightprobe room lights``). Not built: texture synthesis; objects
turned or moved in depth by the alignment.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from lightprobe.core.errors import InputError
from lightprobe.hostlink.relight.room.alignment import AlignmentMixin
from lightprobe.hostlink.relight.room.io import CameraCV, Light, load_camera, load_lights
from lightprobe.hostlink.relight.room.item_buffer import (
    footprints,
    moved_groups,
    raster_cv,
    subdivide,
)
from lightprobe.hostlink.relight.room.radiosity import RadiosityMixin
from lightprobe.hostlink.relight.room.recovery import RecoveryMixin
from lightprobe.hostlink.relight.room.rendering import RenderingMixin

__all__ = ["Room"]


class Room(RadiosityMixin, RecoveryMixin, AlignmentMixin, RenderingMixin):
    """A photographed room: :meth:`recover` its reflectance, then :meth:`render` it under other
    lights. ``directory`` holds room.obj, camera.json and captures/ (see the module notes)."""

    def __init__(self, directory: str | Path, *, patch_size: float | None = None, light_samples: int = 16,
                 offsets: dict[str, Any] | None = None, camera: CameraCV | None = None) -> None:
        from lightprobe.hostlink.relight.rays import build_embree
        from lightprobe.hostlink.relight.scene import load_obj_groups

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
        verts = moved_groups(mesh.vertices, mesh.faces, fg, names, self.offsets, d / "room.obj")
        diag = float(np.linalg.norm(np.ptp(mesh.vertices, axis=0)))
        self.eps = 1e-4 * diag
        self.patch_size = float(patch_size or diag / 16)
        self.light_samples = int(light_samples)
        self.v, self.f, self.fgroup = subdivide(verts, mesh.faces, fg, self.patch_size)
        a, b, c = (self.v[self.f[:, k]] for k in range(3))
        cr = np.cross(b - a, c - a)
        self.area = 0.5 * np.linalg.norm(cr, axis=1)
        self.pn = cr / np.maximum(2 * self.area, 1e-300)[:, None]
        self.pc = (a + b + c) / 3
        self._es = build_embree([(self.v, self.f)])
        tri, bary = raster_cv(self.cam, self.v, self.f)
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
        self.fp = footprints(self.cam, self.cover, self.X, self.N, self.group, self._es, np.arange(len(self.f)), self.pn)
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
