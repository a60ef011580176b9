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

from lightprobe.hostlink.relight.room.alignment import RoomAlignment
from lightprobe.hostlink.relight.room.rendering import RoomRendering

__all__ = ["Room"]


class Room(RoomAlignment, RoomRendering):
    """A photographed room: :meth:`recover` its reflectance, then :meth:`render` it under other
    lights. ``directory`` holds room.obj, camera.json and captures/ (see the module notes)."""


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
