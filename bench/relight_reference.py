"""An independent brute-force reference for relighting: Embree rays and its own shading loop.

It shares no function with the relighting it checks (``lightprobe.hostlink.relight``): not its
direction tree, its leaf lighting, its ray helpers nor its BRDF kernels. The lighting is its own
quadrature of the equirect map (each pixel, or each sub-pixel of a small map, a direction at its
centre carrying radiance x its exact solid angle, CONVENTIONS.md); visibility is one Embree
occlusion ray per (vertex, direction) above the vertex's horizon; the BRDFs are written here from
their formulas (the scene file's material types):

- lambert: ``kd / pi``
- phong: ``kd / pi + ks (p + 2) / (2 pi) max(r . wo, 0)^p``, ``r`` the mirror of ``w`` about ``n``
- blinn-phong: ``kd / pi + ks (p + 8) / (8 pi) max(n . h, 0)^p``, ``h`` the half vector
- ward (isotropic, Walter's normalisation): ``kd / pi + ks exp(-tan^2 d / a^2) /
  (4 pi a^2 sqrt(cos_i cos_o))``, the cosines floored at 0.01 as the scene format defines

Outgoing radiance towards the eye: ``B = sum_j L_j V_j max(n . w_j, 0) f_r(w_j, w_o)``.

Cost: one ray per (vertex, direction above its horizon): ~16k rays per vertex at the default
quadrature (2^15 directions), ~1 s per 100 vertices on 2 cores. Dtype: float64 sums.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np

__all__ = ["QUADRATURE_HEIGHT", "brute_force_radiance", "equirect_quadrature", "function_quadrature",
           "relighter_reference"]

QUADRATURE_HEIGHT = 128  # 128 x 256 = 2^15 directions, the resolution the cuts work at
_LAMBERT, _PHONG, _BLINN, _WARD = 0, 1, 2, 3  # the packed material row's type codes (scene format)


def equirect_quadrature(maps: Sequence[np.ndarray], height: int = QUADRATURE_HEIGHT
                        ) -> tuple[np.ndarray, np.ndarray]:
    """(directions (maps, N, 3), radiance x solid angle (maps, N, 3)) of equirect maps (H, 2H, 3)
    on a ``height x 2 height`` grid of cells. A cell's energy is the exact integral of the map
    over it (its pixels, or its share of a pixel when the map is smaller); its direction is the
    luminance-weighted centroid of its pixels' centre directions (the cell centre when dark), so a
    sun or a lamp smaller than a cell lies where the map has it, not at a grid point. ``height``
    and H must divide one another; NaN, infinite or negative pixels count as 0."""
    h0 = maps[0].shape[0]
    if any(m.shape != (h0, 2 * h0, 3) for m in maps):
        raise ValueError("maps must share one (H, 2H, 3) shape")
    if h0 % height and height % h0:
        raise ValueError(f"map height {h0} and quadrature height {height} must divide one another")
    fine = max(h0, height)
    k = fine // height
    edges = np.cos(np.linspace(0.0, np.pi, fine + 1))
    omega_row = (np.pi / fine) * (edges[:-1] - edges[1:])                # exact, per fine pixel
    theta = (np.arange(fine) + 0.5) * (np.pi / fine)
    phi = (np.arange(2 * fine) + 0.5) * (np.pi / fine)
    t, p = np.meshgrid(theta, phi, indexing="ij")
    fine_dirs = np.stack([np.sin(t) * np.sin(p), np.cos(t), -np.sin(t) * np.cos(p)], axis=-1)
    centre = fine_dirs.reshape(height, k, 2 * height, k, 3).sum(axis=(1, 3))
    lum_w = np.array([0.2126, 0.7152, 0.0722])                           # Rec. 709
    all_dirs, all_light = [], []
    for m in maps:
        x = np.nan_to_num(np.asarray(m, np.float64), nan=0.0, posinf=0.0, neginf=0.0).clip(0.0)
        if h0 < height:
            x = x.repeat(height // h0, axis=0).repeat(height // h0, axis=1)
        e = x * omega_row[:, None, None]
        w = e @ lum_w
        light = e.reshape(height, k, 2 * height, k, 3).sum(axis=(1, 3))
        moment = (fine_dirs * w[..., None]).reshape(height, k, 2 * height, k, 3).sum(axis=(1, 3))
        d = np.where((np.linalg.norm(moment, axis=-1) > 0)[..., None], moment, centre)
        all_dirs.append((d / np.linalg.norm(d, axis=-1, keepdims=True)).reshape(-1, 3))
        all_light.append(light.reshape(-1, 3))
    return np.stack(all_dirs), np.stack(all_light)


def function_quadrature(radiance: Sequence[Callable[[np.ndarray], np.ndarray]], height: int = QUADRATURE_HEIGHT
                        ) -> tuple[np.ndarray, np.ndarray]:
    """The same for radiance given as functions of direction ((N, 3) -> (N, 3)), e.g. a set of
    spherical Gaussians: each cell of the ``height x 2 height`` grid a direction at its centre
    carrying the function's value there times the cell's exact solid angle."""
    edges = np.cos(np.linspace(0.0, np.pi, height + 1))
    omega = np.repeat((np.pi / height) * (edges[:-1] - edges[1:]), 2 * height)
    theta = (np.arange(height) + 0.5) * (np.pi / height)
    phi = (np.arange(2 * height) + 0.5) * (np.pi / height)
    t, p = np.meshgrid(theta, phi, indexing="ij")
    dirs = np.stack([np.sin(t) * np.sin(p), np.cos(t), -np.sin(t) * np.cos(p)], axis=-1).reshape(-1, 3)
    light = np.stack([np.asarray(f(dirs), np.float64) * omega[:, None] for f in radiance])
    return np.broadcast_to(dirs, (len(radiance), *dirs.shape)), light


def _embree(pos: np.ndarray, faces: np.ndarray):  # type: ignore[no-untyped-def]
    from embreex import rtcore_scene as rtcs
    from embreex.mesh_construction import TriangleMesh

    scene = rtcs.EmbreeScene()
    TriangleMesh(scene, np.ascontiguousarray(pos[faces], np.float32))
    return scene


def _specular(kind: int, p: float, cos_i: np.ndarray, cos_o: float, w_dot_o: np.ndarray) -> np.ndarray:
    """The specular lobe (multiplies ks) for one vertex (``cos_o = n . wo``) over its directions."""
    if kind == _PHONG:
        r_dot_o = 2.0 * cos_i * cos_o - w_dot_o                           # (2 (n.w) n - w) . wo
        return (p + 2.0) / (2.0 * np.pi) * np.maximum(r_dot_o, 0.0) ** p
    half_len = np.sqrt(np.maximum(2.0 + 2.0 * w_dot_o, 0.0))
    n_dot_h = np.where(half_len > 1e-12, (cos_i + cos_o) / np.where(half_len > 1e-12, half_len, 1.0), 0.0)
    if kind == _BLINN:
        return (p + 8.0) / (8.0 * np.pi) * np.maximum(n_dot_h, 0.0) ** p
    if kind == _WARD:
        if cos_o <= 0:
            return np.zeros_like(cos_i)
        ch2 = np.maximum(n_dot_h, 1e-12) ** 2
        lobe = np.exp(-(1.0 - ch2) / ch2 / (p * p)) / (
            4.0 * np.pi * p * p * np.sqrt(np.maximum(cos_i, 1e-2) * max(cos_o, 1e-2)))
        return np.where((n_dot_h > 0) & (cos_i > 0), lobe, 0.0)
    return np.zeros_like(cos_i)


def brute_force_radiance(pos: np.ndarray, faces: np.ndarray, normals: np.ndarray, matid: np.ndarray,
                         mats: np.ndarray, dirs: np.ndarray, light: np.ndarray, eye: np.ndarray,
                         vidx: np.ndarray | None = None, eps: float | None = None) -> np.ndarray:
    """(maps, n, 3) radiance towards ``eye`` of the vertices ``vidx`` (default all) of the mesh
    (``pos``, ``faces``; every triangle occludes) with unit ``normals``, lit by ``light`` (maps, N,
    3) radiance x solid angle from ``dirs`` (maps, N, 3) (:func:`equirect_quadrature`). Material of
    vertex ``i``: the row ``mats[matid[i]]`` of the scene format (type code, kd rgb, ks rgb,
    exponent or Ward alpha). Shadow rays start ``eps`` off the surface along the normal (default
    1e-4 of the mesh's bounding-box diagonal)."""
    pos = np.asarray(pos, np.float64)
    if eps is None:
        eps = 1e-4 * float(np.linalg.norm(pos.max(axis=0) - pos.min(axis=0)))
    vidx = np.arange(len(pos)) if vidx is None else np.asarray(vidx, np.int64)
    dirs = np.asarray(dirs, np.float64)
    light = np.asarray(light, np.float64)
    scene = _embree(pos, np.asarray(faces))
    n_maps, n_dirs = light.shape[:2]
    flat_dirs = dirs.reshape(-1, 3)
    out = np.zeros((n_maps, len(vidx), 3))
    for t, i in enumerate(vidx):
        n = np.asarray(normals[i], np.float64)
        cos_i = flat_dirs @ n
        up = np.nonzero(cos_i > 0)[0]                                      # over all maps' directions
        origin = np.broadcast_to((pos[i] + eps * n).astype(np.float32), (up.size, 3))
        free = np.asarray(scene.run(np.ascontiguousarray(origin), np.ascontiguousarray(flat_dirs[up], np.float32),
                                    query="OCCLUDED")) != 0          # Embree: 0 = hit, -1 = free
        lit = up[free]
        wo = np.asarray(eye, np.float64) - pos[i]
        wo /= max(float(np.linalg.norm(wo)), 1e-12)
        row = mats[matid[i]]
        kind, kd, ks, p = int(row[0]), row[1:4], row[4:7], float(row[7])
        ci = cos_i[lit]
        spec = (_specular(kind, p, ci, float(n @ wo), flat_dirs[lit] @ wo) if kind != _LAMBERT
                else np.zeros_like(ci))
        f = (kd[None, :] / np.pi + ks[None, :] * spec[:, None]) * ci[:, None]   # f_r cos, per ray
        contrib = light.reshape(-1, 3)[lit] * f
        out[:, t] = np.stack([contrib[(lit // n_dirs) == mi].sum(axis=0) for mi in range(n_maps)])
    return out

def relighter_reference(rl, maps: Sequence[np.ndarray], eye: np.ndarray,  # type: ignore[no-untyped-def]
                        vidx: np.ndarray | None = None) -> np.ndarray:
    """:func:`brute_force_radiance` of a cut relighter's scene at its objects' current poses
    (``rl.positions()``, ``rl.normals()``, its materials) under equirect ``maps``."""
    dirs, light = equirect_quadrature(maps)
    return brute_force_radiance(rl.positions(), rl.pre.faces, rl.normals(), rl.matid, rl.mats, dirs, light,
                                eye, vidx)
