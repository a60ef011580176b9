"""``lightprobe bench board``: what the service costs a board's core, and on what basis.

A unit is an arm64 board (Raspberry Pi 4/5 class); the speed, start and memory targets were met
on a 2-core x86-64 VM. Three kinds of figure, each said for what it is:

- **one x86-64 core**: ``lightprobe serve`` pinned to one core (``taskset -c 0``, numba and
  OpenMP limited to one thread), at 30 fps on ``sim`` and ``v4l2-fake``: CPU seconds per
  published light set (the service's own CPU over the watched window, divided by the sets the
  WebSocket received), sets per second, first lights from exec, RSS and peak RSS;
- **a board's core, scaled**: that per-set CPU times the ratio of this core's single-thread
  ``sysbench cpu`` score (run here, primes up to 10,000) to a board's published one (leoncode.co.uk's
  Raspberry Pi CPU benchmarks, sysbench 1.0.20, the same command: Pi 3B+ Cortex-A53 at 1.4 GHz
  687.45 events/s, Pi 4 Cortex-A72 at 1.5 GHz 1477.83, Pi 5 Cortex-A76 at 2.4 GHz 2737.49). That
  loop is integer arithmetic: the pipeline's passes are also bound by memory bandwidth, which a
  board has less of; the scaled figure is a floor, not a promise;
- **arm64 under emulation** (``make deb-check``'s report, if there is one): install time with
  the kernels compiled, first lights, frames per second of the arm64 package in an arm64 root
  under QEMU user-mode emulation. Emulation is not a board's speed (on the 2-core Xeon VM the
  emulated service published 2.27 sets/s on sim and 0.47 on v4l2-fake, 13-64 x slower than
  natively): these figures show it runs, not how fast.
"""

from __future__ import annotations

import asyncio
import json
import re
import shutil
import subprocess
import tempfile
import time
from pathlib import Path
from typing import Any

from lightprobe.bench.machine import machine_info
from lightprobe.bench.service_startup import (
    _cpu_s,
    _first_lights,
    _rss_mb,
    _watch,
    start_serve,
    stop_service,
    write_config,
)

ROOT = Path(__file__).resolve().parent.parent
# sysbench 1.0.20 `sysbench cpu --threads=1 --time=60 run` (primes up to 10,000), events/s,
# https://leoncode.co.uk/articles/raspberry-pi-benchmarks
BOARDS = {
    "Raspberry Pi 3B+ (Cortex-A53, 1.4 GHz)": 687.45,
    "Raspberry Pi 4 (Cortex-A72, 1.5 GHz)": 1477.83,
    "Raspberry Pi 5 (Cortex-A76, 2.4 GHz)": 2737.49,
}
FPS = 30.0


def sysbench_single(seconds: float = 10.0) -> float | None:
    """This machine's single-thread ``sysbench cpu`` events/s, pinned to core 0 (None: no sysbench)."""
    exe = shutil.which("sysbench")
    if exe is None:
        return None
    r = subprocess.run(["taskset", "-c", "0", exe, "cpu", "--threads=1", f"--time={seconds:g}", "run"],
                       capture_output=True, text=True, check=True)
    m = re.search(r"events per second:\s*([\d.]+)", r.stdout)
    return float(m.group(1)) if m else None


def pinned_service(state: Path, camera: str, watch_s: float, rss_after_s: float) -> dict[str, Any]:
    """``lightprobe serve`` on one core: first lights, sets/s, CPU per set, RSS."""
    cfg = write_config(state, FPS, 256)
    env = {"NUMBA_NUM_THREADS": "1", "OMP_NUM_THREADS": "1"}
    t0 = time.monotonic()
    log_path = state / "serve.log"
    with log_path.open("w") as log:
        p, url = start_serve(camera, "flashlight", state, cfg, env, log, prefix=("taskset", "-c", "0"))
        try:
            _api, t_lights, _first = asyncio.run(_first_lights(url, 600))
            out: dict[str, Any] = {"camera": camera, "first_lights_s": round(t_lights - t0, 2)}
            time.sleep(2.0)  # past the start's one-off work (the balanced table, the sampler's first pass)
            cpu0, w0 = _cpu_s(p.pid), time.monotonic()
            watched = asyncio.run(_watch(url, watch_s, False))
            cpu1, w1 = _cpu_s(p.pid), time.monotonic()
            sets = watched["sets_per_s"] * (w1 - w0)
            out.update(sets_per_s=round(watched["sets_per_s"], 2),
                       cpu_ms_per_set=round(1e3 * (cpu1 - cpu0) / max(sets, 1.0), 2),
                       cpu_share=round((cpu1 - cpu0) / (w1 - w0), 3))
            rest = rss_after_s - (time.monotonic() - t0)
            if rest > 0:
                time.sleep(rest)
            rss, peak = _rss_mb(p.pid)
            out.update(rss_mb=round(rss, 1), peak_rss_mb=round(peak, 1), rss_at_s=round(time.monotonic() - t0, 1))
        finally:
            out_rc = stop_service(p)
    out["exit"] = out_rc
    return out


def emulated_figures(report: Path) -> dict[str, Any] | None:
    """The arm64 run of ``make deb-check``'s report, marked emulated."""
    if not report.is_file():
        return None
    d = json.loads(report.read_text())
    run = d.get("runs", {}).get("arm64")
    if not run:
        return {"skipped": d.get("skipped", {}).get("arm64", "no arm64 run in the report"), "report": str(report)}
    return {"emulated": True, "report": str(report), "date": d.get("date"), "install_s": run.get("install_s"),
            "services": [{k: s.get(k) for k in ("camera", "first_lights_s", "fps", "threading_layer")}
                         for s in run.get("services", [])],
            "vs_amd64": d.get("arm64_vs_amd64")}


def run(out_dir: Path, quick: bool = False) -> dict[str, Any]:
    watch_s, rss_s = (5.0, 10.0) if quick else (20.0, 60.0)
    res: dict[str, Any] = {"machine": machine_info()}
    with tempfile.TemporaryDirectory(prefix="lp-board-") as tmp:
        res["one_core"] = {cam: pinned_service(Path(tmp) / cam, cam, watch_s, rss_s) for cam in ("sim", "v4l2-fake")}
    score = sysbench_single(5.0 if quick else 20.0)
    res["sysbench_single_events_s"] = score
    scaled: dict[str, Any] = {}
    if score:
        for board, theirs in BOARDS.items():
            factor = score / theirs
            scaled[board] = {"factor": round(factor, 2)}
            for cam, r in res["one_core"].items():
                ms = r["cpu_ms_per_set"] * factor
                # the board's four cores: the pipeline's kernels use them all, the loop one
                scaled[board][cam] = {"cpu_ms_per_set": round(ms, 1),
                                      "sets_per_s_one_core": round(min(FPS, 1e3 / ms), 1) if ms > 0 else None}
    res["scaled"] = scaled
    res["emulated_arm64"] = emulated_figures(ROOT / "dist/deb-check.json")  # make deb-check's report
    res["summary"] = {"one_core": {c: {k: r[k] for k in ("cpu_ms_per_set", "sets_per_s", "first_lights_s", "rss_mb",
                                                          "peak_rss_mb")} for c, r in res["one_core"].items()},
                      "sysbench_single_events_s": score, "scaled": scaled,
                      "emulated_arm64": res["emulated_arm64"]}
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "board.json").write_text(json.dumps(res, indent=2) + "\n")
    return res


if __name__ == "__main__":
    import sys

    r = run(Path(sys.argv[1]) if len(sys.argv) > 1 else ROOT / "bench/results", quick="--quick" in sys.argv)
    print(json.dumps(r["summary"], indent=2))
