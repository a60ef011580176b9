"""Precomputation of self-visibility cuts (SVC) and visibility cut fields (VCF) with Embree.

* SVC, per vertex: leaf value ``V(x, w_j) max(0, n . w_j)`` over the 2^15 directions, cut at the
  integrated-SSE threshold ``tau`` (:func:`lightprobe.hostlink.relight.cuts.coding.select_cut`). Occluders: all
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

import contextlib
import hashlib
import os
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from lightprobe.hostlink.relight.cuts.coding import binary_cut, quantize_cuts_u8, select_cut
from lightprobe.hostlink.relight.cuts.directions import LEAF_SOLID_ANGLE, NDIR, leaf_directions
from lightprobe.hostlink.relight.rays import RAYS_PER_CALL, build_embree, occluded, scene_eps
from lightprobe.hostlink.relight.scene import Scene, vertex_normals

__all__ = [
    "CACHE_VERSION",
    "DEFAULT_TAU",
    "VCF",
    "Job",
    "Precomputed",
    "compute_vcf",
    "cube_points",
    "default_cache_dir",
    "make_job",
    "precompute",
    "run_chunk",
]

DEFAULT_TAU = 2e-5
CACHE_VERSION = 2  # 2: timings in KEY.json beside the cut file (the .npz holds cuts only)


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


def _svc_cuts(es, verts: np.ndarray, normals: np.ndarray, eps: float, tau: float,  # type: ignore[no-untyped-def]
              threads: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """SVC cuts of a few vertices (at most ``RAYS_PER_CALL`` rays at a time)."""
    dirs = leaf_directions()
    out: list[tuple[np.ndarray, np.ndarray]] = []
    step = max(1, RAYS_PER_CALL // (NDIR // 2))
    for s in range(0, len(verts), step):
        v, n = verts[s:s + step], normals[s:s + step]
        cos = n @ dirs.T                                       # (n, 2^15)
        if es is None:
            leaf = np.maximum(cos, 0)
        else:
            vi, di = np.nonzero(cos > 0)
            occ = occluded(es, v[vi] + eps * n[vi], dirs[di], threads)
            leaf = np.zeros_like(cos)
            leaf[vi[~occ], di[~occ]] = cos[vi[~occ], di[~occ]]
        out.extend(select_cut(leaf[k], tau, LEAF_SOLID_ANGLE) for k in range(len(v)))
    return out


def _vcf_cuts(es, pts: np.ndarray, c: np.ndarray, r: float, threads: int,  # type: ignore[no-untyped-def]
              tick: Callable[[int], None] = lambda n: None) -> list[tuple[np.ndarray, np.ndarray]]:
    """Binary visibility cuts at VCF sample points ``pts`` around an object (centre ``c``,
    radius ``r``); only directions inside the bounding cone are traced."""
    dirs = leaf_directions()
    out: list[tuple[np.ndarray, np.ndarray]] = []
    step = max(1, RAYS_PER_CALL // (NDIR // 4))
    for s in range(0, len(pts), step):
        chunk = pts[s:s + step]
        to_c = c - chunk
        d = np.linalg.norm(to_c, axis=1)
        cos_cone = np.where(d > r, np.sqrt(np.clip(1 - (r / np.maximum(d, 1e-12)) ** 2, 0, 1)), -2.0)
        cone = (to_c / d[:, None]) @ dirs.T >= cos_cone[:, None] - 1e-6   # bounding-cone culling
        pi, di = np.nonzero(cone)
        occ = occluded(es, chunk[pi], dirs[di], threads)
        bounds = np.searchsorted(pi, np.arange(len(chunk) + 1))
        for k in range(len(chunk)):                         # stream point by point into cuts
            bits = np.ones(NDIR, np.uint8)
            a, b = bounds[k], bounds[k + 1]
            bits[di[a:b][occ[a:b]]] = 0
            out.append(binary_cut(bits))
        tick(len(chunk))
    return out


def _vcf_frame(mesh_v: np.ndarray, cfg: tuple[int, int, float, float]) -> tuple[np.ndarray, float, np.ndarray]:
    """Centre, radius and sphere radii of an object's VCF."""
    spheres, _grid, inner, outer = cfg
    lo, hi = mesh_v.min(axis=0), mesh_v.max(axis=0)
    c = (lo + hi) / 2
    r = float(np.linalg.norm(mesh_v - c, axis=1).max())
    radii = np.linspace(inner * r, outer * r, spheres) if spheres > 1 else np.array([inner * r])
    return c, r, radii


def _pack(cuts: list[tuple[np.ndarray, np.ndarray]], value_dtype: type) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    lens = np.array([len(h) for h, _ in cuts], np.int64)
    heights = np.concatenate([h for h, _ in cuts]) if cuts else np.zeros(0, np.uint8)
    values = np.concatenate([v for _, v in cuts]) if cuts else np.zeros(0)
    return lens, heights.astype(np.uint8), values.astype(value_dtype)


def compute_vcf(mesh_v: np.ndarray, mesh_f: np.ndarray, cfg: tuple[int, int, float, float],
                tick: Callable[[int], None]) -> VCF:
    """The VCF of one mesh, in this process."""
    c, r, radii = _vcf_frame(mesh_v, cfg)
    pts = cube_points(radii, cfg[1]) + c
    lens, hs, vs = _pack(_vcf_cuts(build_embree([(mesh_v, mesh_f)]), pts, c, r, 2, tick), np.uint8)
    return VCF(c, r, radii, cfg[1], np.concatenate([[0], np.cumsum(lens)]), hs, vs)


# ---- chunks: pure functions of (scene key, chunk, parameters) ---------------------------------------
SVC_TASK_VERTICES = 256  # vertices per SVC chunk (4 Embree calls of 2^20 rays at most)


@dataclass
class Job:
    """Everything a chunk needs, shipped once per worker (``Client.scatter(broadcast=True)``).

    ``groups[g]`` = (vertex indices, occluder meshes); ``movable[k]`` = (vertices, faces) of
    object k, whose VCF is chunked one sphere (``6 grid^2`` points) per task."""

    key: str
    vertices: np.ndarray
    normals: np.ndarray
    groups: list[tuple[np.ndarray, list[tuple[np.ndarray, np.ndarray]]]]
    movable: dict[int, tuple[np.ndarray, np.ndarray]]
    eps: float
    tau: float
    cfg: tuple[int, int, float, float]
    threads: int = 2

    def chunks(self) -> list[tuple[str, int, int, int]]:
        """("svc", group, lo, hi) ranges of a group's vertex list and ("vcf", object, lo, hi)
        ranges of an object's VCF points, in a fixed order (the assembly order)."""
        out = [("svc", g, lo, min(lo + SVC_TASK_VERTICES, len(idx)))
               for g, (idx, _) in enumerate(self.groups) for lo in range(0, len(idx), SVC_TASK_VERTICES)]
        per_sphere = 6 * self.cfg[1] ** 2
        out += [("vcf", k, s * per_sphere, (s + 1) * per_sphere)
                for k in sorted(self.movable) for s in range(self.cfg[0])]
        return out


_EMBREE: dict[tuple[str, str, int], object] = {}  # per process: built once per (scene, group/object)


def _embree_for(job: Job, kind: str, index: int):  # type: ignore[no-untyped-def]
    key = (job.key, kind, index)
    if key not in _EMBREE:
        if len(_EMBREE) >= 8:
            _EMBREE.pop(next(iter(_EMBREE)))
        meshes = job.groups[index][1] if kind == "svc" else [job.movable[index]]
        _EMBREE[key] = build_embree(meshes) if meshes else None
    return _EMBREE[key]


def run_chunk(job: Job, chunk: tuple[str, int, int, int]) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """One chunk's cuts as (lengths, heights, values, seconds): SVC values float16, VCF values
    0/1 uint8. Deterministic; runs in this process or on a Dask worker."""
    import time

    t0 = time.perf_counter()
    kind, index, lo, hi = chunk
    es = _embree_for(job, kind, index)
    if kind == "svc":
        sel = job.groups[index][0][lo:hi]
        cuts = _svc_cuts(es, job.vertices[sel], job.normals[sel], job.eps, job.tau, job.threads)
        lens, hs, vs = _pack(cuts, np.float16)
    else:
        mv = job.movable[index][0]
        c, r, radii = _vcf_frame(mv, job.cfg)
        pts = (cube_points(radii, job.cfg[1]) + c)[lo:hi]
        lens, hs, vs = _pack(_vcf_cuts(es, pts, c, r, job.threads), np.uint8)
    return lens, hs, vs, time.perf_counter() - t0


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


def precompute(scene: Scene, *, tau: float = DEFAULT_TAU, spheres: int = 32, grid: int = 32,
               inner: float = 1.2, outer: float = 10.0, cache_dir: Path | None = None,
               progress: bool = True, value_bits: int = 8, cluster: object = None) -> Precomputed:
    """SVC for every vertex and a VCF for every movable object (cached on disk).

    ``value_bits`` is the precision of the SVC values the renderer gets: 8 (default: the ``u8``
    encoding of :mod:`lightprobe.hostlink.relight.cuts.coding`, 8-bit codes with a float16 scale per cut) or 16
    (float16). The disk cache keeps float16; the 8-bit values are derived from it, exactly as a
    reader of the u8 stream would decode them.

    ``cluster`` runs the chunks on Dask (:mod:`lightprobe.hostlink.relight.cuts.cluster`): a
    ``distributed.Client``, a scheduler address (``tcp://host:8786``) or ``"local"`` (a local
    cluster sized to the machine); ``None`` runs them in this process. Either way every chunk's
    result is cached as it arrives (an interrupted run redoes only the missing chunks) and the
    cut file is byte-identical. Deterministic: fixed direction set, fixed chunking, no randomness.
    """
    if value_bits not in (8, 16):
        raise ValueError("value_bits must be 8 or 16")
    pc = _precompute(scene, tau, spheres, grid, inner, outer, cache_dir, progress, cluster)
    if value_bits == 8:
        pc.svc_values = quantize_cuts_u8(pc.svc_offsets, pc.svc_values)
    return pc


def make_job(scene: Scene, tau: float = DEFAULT_TAU, cfg: tuple[int, int, float, float] = (32, 32, 1.2, 10.0),
             threads: int = 2) -> Job:
    """The scene's chunkable precompute: vertex groups with their occluders, movable meshes."""
    verts, norms, oid, _faces, _fobj = _gather(scene)
    movable = [k for k, o in enumerate(scene.objects) if o.movable]
    static = [(o.mesh.vertices, o.mesh.faces) for o in scene.objects if not o.movable]
    groups = [(np.nonzero(~np.isin(oid, movable))[0], static)]
    for k in movable:
        o = scene.objects[k]
        groups.append((np.nonzero(oid == k)[0], [*static, (o.mesh.vertices, o.mesh.faces)]))
    cfg = (int(cfg[0]), int(cfg[1]), float(cfg[2]), float(cfg[3]))
    return Job(_cache_key(scene, tau, cfg), verts, norms, groups,
               {k: (scene.objects[k].mesh.vertices, scene.objects[k].mesh.faces) for k in movable},
               scene_eps(scene), float(tau), cfg, threads)


ChunkResult = tuple[np.ndarray, np.ndarray, np.ndarray, float]


def chunk_dir(cache_dir: Path, key: str) -> Path:
    return cache_dir / f"{key}.chunks"


def _chunk_path(d: Path, chunk: tuple[str, int, int, int]) -> Path:
    kind, index, lo, hi = chunk
    return d / f"{kind}-{index}-{lo}-{hi}.npz"


def save_chunk(d: Path, chunk: tuple[str, int, int, int], res: ChunkResult) -> None:
    d.mkdir(parents=True, exist_ok=True)
    path = _chunk_path(d, chunk)
    tmp = path.with_suffix(f".tmp{os.getpid()}.npz")
    np.savez(tmp, lens=res[0], heights=res[1], values=res[2], seconds=np.array(res[3]))
    os.replace(tmp, path)


def load_chunk(d: Path, chunk: tuple[str, int, int, int]) -> ChunkResult | None:
    try:
        with np.load(_chunk_path(d, chunk)) as z:
            return z["lens"], z["heights"], z["values"], float(z["seconds"])
    except (OSError, KeyError, ValueError):
        return None


def _precompute(scene: Scene, tau: float, spheres: int, grid: int, inner: float, outer: float,
                cache_dir: Path | None, progress: bool, cluster: object = None) -> Precomputed:
    import shutil
    import time

    t0 = time.perf_counter()
    cfg = (int(spheres), int(grid), float(inner), float(outer))
    cache_dir = default_cache_dir() if cache_dir is None else Path(cache_dir)
    job = make_job(scene, tau, cfg)
    path = cache_dir / f"{job.key}.npz"
    verts, norms, oid, faces, fobj = _gather(scene)
    if path.is_file():
        pc = _load(path, verts, norms, oid, faces, fobj, tau)
        if pc is not None:
            return pc
    chunks = job.chunks()
    cdir = chunk_dir(cache_dir, job.key)
    results: dict[tuple[str, int, int, int], ChunkResult] = {}
    for c in chunks:  # a restarted run keeps what an earlier one finished
        r = load_chunk(cdir, c)
        if r is not None:
            results[c] = r
    missing = [c for c in chunks if c not in results]
    with _progress(progress) as bar:
        task = bar.add_task("SVC + VCF chunks", total=len(chunks), completed=len(results))

        def done(c: tuple[str, int, int, int], r: ChunkResult) -> None:
            save_chunk(cdir, c, r)
            results[c] = r
            bar.advance(task, 1)

        if cluster is None:
            for c in missing:
                done(c, run_chunk(job, c))
        else:
            from lightprobe.hostlink.relight.cuts.cluster import run_on_dask

            run_on_dask(run_chunk, job, missing, cluster, done)
    pc = _assemble(job, results, verts, norms, oid, faces, fobj)
    pc.seconds = time.perf_counter() - t0
    pc.vcf_seconds = sum(r[3] for c, r in results.items() if c[0] == "vcf")
    _save(path, pc)
    shutil.rmtree(cdir, ignore_errors=True)
    return pc


def _assemble(job: Job, results: dict[tuple[str, int, int, int], ChunkResult], verts: np.ndarray,
              norms: np.ndarray, oid: np.ndarray, faces: np.ndarray, fobj: np.ndarray) -> Precomputed:
    """Chunk results -> SVC arrays in vertex order and one VCF per movable object."""
    n = len(verts)
    lens = np.zeros(n, np.int64)
    parts_h: list[np.ndarray | None] = [None] * n
    parts_v: list[np.ndarray | None] = [None] * n
    vcf_parts: dict[int, list[ChunkResult]] = {}
    for c in job.chunks():
        kind, g, lo, hi = c
        ln, hs, vs, _ = results[c]
        if kind == "vcf":
            vcf_parts.setdefault(g, []).append(results[c])
            continue
        sel = job.groups[g][0][lo:hi]
        off = np.concatenate([[0], np.cumsum(ln)])
        for j, i in enumerate(sel):
            lens[i] = ln[j]
            parts_h[i] = hs[off[j]:off[j + 1]]
            parts_v[i] = vs[off[j]:off[j + 1]]
    empty_h, empty_v = np.zeros(0, np.uint8), np.zeros(0, np.float16)
    svc_h = np.concatenate([empty_h] + [p if p is not None else empty_h for p in parts_h])
    svc_v = np.concatenate([empty_v] + [p if p is not None else empty_v for p in parts_v])
    vcf: dict[int, VCF] = {}
    for k, parts in vcf_parts.items():
        centre, r, radii = _vcf_frame(job.movable[k][0], job.cfg)
        ln = np.concatenate([p[0] for p in parts])
        vcf[k] = VCF(centre, r, radii, job.cfg[1], np.concatenate([[0], np.cumsum(ln)]),
                     np.concatenate([p[1] for p in parts]), np.concatenate([p[2] for p in parts]))
    return Precomputed(verts, norms, oid, faces, fobj, np.concatenate([[0], np.cumsum(lens)]),
                       svc_h, svc_v.astype(np.float32), vcf, job.tau)


def _savez_deterministic(path: Path, arrays: dict[str, np.ndarray]) -> None:
    """``np.savez`` with fixed zip timestamps, written atomically: the same arrays give the same
    bytes (``np.load`` reads it as any .npz)."""
    import zipfile

    tmp = path.with_suffix(f".tmp{os.getpid()}.npz")
    with zipfile.ZipFile(tmp, "w", zipfile.ZIP_STORED, allowZip64=True) as zf:
        for name in sorted(arrays):
            info = zipfile.ZipInfo(f"{name}.npy", date_time=(1980, 1, 1, 0, 0, 0))
            with zf.open(info, "w", force_zip64=True) as f:
                np.lib.format.write_array(f, np.asanyarray(arrays[name]), allow_pickle=False)
    os.replace(tmp, path)


def _save(path: Path, pc: Precomputed) -> None:
    """The cut file (``KEY.npz``: byte-identical for the same scene and parameters) and its
    timings beside it (``KEY.json``)."""
    import json

    path.parent.mkdir(parents=True, exist_ok=True)
    arrays: dict[str, np.ndarray] = {
        "svc_offsets": pc.svc_offsets, "svc_heights": pc.svc_heights,
        "svc_values": pc.svc_values.astype(np.float16)}
    for k, f in pc.vcf.items():
        for name in ("center", "radii", "offsets", "heights", "values"):
            arrays[f"vcf{k}_{name}"] = getattr(f, name)
        arrays[f"vcf{k}_meta"] = np.array([f.radius, f.grid])
    _savez_deterministic(path, arrays)
    tmp = path.with_suffix(f".tmp{os.getpid()}.json")
    tmp.write_text(json.dumps({"seconds": pc.seconds, "vcf_seconds": pc.vcf_seconds}))
    os.replace(tmp, path.with_suffix(".json"))


def _load(path: Path, verts: np.ndarray, norms: np.ndarray, oid: np.ndarray, faces: np.ndarray,
          fobj: np.ndarray, tau: float) -> Precomputed | None:
    import json

    try:
        z = np.load(path)
        vcf = {}
        for key in z.files:
            if key.startswith("vcf") and key.endswith("_meta"):
                k = int(key[3:-5])
                meta = z[key]
                vcf[k] = VCF(z[f"vcf{k}_center"], float(meta[0]), z[f"vcf{k}_radii"], int(meta[1]),
                             z[f"vcf{k}_offsets"], z[f"vcf{k}_heights"], z[f"vcf{k}_values"])
        times = {"seconds": 0.0, "vcf_seconds": 0.0}
        with contextlib.suppress(OSError, ValueError):
            times.update(json.loads(path.with_suffix(".json").read_text()))
        return Precomputed(verts, norms, oid, faces, fobj, z["svc_offsets"], z["svc_heights"],
                           z["svc_values"].astype(np.float32), vcf, tau, float(times["seconds"]), True,
                           float(times["vcf_seconds"]))
    except (OSError, KeyError, ValueError):
        return None   # unreadable cache entry: recompute
