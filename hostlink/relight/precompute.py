"""Precomputation of self-visibility cuts (SVC) and visibility cut fields (VCF) with Embree.

* SVC, per vertex: leaf value ``V(x, w_j) max(0, n . w_j)`` over the 2^15 directions, cut at the
  integrated-SSE threshold ``tau`` (:func:`hostlink.relight.cuts.select_cut`). Occluders: all
  static geometry; for a movable object's vertices, the object itself plus the static geometry at
  its precompute pose (exact for the ground plane under translations parallel to it; other static
  objects' shadows on a moved object are those of the precompute pose: a stated approximation).
* VCF, per movable object: ``spheres`` concentric spheres with radii uniform in [inner r, outer r]
  (paper: 32 between 1.2 r and 10 r), ``6 grid^2`` points each (cube-map layout, paper: grid 32).
  Only directions inside the bounding cone (angle asin(r/d)) are traced; the rest are visible.
  Visibility is streamed point by point into lossless binary cuts.

Rays start at ``x + eps n`` with ``eps = 1e-4`` of the scene diagonal (Embree has no tnear).
Results are cached on disk, keyed by a SHA-256 over meshes, flags and parameters.

References
----------
K. Iwasaki et al., "Interactive relighting of captured illumination with visibility cuts",
Sec. V-A-1 (precomputation), Sec. VI (32 spheres, 6 x 32^2 points, 1.2 r .. 10 r).
"""

from __future__ import annotations

import hashlib
import os
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from hostlink.relight.cuts import binary_cut, quantize_cuts_u8, select_cut
from hostlink.relight.directions import LEAF_SOLID_ANGLE, NDIR, leaf_directions
from hostlink.relight.scene import Scene, vertex_normals

__all__ = [
    "CACHE_VERSION",
    "DEFAULT_TAU",
    "VCF",
    "Precomputed",
    "build_embree",
    "compute_vcf",
    "cube_points",
    "default_cache_dir",
    "occluded",
    "precompute",
    "scene_eps",
]

DEFAULT_TAU = 2e-5
CACHE_VERSION = 1
_RAYS_PER_CALL = 1 << 20


@dataclass
class VCF:
    """Visibility cut field of one movable object (binary cuts at sample points)."""
    center: np.ndarray          # (3,) bounding-sphere centre at the precompute pose
    radius: float
    radii: np.ndarray           # (K,) sphere radii
    grid: int
    offsets: np.ndarray         # (P+1,) int64 into heights / values
    heights: np.ndarray         # uint8
    values: np.ndarray          # uint8 0/1


@dataclass
class Precomputed:
    vertices: np.ndarray        # (N, 3) float64, precompute pose
    normals: np.ndarray         # (N, 3)
    object_id: np.ndarray       # (N,) int64 index into scene.objects
    faces: np.ndarray           # (F, 3) global vertex indices
    face_object: np.ndarray     # (F,)
    svc_offsets: np.ndarray     # (N+1,) int64
    svc_heights: np.ndarray     # uint8
    svc_values: np.ndarray      # float32: the u8 (default) or float16 stored values, decoded
    vcf: dict[int, VCF] = field(default_factory=dict)
    tau: float = DEFAULT_TAU
    seconds: float = 0.0
    cached: bool = False
    vcf_seconds: float = 0.0


def default_cache_dir() -> Path:
    """``$XDG_CACHE_HOME/lightprobe/relight`` or ``~/.cache/lightprobe/relight`` (read at call)."""
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "lightprobe" / "relight"


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


def cube_points(radii: np.ndarray, grid: int) -> np.ndarray:
    """(K * 6 * grid^2, 3) unit-sphere-scaled sample points: index ((k*6 + f)*grid + iy)*grid + ix,
    face f: major axis f // 2, sign +/- for f % 2 = 0/1, texel centres on the cube projected."""
    t = (np.arange(grid) + 0.5) / grid * 2 - 1
    ty, tx = np.meshgrid(t, t, indexing="ij")
    faces = []
    for f in range(6):
        a = f // 2
        p = np.zeros((grid, grid, 3))
        p[..., a] = 1.0 if f % 2 == 0 else -1.0
        p[..., (a + 1) % 3] = tx
        p[..., (a + 2) % 3] = ty
        faces.append(p.reshape(-1, 3))
    unit = np.concatenate(faces)
    unit /= np.linalg.norm(unit, axis=1, keepdims=True)
    return (radii[:, None, None] * unit[None]).reshape(-1, 3)


def _cache_key(scene: Scene, tau: float, vcf_cfg: tuple[int, int, float, float]) -> str:
    h = hashlib.sha256(f"v{CACHE_VERSION}|tau={tau!r}|vcf={vcf_cfg!r}".encode())
    for o in scene.objects:
        h.update(f"|{o.name}|{o.movable}|".encode())
        h.update(np.ascontiguousarray(o.mesh.vertices, np.float64).tobytes())
        h.update(np.ascontiguousarray(o.mesh.faces, np.int64).tobytes())
    return h.hexdigest()[:32]


def _svc_chunk(es, verts: np.ndarray, normals: np.ndarray, eps: float, tau: float,  # type: ignore[no-untyped-def]
               out: list[tuple[np.ndarray, np.ndarray]]) -> None:
    dirs = leaf_directions()
    cos = normals @ dirs.T                                   # (n, 2^15)
    vi, di = np.nonzero(cos > 0)
    origins = verts[vi] + eps * normals[vi]
    occ = occluded(es, origins, dirs[di])
    leaf = np.zeros_like(cos)
    leaf[vi[~occ], di[~occ]] = cos[vi[~occ], di[~occ]]
    for k in range(len(verts)):
        out.append(select_cut(leaf[k], tau, LEAF_SOLID_ANGLE))


def compute_vcf(mesh_v: np.ndarray, mesh_f: np.ndarray, cfg: tuple[int, int, float, float],
                tick: Callable[[int], None]) -> VCF:
    spheres, grid, inner, outer = cfg
    lo, hi = mesh_v.min(axis=0), mesh_v.max(axis=0)
    c = (lo + hi) / 2
    r = float(np.linalg.norm(mesh_v - c, axis=1).max())
    radii = np.linspace(inner * r, outer * r, spheres) if spheres > 1 else np.array([inner * r])
    pts = cube_points(radii, grid) + c
    es = build_embree([(mesh_v, mesh_f)])
    dirs = leaf_directions()
    hs: list[np.ndarray] = []
    vs: list[np.ndarray] = []
    step = max(1, _RAYS_PER_CALL // (NDIR // 4))
    for s in range(0, len(pts), step):
        chunk = pts[s:s + step]
        to_c = c - chunk
        d = np.linalg.norm(to_c, axis=1)
        cos_cone = np.where(d > r, np.sqrt(np.clip(1 - (r / np.maximum(d, 1e-12)) ** 2, 0, 1)), -2.0)
        cone = (to_c / d[:, None]) @ dirs.T >= cos_cone[:, None] - 1e-6   # bounding-cone culling
        pi, di = np.nonzero(cone)
        occ = occluded(es, chunk[pi], dirs[di])
        bounds = np.searchsorted(pi, np.arange(len(chunk) + 1))
        for k in range(len(chunk)):                         # stream point by point into cuts
            bits = np.ones(NDIR, np.uint8)
            a, b = bounds[k], bounds[k + 1]
            bits[di[a:b][occ[a:b]]] = 0
            h, v = binary_cut(bits)
            hs.append(h)
            vs.append(v)
        tick(len(chunk))
    lens = np.array([len(h) for h in hs], np.int64)
    return VCF(c, r, radii, grid, np.concatenate([[0], np.cumsum(lens)]),
               np.concatenate(hs), np.concatenate(vs))


def _progress(enabled: bool):  # type: ignore[no-untyped-def]
    from rich.console import Console
    from rich.progress import BarColumn, Progress, TextColumn, TimeRemainingColumn

    return Progress(TextColumn("{task.description}"), BarColumn(), TextColumn("{task.completed}/{task.total}"),
                    TimeRemainingColumn(), console=Console(stderr=True), disable=not enabled, transient=True)


def _gather(scene: Scene) -> tuple[np.ndarray, ...]:
    verts, norms, oid, faces, fobj = [], [], [], [], []
    base = 0
    for k, o in enumerate(scene.objects):
        verts.append(o.mesh.vertices)
        norms.append(vertex_normals(o.mesh))
        oid.append(np.full(len(o.mesh.vertices), k, np.int64))
        faces.append(o.mesh.faces + base)
        fobj.append(np.full(len(o.mesh.faces), k, np.int64))
        base += len(o.mesh.vertices)
    return (np.concatenate(verts), np.concatenate(norms), np.concatenate(oid),
            np.concatenate(faces), np.concatenate(fobj))


def scene_eps(scene: Scene) -> float:
    """Ray offset: 1e-4 of the scene's bounding-box diagonal."""
    allv = np.concatenate([o.mesh.vertices for o in scene.objects])
    return 1e-4 * float(np.linalg.norm(np.ptp(allv, axis=0)))


def precompute(scene: Scene, *, tau: float = DEFAULT_TAU, spheres: int = 32, grid: int = 32,
               inner: float = 1.2, outer: float = 10.0, cache_dir: Path | None = None,
               progress: bool = True, value_bits: int = 8) -> Precomputed:
    """SVC for every vertex and a VCF for every movable object (cached on disk).

    ``value_bits`` is the precision of the SVC values the renderer gets: 8 (default: the ``u8``
    encoding of :mod:`hostlink.relight.cuts`, 8-bit codes with a float16 scale per cut) or 16
    (float16). The disk cache keeps float16; the 8-bit values are derived from it, exactly as a
    reader of the u8 stream would decode them.
    Deterministic: fixed direction set, fixed chunking, no randomness.
    """
    if value_bits not in (8, 16):
        raise ValueError("value_bits must be 8 or 16")
    pc = _precompute(scene, tau, spheres, grid, inner, outer, cache_dir, progress)
    if value_bits == 8:
        pc.svc_values = quantize_cuts_u8(pc.svc_offsets, pc.svc_values)
    return pc


def _precompute(scene: Scene, tau: float, spheres: int, grid: int, inner: float, outer: float,
                cache_dir: Path | None, progress: bool) -> Precomputed:
    import time

    t0 = time.perf_counter()
    cfg = (int(spheres), int(grid), float(inner), float(outer))
    cache_dir = default_cache_dir() if cache_dir is None else Path(cache_dir)
    path = cache_dir / f"{_cache_key(scene, tau, cfg)}.npz"
    verts, norms, oid, faces, fobj = _gather(scene)
    if path.is_file():
        pc = _load(path, verts, norms, oid, faces, fobj, tau)
        if pc is not None:
            return pc
    eps = scene_eps(scene)
    static = [(o.mesh.vertices, o.mesh.faces) for o in scene.objects if not o.movable]
    cuts: list[tuple[np.ndarray, np.ndarray]] = [(np.zeros(0, np.uint8), np.zeros(0, np.float32))] * len(verts)
    vcf: dict[int, VCF] = {}
    with _progress(progress) as bar:
        task = bar.add_task("SVC", total=len(verts))
        groups = [(np.nonzero(~np.isin(oid, [k for k, o in enumerate(scene.objects) if o.movable]))[0], static)]
        for k, o in enumerate(scene.objects):
            if o.movable:
                groups.append((np.nonzero(oid == k)[0], [*static, (o.mesh.vertices, o.mesh.faces)]))
        for idx, occluders in groups:
            if len(idx) == 0:
                continue
            es = build_embree(occluders) if occluders else None
            step = max(1, _RAYS_PER_CALL // (NDIR // 2))
            for s in range(0, len(idx), step):
                sel = idx[s:s + step]
                out: list[tuple[np.ndarray, np.ndarray]] = []
                if es is None:
                    _svc_unoccluded(norms[sel], tau, out)
                else:
                    _svc_chunk(es, verts[sel], norms[sel], eps, tau, out)
                for i, c in zip(sel, out, strict=True):
                    cuts[i] = c
                bar.advance(task, len(sel))
        t_vcf = time.perf_counter()
        for k, o in enumerate(scene.objects):
            if o.movable:
                t = bar.add_task(f"VCF {o.name}", total=cfg[0] * 6 * cfg[1] ** 2)
                vcf[k] = compute_vcf(o.mesh.vertices, o.mesh.faces, cfg,
                                     lambda n, t=t: bar.advance(t, n))  # type: ignore[misc]
        t_vcf = time.perf_counter() - t_vcf
    lens = np.array([len(h) for h, _ in cuts], np.int64)
    pc = Precomputed(verts, norms, oid, faces, fobj, np.concatenate([[0], np.cumsum(lens)]),
                     np.concatenate([h for h, _ in cuts]),
                     np.concatenate([v for _, v in cuts]).astype(np.float16).astype(np.float32),
                     vcf, tau, time.perf_counter() - t0, False, t_vcf)
    _save(path, pc)
    return pc


def _svc_unoccluded(normals: np.ndarray, tau: float, out: list[tuple[np.ndarray, np.ndarray]]) -> None:
    leaf = np.maximum(normals @ leaf_directions().T, 0)
    for k in range(len(normals)):
        out.append(select_cut(leaf[k], tau, LEAF_SOLID_ANGLE))


def _save(path: Path, pc: Precomputed) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    arrays: dict[str, np.ndarray] = {
        "svc_offsets": pc.svc_offsets, "svc_heights": pc.svc_heights,
        "svc_values": pc.svc_values.astype(np.float16), "seconds": np.array(pc.seconds),
        "vcf_seconds": np.array(pc.vcf_seconds)}
    for k, f in pc.vcf.items():
        for name in ("center", "radii", "offsets", "heights", "values"):
            arrays[f"vcf{k}_{name}"] = getattr(f, name)
        arrays[f"vcf{k}_meta"] = np.array([f.radius, f.grid])
    tmp = path.with_suffix(f".tmp{os.getpid()}.npz")
    np.savez(tmp, **arrays)  # type: ignore[arg-type]
    os.replace(tmp, path)


def _load(path: Path, verts: np.ndarray, norms: np.ndarray, oid: np.ndarray, faces: np.ndarray,
          fobj: np.ndarray, tau: float) -> Precomputed | None:
    try:
        z = np.load(path)
        vcf = {}
        for key in z.files:
            if key.startswith("vcf") and key.endswith("_meta"):
                k = int(key[3:-5])
                meta = z[key]
                vcf[k] = VCF(z[f"vcf{k}_center"], float(meta[0]), z[f"vcf{k}_radii"], int(meta[1]),
                             z[f"vcf{k}_offsets"], z[f"vcf{k}_heights"], z[f"vcf{k}_values"])
        return Precomputed(verts, norms, oid, faces, fobj, z["svc_offsets"], z["svc_heights"],
                           z["svc_values"].astype(np.float32), vcf, tau, float(z["seconds"]), True,
                           float(z["vcf_seconds"]))
    except (OSError, KeyError, ValueError):
        return None   # unreadable cache entry: recompute
