"""``lightprobe bench NAME [--out DIR]``: run the benchmark module ``lightprobe.bench.NAME``.

Each benchmark module exposes ``run(out_dir: Path, quick: bool) -> dict`` which writes
``NAME.json`` and PNG plots into ``out_dir`` and returns the JSON it wrote.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

BENCHMARKS = {
    "pipeline": "per-stage time and fused-radiance error on the simulated probe",
    "hdr": "HDR fusion: accuracy and speed against OpenCV MergeDebevec",
    "samplers": "run time against error for every sampler on the shared maps",
    "service": "WebSocket load: pipeline fps and memory with many clients",
    "relight": "cut relighting: error and frame time (and relight_sg, and the Pareto plot of both)",
    "relight_sg": "SG relighting (no precompute): error against brute force, frame times, deformation",
    "room": "real-room relighting at 640 x 480: recovery, light power change, light added, object inserted, "
            "moved, a block removed",
    "fleet": "50 simulated probes at 10 Hz through one mosquitto into one merged stream: latency, CPU",
    "cluster": "cut precompute in-process against a 2-worker Dask cluster: time, identity, overhead",
    "formats": "host formats: SH + primary light irradiance error and time, GGX cube map time and error",
    "live": "live rate: light sets per sensor and wall second, change latency, error at that rate, "
            "CPU per frame, start times, RSS",
    "replay": "recordings: the recorder's CPU per frame and dropped frames while the service runs at 30 fps; "
              "a recording read back and the pipeline replayed on it as fast as they go",
    "board": "the service on one pinned core (CPU per set, start, RSS), scaled to Raspberry Pi cores by "
             "published single-core ratios; the arm64 package under emulation (make deb-check's report)",
    "stability": "a static scene's published energy over 3,600 sensor frames from a cold start: first sets, "
                 "settling, frame-to-frame change, excursion, creep, direction jitter",
}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="lightprobe bench", description="Run a benchmark.")
    p.add_argument("name", choices=sorted(BENCHMARKS), help="; ".join(f"{k}: {v}" for k, v in BENCHMARKS.items()))
    p.add_argument("--out", type=Path, default=Path("bench/results"), help="output folder (default bench/results)")
    p.add_argument("--quick", action="store_true", help="fewer repetitions (smoke run)")
    a = p.parse_args(argv)
    a.out.mkdir(parents=True, exist_ok=True)
    from lightprobe.bench import (
        board,
        cluster,
        fleet,
        formats,
        hdr,
        live,
        pipeline,
        relight,
        relight_sg,
        replay,
        room,
        samplers,
        service,
        stability,
    )
    from lightprobe.bench.machine import machine_info

    runners = {"pipeline": pipeline, "hdr": hdr, "samplers": samplers, "service": service, "relight": relight,
               "relight_sg": relight_sg, "room": room, "fleet": fleet, "cluster": cluster, "formats": formats,
               "live": live, "stability": stability, "replay": replay,
               "board": board}
    result = runners[a.name].run(a.out, quick=a.quick)
    print(json.dumps({"machine": machine_info(), **result.get("summary", {})}, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
