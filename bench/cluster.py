"""``lightprobe bench cluster [--quick]``: the cut precompute in-process against a 2-worker Dask
cluster on this machine, in one run.

Scene: ``../shared/data/meshes/spot.obj`` on a ground plane, spot movable (SVC for every vertex,
a VCF of ``spheres`` x 6 x ``grid^2`` points; full: ground 61 x 61 + spot = 7,276 vertices, VCF
16 x 6 x 16^2; quick: ground 25 x 25, VCF 4 x 6 x 8^2). Each run starts from an empty cache.

Reported: wall time in-process (Embree on 2 threads) and on a ``LocalCluster`` of 2
single-threaded worker processes (cluster start-up and scatter timed apart), byte equality of the
two cut files, the per-chunk compute times (from the chunks themselves), and the Dask per-task
overhead (500 empty tasks through the same cluster). The scaling model to N workers:
``T(N) = T_setup + T_ship + max(sum(t_chunk) / N, max t_chunk) + n_tasks x overhead / N``,
every term measured here (``model_compute_s_by_workers`` is the last two terms).
"""

from __future__ import annotations

import json
import shutil
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from lightprobe.bench.relight_scenes import scene_file


def _noop(x: int) -> int:
    return x


def run(out_dir: Path, quick: bool) -> dict[str, Any]:
    from distributed import wait

    from lightprobe.hostlink.relight.cuts import precompute as pre
    from lightprobe.hostlink.relight.cuts.cluster import connect
    from lightprobe.hostlink.relight.scene import load_scene

    res, spheres, grid = (25, 4, 8) if quick else (61, 16, 16)
    work = Path(tempfile.mkdtemp(prefix="lightprobe-bench-cluster-"))
    try:
        scene = load_scene(scene_file(work, True, res))
        job = pre.make_job(scene, cfg=(spheres, grid, 1.2, 10.0))
        chunks = job.chunks()

        t0 = time.perf_counter()
        a = pre.precompute(scene, spheres=spheres, grid=grid, cache_dir=work / "inproc", progress=False)
        t_inproc = time.perf_counter() - t0

        t0 = time.perf_counter()
        with connect("local", workers=2) as client:
            client.wait_for_workers(2)
            t_setup = time.perf_counter() - t0
            import dataclasses

            t1 = time.perf_counter()
            client.scatter(dataclasses.replace(job, threads=1), broadcast=True, hash=False)
            t_ship = time.perf_counter() - t1
            t1 = time.perf_counter()
            b = pre.precompute(scene, spheres=spheres, grid=grid, cache_dir=work / "dask", progress=False,
                               cluster=client)
            t_dask = time.perf_counter() - t1
            n = 500
            t1 = time.perf_counter()
            wait([client.submit(_noop, i, pure=False) for i in range(n)])
            overhead = (time.perf_counter() - t1) / n
        (fa,), (fb,) = (work / "inproc").glob("*.npz"), (work / "dask").glob("*.npz")
        identical = fa.read_bytes() == fb.read_bytes()
        # per-chunk compute times, in this process (one Embree thread, as on a worker)
        one = dataclasses.replace(job, threads=1)
        times = np.array([pre.run_chunk(one, c)[3] for c in chunks])
        model = {str(w): round(float(max(times.sum() / w, times.max()) + len(chunks) * overhead / w), 2)
                 for w in (1, 2, 4, 8, 16, 32)}
        result = {
            "scene": {"vertices": len(a.vertices), "vcf_points": spheres * 6 * grid ** 2,
                      "chunks": len(chunks), "svc_chunks": sum(c[0] == "svc" for c in chunks)},
            "inprocess_s": round(t_inproc, 2),
            "dask_2_workers_s": round(t_dask, 2),
            "dask_cluster_start_s": round(t_setup, 2),
            "dask_scatter_job_s": round(t_ship, 3),
            "speedup": round(t_inproc / t_dask, 2),
            "identical_cut_files": identical,
            "chunk_s": {"sum": round(float(times.sum()), 2), "median": round(float(np.median(times)), 3),
                        "max": round(float(times.max()), 3)},
            "dask_task_overhead_ms": round(overhead * 1e3, 3),
            "model_compute_s_by_workers": model,
            "svc_bytes": int(a.svc_heights.nbytes + a.svc_values.nbytes),
            "cached_both": bool(a.cached or b.cached),
        }
        result["summary"] = {k: result[k] for k in ("inprocess_s", "dask_2_workers_s", "speedup",
                                                   "identical_cut_files", "dask_task_overhead_ms")}
        (out_dir / "cluster.json").write_text(json.dumps(result, indent=2))
        return result
    finally:
        shutil.rmtree(work, ignore_errors=True)
