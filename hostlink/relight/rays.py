"""Rays against a scene's triangles, shared by every relighting method (cuts, SG, the room): the
Embree scene of a set of meshes, occlusion queries in batches, and the ray offset a scene needs."""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import numpy as np

from lightprobe.hostlink.relight.scene import Scene

__all__ = ["RAYS_PER_CALL", "build_embree", "occluded", "scene_eps"]

RAYS_PER_CALL = 1 << 20


def build_embree(meshes: list[tuple[np.ndarray, np.ndarray]]):  # type: ignore[no-untyped-def]
    """An Embree scene of the given (vertices, faces) meshes."""
    from embreex import rtcore_scene as rtcs
    from embreex.mesh_construction import TriangleMesh

    scene = rtcs.EmbreeScene()
    for v, f in meshes:
        TriangleMesh(scene, np.ascontiguousarray(v[f], np.float32))
    return scene


def occluded(scene, origins: np.ndarray, dirs: np.ndarray, threads: int = 2) -> np.ndarray:  # type: ignore[no-untyped-def]
    """Boolean occlusion per ray (Embree OCCLUDED returns 0 for a hit, -1 for free)."""
    o = np.ascontiguousarray(origins, np.float32)
    d = np.ascontiguousarray(dirs, np.float32)
    n = len(o)
    if n == 0:
        return np.zeros(0, bool)
    parts = max(1, min(threads, n // 4096))
    bounds = np.linspace(0, n, parts + 1).astype(int)
    if parts == 1:
        return np.asarray(scene.run(o, d, query="OCCLUDED")) == 0
    with ThreadPoolExecutor(parts) as ex:   # Embree releases the GIL
        res = list(ex.map(lambda k: np.asarray(scene.run(o[bounds[k]:bounds[k + 1]],
                                                         d[bounds[k]:bounds[k + 1]],
                                                         query="OCCLUDED")) == 0, range(parts)))
    return np.concatenate(res)


def scene_eps(scene: Scene) -> float:
    """Ray offset: 1e-4 of the scene's bounding-box diagonal."""
    allv = np.concatenate([o.mesh.vertices for o in scene.objects])
    return 1e-4 * float(np.linalg.norm(np.ptp(allv, axis=0)))
