"""``lightprobe bench service``: WebSocket load on the probe service (bounded in time).

Starts ``lightprobe serve --camera sim --scene flashlight`` as a subprocess on 127.0.0.1 (the real
pipeline on the simulator), waits for frames, then measures two phases of equal length:
``unloaded`` (no clients) and ``loaded`` (N WebSocket clients on loopback). Per phase: pipeline
fps (frames / wall time, from ``/status``), mean burst time (``timings.total``), the service's RSS
(``/proc/PID/status`` VmRSS, sampled each second), the service's CPU seconds per frame
(``/proc/PID/stat``: with few frames per phase on a slow box this isolates the fan-out cost better
than the fps ratio) and, when loaded, messages received per client
and frame-to-client latency (receive time - the light set's timestamp). Writes ``service.json``
and ``service.png``.
"""

from __future__ import annotations

import asyncio
import json
import os
import re
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

__all__ = ["run"]

ROOT = Path(__file__).resolve().parent.parent


def _rss_mb(pid: int) -> float:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return float("nan")


def _cpu_s(pid: int) -> float:
    """utime + stime of the whole service process (all threads), seconds."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    except (OSError, IndexError, ValueError):
        return float("nan")


def _start_service(state: Path, fps: float, light_count: int) -> tuple[subprocess.Popen[str], str]:
    cfg = state / "config.toml"
    state.mkdir(parents=True, exist_ok=True)
    cfg.write_text(f"[pipeline]\nfps = {fps!r}\nlight_count = {light_count}\n[mdns]\nenabled = false\n")
    p = subprocess.Popen([sys.executable, "-m", "device.cli", "serve", "--camera", "sim", "--scene", "flashlight",
                          "--port", "0", "--state-dir", str(state), "--config", str(cfg), "--log-format", "json"],
                         cwd=ROOT, env={**os.environ, "PYTHONPATH": str(ROOT)}, stdout=subprocess.PIPE,
                         stderr=subprocess.DEVNULL, text=True)
    assert p.stdout is not None
    for line in p.stdout:
        if m := re.search(r"dashboard (http://\S+)", line):
            return p, m.group(1).rstrip("/")
    raise RuntimeError(f"service exited with {p.wait()}")


async def _status(session: Any, url: str) -> dict[str, Any]:
    async with session.get(url + "/api/v1/status") as r:
        return await r.json()  # type: ignore[no-any-return]


async def _phase(session: Any, url: str, pid: int, seconds: float, clients: int) -> dict[str, Any]:
    import aiohttp

    stop = asyncio.Event()
    received: list[int] = [0] * clients
    latencies: list[float] = []
    nbytes = [0]

    async def client(i: int) -> None:
        async with session.ws_connect(url + "/api/v1/stream", heartbeat=None) as ws:
            while not stop.is_set():
                try:
                    msg = await ws.receive(timeout=0.5)
                except TimeoutError:
                    continue
                if msg.type != aiohttp.WSMsgType.TEXT:
                    break
                received[i] += 1
                nbytes[0] += len(msg.data)
                if i % 5 == 0:
                    latencies.append(time.time() - json.loads(msg.data)["timestamp"])

    tasks = [asyncio.create_task(client(i)) for i in range(clients)]
    await asyncio.sleep(1.0 if clients else 0.0)  # connect before counting
    s0, t0, cpu0 = await _status(session, url), time.monotonic(), _cpu_s(pid)
    rss, totals, seen = [], [], s0["frame"]
    while time.monotonic() - t0 < seconds:
        await asyncio.sleep(1.0)
        rss.append(_rss_mb(pid))
        st = await _status(session, url)
        if st["frame"] != seen:
            seen = st["frame"]
            totals.append(st["timings"].get("total", float("nan")))
    s1, t1, cpu1 = await _status(session, url), time.monotonic(), _cpu_s(pid)
    stop.set()
    await asyncio.gather(*tasks, return_exceptions=True)
    frames = s1["frames"] - s0["frames"]
    lat = sorted(latencies)
    return {
        "clients": clients, "seconds": round(t1 - t0, 2), "frames": frames,
        "fps": frames / (t1 - t0), "cpu_s_per_frame": (cpu1 - cpu0) / frames if frames else None,
        "burst_time_mean_s": sum(totals) / len(totals) if totals else None,
        "rss_mb": rss, "rss_max_mb": max(rss) if rss else None,
        "messages_per_client_min": min(received) if clients else None,
        "messages_per_client_max": max(received) if clients else None,
        "mbytes_sent": nbytes[0] / 1e6,
        "latency_median_s": lat[len(lat) // 2] if lat else None,
        "latency_p95_s": lat[int(0.95 * (len(lat) - 1))] if lat else None,
        "ws_dropped": s1["websocket"]["dropped"], "ws_frames_skipped": s1["websocket"]["frames_skipped"],
    }


def _plot(result: dict[str, Any], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 2, figsize=(10, 3.6))
    for name in ("unloaded", "loaded"):
        ph = result[name]
        ax[0].plot(ph["rss_mb"], label=f"{name} ({ph['clients']} clients)")
    ax[0].set_xlabel("time in phase (s)")
    ax[0].set_ylabel("service RSS (MB)")
    ax[0].legend()
    ax[0].set_title("memory")
    names = ["unloaded", "loaded"]
    ax[1].bar(names, [result[n]["fps"] for n in names], color=["#888", "#f2b33d"])
    ax[1].set_ylabel("pipeline fps")
    ax[1].set_title(f"fps ratio loaded/unloaded = {result['summary']['fps_ratio']:.3f}")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


async def _bench(seconds: float, clients: int, fps: float, light_count: int) -> dict[str, Any]:
    import aiohttp

    with tempfile.TemporaryDirectory(prefix="lp-bench-") as tmp:
        p, url = _start_service(Path(tmp) / "state", fps, light_count)
        try:
            async with aiohttp.ClientSession() as session:
                t_start = time.monotonic()
                while True:  # warm-up: remap tables, first bursts
                    st = await _status(session, url)
                    if st["frames"] >= 3:
                        break
                    if time.monotonic() - t_start > 400:
                        raise RuntimeError("no frames within 400 s")
                    await asyncio.sleep(1.0)
                warmup = time.monotonic() - t_start
                unloaded = await _phase(session, url, p.pid, seconds, 0)
                loaded = await _phase(session, url, p.pid, seconds, clients)
            t_stop = time.monotonic()
            p.send_signal(signal.SIGTERM)
            rc = p.wait(10)
            stop_s = time.monotonic() - t_stop
        finally:
            if p.poll() is None:
                p.kill()
                p.wait(5)
    ratio = loaded["fps"] / unloaded["fps"] if unloaded["fps"] else float("nan")
    summary = {
        "clients": clients, "phase_seconds": seconds, "light_count": light_count, "fps_target": fps,
        "startup_to_3_frames_s": round(warmup, 1),
        "fps_unloaded": round(unloaded["fps"], 3), "fps_loaded": round(loaded["fps"], 3),
        "fps_ratio": round(ratio, 3),
        "burst_time_unloaded_s": unloaded["burst_time_mean_s"], "burst_time_loaded_s": loaded["burst_time_mean_s"],
        "cpu_s_per_frame_unloaded": unloaded["cpu_s_per_frame"],
        "cpu_s_per_frame_loaded": loaded["cpu_s_per_frame"],
        "rss_max_unloaded_mb": unloaded["rss_max_mb"], "rss_max_loaded_mb": loaded["rss_max_mb"],
        "latency_median_s": loaded["latency_median_s"], "latency_p95_s": loaded["latency_p95_s"],
        "ws_dropped": loaded["ws_dropped"], "sigterm_exit_s": round(stop_s, 2), "exit_code": rc,
    }
    return {"summary": summary, "unloaded": unloaded, "loaded": loaded}


def run(out_dir: Path, quick: bool = False) -> dict[str, Any]:
    """Run the load benchmark; ``quick``: 10 s phases and 10 clients."""
    seconds, clients = (10.0, 10) if quick else (30.0, 50)
    result = asyncio.run(_bench(seconds, clients, fps=10.0, light_count=256))
    from bench.cli import machine_info

    result["machine"] = machine_info()
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "service.json").write_text(json.dumps(result, indent=2))
    _plot(result, out_dir / "service.png")
    return result
