"""Start-up and reconnect latency of the probe service (part of ``lightprobe bench service``).

Start-up: ``lightprobe serve --camera sim`` as a subprocess; per run, from ``exec`` (just before
``Popen``): ``api_s`` when the dashboard line is printed (the server listens: it is printed after
the socket accepts) and ``/api/v1/healthz`` answers, ``lights_s`` when the first light set arrives
on ``WS /api/v1/stream`` (the client connects as soon as the API answers), and the service's CPU
seconds by then (``/proc/PID/stat``: the least load-dependent figure on a shared box).
``cold``: a fresh state directory (projection tables built); ``warm``: the same state directory
again (tables loaded from ``STATE/cache``). numba's kernel cache is warm in both (it is built
once per install, not per calibration), and so is the simulator's lens-matrix cache (the user's,
:func:`lightprobe.sim.plugin.sim_cache_dir`: the simulator's, not the unit's).

Reconnect: the service in-process (the real pipeline on the simulator, default backoff), a 5 s
simulated disconnect (``lightprobe.sim.faults``); ``resume_s`` = first fresh (``stale: false``) light set
on the WebSocket minus the moment the camera is back, with the first burst's capture time.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import shutil
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["exec_to_lights", "in_process_service", "reconnect_latency", "start_serve", "startup_summary", "stop_service", "wait_for_api",
           "write_config"]

ROOT = Path(__file__).resolve().parent.parent



def stop_service(p: subprocess.Popen[str], timeout: float = 10.0) -> int:
    """SIGTERM a service started by a benchmark, SIGKILL it if it has not exited in ``timeout``
    seconds; returns its exit code."""
    p.send_signal(signal.SIGTERM)
    try:
        return p.wait(timeout)
    except subprocess.TimeoutExpired:
        p.kill()
        return p.wait(5)

def _cpu_s(pid: int) -> float:
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    except (OSError, IndexError, ValueError):
        return float("nan")


def write_config(state: Path, fps: float, light_count: int) -> Path:
    state.mkdir(parents=True, exist_ok=True)
    cfg = state / "config.toml"
    cfg.write_text(f"[pipeline]\nfps = {fps!r}\nlight_count = {light_count}\n[mdns]\nenabled = false\n")
    return cfg


async def wait_for_api(session: Any, url: str) -> None:
    """Return as soon as the service at ``url`` answers ``/api/v1/healthz`` (polled every 2 ms)."""
    import aiohttp

    while True:
        try:
            async with session.get(url + "/api/v1/healthz") as r:
                await r.read()
        except aiohttp.ClientConnectionError:
            await asyncio.sleep(0.002)
        else:
            return


async def _first_lights(url: str, wait_s: float) -> tuple[float, float, dict[str, Any]]:
    """(API answered, first light set) monotonic times and that light set."""
    import aiohttp

    async with aiohttp.ClientSession() as session:
        await wait_for_api(session, url)
        t_api = time.monotonic()
        async with session.ws_connect(url + "/api/v1/stream") as ws:
            msg = await ws.receive(timeout=wait_s)
            t_lights = time.monotonic()
    if msg.type != aiohttp.WSMsgType.TEXT:
        raise RuntimeError(f"stream ended before the first light set: {msg}")
    return t_api, t_lights, json.loads(msg.data)


def exec_to_lights(state: Path, scene: str = "lebombo", *, fps: float = 10.0, light_count: int = 256,
                   timeout: float = 400.0) -> dict[str, Any]:
    """One start of ``lightprobe serve``: seconds from exec to the API and to the first lights."""
    cfg = write_config(state, fps, light_count)
    t0 = time.monotonic()
    p, url = start_serve("sim", scene, state, cfg, {}, subprocess.DEVNULL)
    try:
        t_print = time.monotonic()
        t_api, t_lights, first = asyncio.run(_first_lights(url, timeout))
        cpu = _cpu_s(p.pid)
    finally:
        stop_service(p)
    return {"printed_s": t_print - t0, "api_s": t_api - t0, "lights_s": t_lights - t0,
            "api_to_lights_s": t_lights - t_api, "service_cpu_s": cpu, "frame": first["frame"],
            "lights": len(first["lights"]), "loadavg_1min": os.getloadavg()[0]}


def _stats(runs: list[dict[str, Any]], key: str) -> dict[str, float]:
    v = [float(r[key]) for r in runs]
    return {"min": round(min(v), 3), "median": round(statistics.median(v), 3), "max": round(max(v), 3)}


def startup_summary(reps_warm: int, reps_cold: int, scene: str = "lebombo") -> dict[str, Any]:
    """Cold starts (fresh state dir each) and warm restarts (one state dir, tables cached)."""
    out: dict[str, Any] = {"scene": scene, "cold": [], "warm": []}
    with tempfile.TemporaryDirectory(prefix="lp-start-") as tmp:
        for i in range(reps_cold):
            out["cold"].append(exec_to_lights(Path(tmp) / f"cold{i}", scene))
            print("cold", json.dumps(out["cold"][-1]), file=sys.stderr, flush=True)
        warm = Path(tmp) / "warm"
        exec_to_lights(warm, scene)  # builds the tables once
        for _ in range(reps_warm):
            out["warm"].append(exec_to_lights(warm, scene))
            print("warm", json.dumps(out["warm"][-1]), file=sys.stderr, flush=True)
    for kind in ("cold", "warm"):
        if out[kind]:
            out[f"{kind}_summary"] = {k: _stats(out[kind], k) for k in
                                      ("api_s", "lights_s", "api_to_lights_s", "service_cpu_s")}
    return out


# ---- reconnect ----------------------------------------------------------------------------------
@contextlib.asynccontextmanager
async def in_process_service(state: Path, scene: str, fps: float, probe_id: str) -> AsyncIterator[tuple[str, Any]]:
    """The service in this process on ``127.0.0.1`` (the real app, pipeline and simulator, no
    mDNS, 256 lights, the default reconnect backoff, as ``lightprobe serve``): yields its URL and
    its :class:`lightprobe.device.service.state.ServiceState` (camera, runner)."""
    from aiohttp import web

    from lightprobe.device.bootstrap import camera_factory, pipeline_factory
    from lightprobe.device.service.app import create_app
    from lightprobe.device.service.config import ServiceConfig
    from lightprobe.device.service.state import STATE

    cfg = ServiceConfig(path=state / "config.toml").with_patch(
        {"mdns": {"enabled": False}, "pipeline": {"fps": fps, "light_count": 256}})
    app = create_app(cfg, camera_factory("sim", scene, state / "cache"), pipeline_factory(state, probe_id),
                     token=f"{probe_id}-token-0123456789", probe_id=probe_id, port=0)
    runner = web.AppRunner(app, shutdown_timeout=0.5, access_log=None)
    await runner.setup()
    try:
        site = web.TCPSite(runner, "127.0.0.1", 0)
        await site.start()
        port = site._server.sockets[0].getsockname()[1]  # type: ignore[union-attr]
        yield f"http://127.0.0.1:{port}", app[STATE]
    finally:
        await runner.cleanup()


async def _reconnect_once(state: Path, outage_s: float) -> dict[str, Any]:
    import aiohttp

    async with (in_process_service(state, "flashlight", 10.0, "benchprobe01") as (url, st),
                aiohttp.ClientSession() as c, c.ws_connect(url + "/api/v1/stream") as ws):
        for _ in range(4):  # settle: bracket adapted, steady bursts
            await ws.receive(timeout=300)
        st.camera.faults.inject("disconnect", duration_s=outage_s)
        back = time.monotonic() + outage_s  # the simulator counts from the injection
        stale = False
        while True:
            d = json.loads((await ws.receive(timeout=60)).data)
            stale = stale or d["stale"]
            if stale and not d["stale"]:
                break
        t_fresh = time.monotonic()
        timings = dict(st.runner.result.timings)
        exposures = list(st.runner.result.exposures)
    return {"resume_s": t_fresh - back, "first_burst_capture_s": timings.get("capture"),
            "first_burst_total_s": timings.get("total"), "exposures": len(exposures),
            "loadavg_1min": os.getloadavg()[0]}


def reconnect_latency(reps: int, outage_s: float = 5.0) -> dict[str, Any]:
    """``reps`` disconnects of ``outage_s`` seconds, each on a fresh in-process service with a
    warm table cache."""
    runs = []
    with tempfile.TemporaryDirectory(prefix="lp-reconnect-") as tmp:
        for i in range(reps):
            state = Path(tmp) / "state"
            runs.append(asyncio.run(_reconnect_once(state, outage_s)))
            print("reconnect", i, json.dumps(runs[-1]), file=sys.stderr, flush=True)
        shutil.rmtree(Path(tmp) / "state", ignore_errors=True)
    return {"outage_s": outage_s, "runs": runs, "resume_s": _stats(runs, "resume_s"),
            "first_burst_capture_s": _stats(runs, "first_burst_capture_s")}


def main(argv: list[str] | None = None) -> int:
    """``python -m lightprobe.bench.service_startup [--warm N] [--cold N] [--scene S] [--state DIR]``: the
    start-up part alone (seconds; no plots). ``--state`` keeps the warm state dir between calls."""
    import argparse

    p = argparse.ArgumentParser(prog="python -m lightprobe.bench.service_startup", description=main.__doc__)
    p.add_argument("--warm", type=int, default=5, help="warm starts (default 5)")
    p.add_argument("--cold", type=int, default=0, help="cold starts (default 0)")
    p.add_argument("--scene", default="lebombo")
    p.add_argument("--state", type=Path, default=None, help="warm state dir to reuse (default: a temporary one)")
    a = p.parse_args(argv)
    if a.state is None:
        out = startup_summary(a.warm, a.cold, a.scene)
    else:
        out = {"scene": a.scene, "cold": [], "warm": []}
        exec_to_lights(a.state, a.scene)  # builds the tables if needed
        for _ in range(a.warm):
            out["warm"].append(exec_to_lights(a.state, a.scene))
            print("warm", json.dumps(out["warm"][-1]), file=sys.stderr, flush=True)
        out["warm_summary"] = {k: _stats(out["warm"], k) for k in
                               ("api_s", "lights_s", "api_to_lights_s", "service_cpu_s")}
    for kind in ("cold", "warm"):
        if f"{kind}_summary" in out:
            print(kind, json.dumps(out[f"{kind}_summary"]))
    print("loadavg", [round(r["loadavg_1min"], 2) for r in out["warm"] + out["cold"]])
    return 0


# ---- live figures (lightprobe bench live, part 2) ---------------------------------------------
def _rss_mb(pid: int) -> tuple[float, float]:
    """(VmRSS, VmHWM) of a process in MB."""
    vals = {}
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        k, _, v = line.partition(":")
        if k in ("VmRSS", "VmHWM"):
            vals[k] = int(v.split()[0]) / 1024
    return vals.get("VmRSS", float("nan")), vals.get("VmHWM", float("nan"))


async def _watch(url: str, seconds: float, q2tree: bool) -> dict[str, Any]:
    """Light sets on the WebSocket for ``seconds`` (after the first), the first q2tree call."""
    import aiohttp

    out: dict[str, Any] = {}
    async with aiohttp.ClientSession() as session, session.ws_connect(url + "/api/v1/stream") as ws:
        await ws.receive(timeout=120)
        if q2tree:
            t = time.monotonic()
            async with session.get(url + "/api/v1/q2tree") as r:
                await r.read()
                out["q2tree_status"] = r.status
            out["q2tree_first_s"] = time.monotonic() - t
        n, t0, frames = 0, time.monotonic(), set()
        glass, probe, wire = [], [], []  # capture -> received here; capture -> published; published -> here
        while time.monotonic() - t0 < seconds:
            msg = await ws.receive(timeout=30)
            received = time.time()
            if msg.type != aiohttp.WSMsgType.TEXT:
                break
            n += 1
            d = json.loads(msg.data)
            frames.add(d["frame"])
            if d.get("captured") is not None and not d.get("stale"):
                glass.append(received - d["captured"])
                probe.append(d["timestamp"] - d["captured"])
                wire.append(received - d["timestamp"])
        out["sets_per_s"] = n / (time.monotonic() - t0)
        out["distinct_frames_per_s"] = len(frames) / (time.monotonic() - t0)
        if glass:  # glass-to-host: the middle of the newest frame's exposure -> the message here
            out["glass_to_host_ms"] = {"p50": 1e3 * float(np.percentile(glass, 50)),
                                       "p99": 1e3 * float(np.percentile(glass, 99)),
                                       "max": 1e3 * float(np.max(glass)), "n": len(glass)}
            out["capture_to_publish_ms"] = {"p50": 1e3 * float(np.percentile(probe, 50)),
                                            "p99": 1e3 * float(np.percentile(probe, 99))}
            out["publish_to_host_ms"] = {"p50": 1e3 * float(np.percentile(wire, 50)),
                                         "p99": 1e3 * float(np.percentile(wire, 99))}
    return out


def start_serve(camera: str, scene: str, state: Path, cfg: Path, env: dict[str, str], stderr: Any,
                prefix: tuple[str, ...] = ()) -> tuple[subprocess.Popen[str], str]:
    """``lightprobe serve`` as a user starts it (after ``prefix``: ``taskset -c 0``); returns
    the process and the dashboard URL it printed."""
    p = subprocess.Popen([*prefix, sys.executable, "-m", "lightprobe.cli", "serve", "--camera", camera, "--scene", scene,
                          "--port", "0", "--state-dir", str(state), "--config", str(cfg), "--log-format", "json"],
                         cwd=ROOT, env={**os.environ, "PYTHONPATH": str(ROOT), **env}, stdout=subprocess.PIPE,
                         stderr=stderr, text=True)
    assert p.stdout is not None
    for line in p.stdout:
        if "dashboard http://" in line:
            return p, line.split("dashboard ", 1)[1].split()[0].rstrip("/")
    raise RuntimeError(f"service exited with {p.wait()}")


def serve_live(state: Path, *, camera: str = "sim", scene: str = "flashlight", watch_s: float = 10.0,
               rss_after_s: float = 60.0, env: dict[str, str] | None = None, q2tree: bool = True,
               fps: float = 30.0) -> dict[str, Any]:
    """``lightprobe serve`` as a user starts it: first lights after exec, light sets per second
    on the WebSocket, the first q2tree call, reconnects logged, RSS and peak RSS after
    ``rss_after_s`` seconds."""
    cfg = write_config(state, fps, 256)
    t0 = time.monotonic()
    log_path = state / "serve.log"
    with log_path.open("w") as log:
        p, url = start_serve(camera, scene, state, cfg, env or {}, log)
        try:
            _t_api, t_lights, _first = asyncio.run(_first_lights(url, 300))
            out: dict[str, Any] = {"camera": camera, "scene": scene, "lights_s": t_lights - t0}
            out.update(asyncio.run(_watch(url, watch_s, q2tree)))
            rest = rss_after_s - (time.monotonic() - t0)
            if rest > 0:
                time.sleep(rest)
            out["rss_mb"], out["peak_rss_mb"] = _rss_mb(p.pid)
            out["rss_at_s"] = time.monotonic() - t0
            out["service_cpu_s"] = _cpu_s(p.pid)
        finally:
            stop_service(p)
    text = log_path.read_text()
    out["reconnects"] = text.count("reconnect")
    out["capture_timeouts"] = text.count("CaptureTimeout")
    out["loadavg_1min"] = os.getloadavg()[0]
    return out


def live_service_figures(quick: bool = False) -> dict[str, Any]:
    """The wall-time part of ``lightprobe bench live`` (see bench/live.py)."""
    rss_s = 15.0 if quick else 60.0
    res: dict[str, Any] = {}
    with tempfile.TemporaryDirectory(prefix="lp-live-") as tmp:
        base = Path(tmp)
        res["sim_cold"] = serve_live(base / "sim", rss_after_s=rss_s)
        # warm (the balanced table on disk): 20 s of the stream, glass-to-host latency among it
        res["sim_warm"] = serve_live(base / "sim", rss_after_s=0, watch_s=20, q2tree=False)
        res["sim_lebombo"] = serve_live(base / "leb", scene="lebombo", rss_after_s=0, watch_s=5, q2tree=False)
        res["unit_numba_cache_cold"] = serve_live(base / "unit", rss_after_s=0, watch_s=3, q2tree=False,
                                                  env={"NUMBA_CACHE_DIR": str(base / "unit" / "cache" / "numba")})
        res["v4l2_fake"] = serve_live(base / "v4l2", camera="v4l2-fake", rss_after_s=rss_s)
    return res


if __name__ == "__main__":  # at the end: main() uses the helpers defined above
    sys.exit(main())
