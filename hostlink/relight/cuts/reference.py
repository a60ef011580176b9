"""Brute-force reference: the same 2^15 directions, full ray-cast visibility, the same BRDFs.

It isolates the error the cuts (clustering, VCF interpolation) introduce. Dtype: float64 sums.
"""

from __future__ import annotations

import numpy as np

from lightprobe.hostlink.relight.cuts.directions import leaf_directions
from lightprobe.hostlink.relight.cuts.kernels import shade_dense
from lightprobe.hostlink.relight.cuts.render import Relighter
from lightprobe.hostlink.relight.rays import build_embree, occluded, scene_eps

__all__ = ["brute_force_radiance", "reference_radiance"]


def reference_radiance(rl: Relighter, leaf_lights: np.ndarray, eye: np.ndarray,
                       vidx: np.ndarray | None = None, chunk: int = 64) -> np.ndarray:
    """(maps, n, 3) radiance towards ``eye`` for each leaf-light array in ``leaf_lights``
    (maps, 2^15, 3), with every object at its current pose (rotation and translation) occluding
    every vertex; normals rotate with their object."""
    return brute_force_radiance(rl.positions(), rl.pre.faces, rl.normals(), rl.matid, rl.mats,
                                scene_eps(rl.scene), leaf_lights, eye, vidx, chunk)


def brute_force_radiance(pos: np.ndarray, faces: np.ndarray, normals: np.ndarray, matid: np.ndarray,
                         mats: np.ndarray, eps: float, leaf_lights: np.ndarray, eye: np.ndarray,
                         vidx: np.ndarray | None = None, chunk: int = 64) -> np.ndarray:
    """The reference for any geometry (no precompute): (maps, n, 3) radiance towards ``eye`` of
    the vertices ``vidx`` of the mesh (``pos``, ``faces``), every triangle occluding, ``normals``,
    material rows ``mats[matid]``, rays offset by ``eps`` along the normal."""
    vidx = np.arange(len(pos)) if vidx is None else np.asarray(vidx, np.int64)
    es = build_embree([(pos, faces)])
    dirs = leaf_directions()
    L = np.ascontiguousarray(leaf_lights, np.float64).reshape(-1, dirs.shape[0], 3)
    out = np.zeros((L.shape[0], len(vidx), 3))
    for s in range(0, len(vidx), chunk):
        rows = vidx[s:s + chunk]
        n = normals[rows]
        cos = n @ dirs.T
        vi, di = np.nonzero(cos > 0)
        occ = occluded(es, pos[rows][vi] + eps * n[vi], dirs[di])
        vc = np.zeros_like(cos)
        vc[vi[~occ], di[~occ]] = cos[vi[~occ], di[~occ]]
        wo = np.asarray(eye, float) - pos[rows]
        wo /= np.maximum(np.linalg.norm(wo, axis=1, keepdims=True), 1e-12)
        res = np.zeros((L.shape[0], len(rows), 3))
        shade_dense(vc, rows, normals, wo, matid, mats, dirs, L, res)
        out[:, s:s + len(rows)] = res
    return out
