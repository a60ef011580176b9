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

Accuracy (issue 4): ``lightprobe serve --camera sim --scene MAP`` for each shared map, the
published 256 lights against the true map's upper hemisphere: diffuse irradiance at 64
upward-facing normals (exact pixel sums), relative error after the best global scale, and that
scale (1 = the simulator's unit).
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

import numpy as np

__all__ = ["run", "run_accuracy"]

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


def _start_service(state: Path, fps: float, light_count: int,
                   scene: str = "flashlight") -> tuple[subprocess.Popen[str], str]:
    cfg = state / "config.toml"
    state.mkdir(parents=True, exist_ok=True)
    cfg.write_text(f"[pipeline]\nfps = {fps!r}\nlight_count = {light_count}\n[mdns]\nenabled = false\n")
    p = subprocess.Popen([sys.executable, "-m", "device.cli", "serve", "--camera", "sim", "--scene", scene,
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
    me0 = time.process_time()
    rss, totals, seen = [], [], s0["frame"]
    while time.monotonic() - t0 < seconds:
        await asyncio.sleep(1.0)
        rss.append(_rss_mb(pid))
        st = await _status(session, url)
        if st["frame"] != seen:
            seen = st["frame"]
            totals.append(st["timings"].get("total", float("nan")))
    s1, t1, cpu1 = await _status(session, url), time.monotonic(), _cpu_s(pid)
    me1, load = time.process_time(), os.getloadavg()[0]
    stop.set()
    await asyncio.gather(*tasks, return_exceptions=True)
    frames = s1["frames"] - s0["frames"]
    lat = sorted(latencies)
    return {
        "clients": clients, "seconds": round(t1 - t0, 2), "frames": frames,
        "fps": frames / (t1 - t0), "cpu_s_per_frame": (cpu1 - cpu0) / frames if frames else None,
        "service_cpu_s": cpu1 - cpu0, "bench_clients_cpu_s": me1 - me0, "loadavg_1min_at_end": load,
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
        "bench_clients_cpu_s_loaded": loaded["bench_clients_cpu_s"],
        "loadavg_unloaded": unloaded["loadavg_1min_at_end"], "loadavg_loaded": loaded["loadavg_1min_at_end"],
        "rss_max_unloaded_mb": unloaded["rss_max_mb"], "rss_max_loaded_mb": loaded["rss_max_mb"],
        "latency_median_s": loaded["latency_median_s"], "latency_p95_s": loaded["latency_p95_s"],
        "ws_dropped": loaded["ws_dropped"], "sigterm_exit_s": round(stop_s, 2), "exit_code": rc,
    }
    return {"summary": summary, "unloaded": unloaded, "loaded": loaded}


# ---- end-to-end accuracy: the served lights against the true map -------------------------------------
SETTLE_FRAMES = 4
MAPS = ["studio_small_03_1k", "rooitou_park_1k", "potsdamer_platz_1k", "lebombo_1k", "dikhololo_night_1k",
        "interior_blender.exr"]


def upper_normals(n: int = 64) -> np.ndarray:
    """``n`` upward-facing normals (y >= 0): a spherical Fibonacci set on the upper hemisphere."""
    i = np.arange(n) + 0.5
    y = 1.0 - i / n  # uniform in y on [0, 1]: equal area on the hemisphere
    phi = np.pi * (1 + 5**0.5) * i
    r = np.sqrt(1 - y * y)
    return np.stack([r * np.sin(phi), y, -r * np.cos(phi)], axis=1)


def irradiance_truth(equirect: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """Diffuse irradiance (N, 3) from the map's upper hemisphere, exact pixel sums (float64):
    E(n) = sum over pixels with y > 0 of L * Omega_pixel * max(0, n . w)."""
    from device.sphere import equirect_directions, equirect_solid_angle

    h = equirect.shape[0]
    top = h // 2  # rows 0 .. h/2 - 1 are exactly the upper hemisphere
    d = equirect_directions(h)[:top].reshape(-1, 3)
    e = (equirect[:top].astype(np.float64) * equirect_solid_angle(h)[:top, :, None]).reshape(-1, 3)
    return np.maximum(normals @ d.T, 0.0) @ e


def irradiance_lights(lights: list[dict[str, Any]], normals: np.ndarray) -> np.ndarray:
    d = np.array([li["direction"] for li in lights], np.float64)
    rgb = np.array([li["rgb"] for li in lights], np.float64)
    return np.maximum(normals @ d.T, 0.0) @ rgb


def compare_irradiance(truth: np.ndarray, est: np.ndarray) -> dict[str, float]:
    """Relative error of luminance irradiance after the best global scale s (least squares on
    relative residuals), and s itself (1 = the lights are in the simulator's unit)."""
    w = np.array([0.2126, 0.7152, 0.0722])
    t, e = truth @ w, est @ w
    ok = t > 1e-12 * t.max()
    q = e[ok] / t[ok]
    s = float(q.sum() / (q * q).sum())
    rel = np.abs(s * q - 1.0)
    raw = np.abs(q - 1.0)
    return {"scale": 1.0 / s, "max_rel_err_scaled": float(rel.max()), "rms_rel_err_scaled": float(np.sqrt((rel**2).mean())),
            "max_rel_err_unscaled": float(raw.max())}


async def _accuracy_one(name: str, light_count: int) -> dict[str, Any]:
    import aiohttp

    from sim.scenarios import load_scene

    with tempfile.TemporaryDirectory(prefix="lp-acc-") as tmp:
        p, url = _start_service(Path(tmp) / "state", 10.0, light_count, scene=name)
        try:
            async with aiohttp.ClientSession() as session, session.ws_connect(url + "/api/v1/stream") as ws:
                first = json.loads((await ws.receive(timeout=400)).data)
                d = first
                while d["frame"] < first["frame"] + SETTLE_FRAMES:  # let the bracket planner adapt
                    d = json.loads((await ws.receive(timeout=120)).data)
        finally:
            p.send_signal(signal.SIGTERM)
            try:
                p.wait(10)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait(5)
    truth_map = load_scene(name).radiance_equirect(0.0)
    normals = upper_normals()
    cmp = compare_irradiance(irradiance_truth(truth_map, normals), irradiance_lights(d["lights"], normals))
    return {"map": name, "lights": len(d["lights"]), "unit": d["unit"], "method": d["method"],
            "frames_used": [first["frame"], d["frame"]], **cmp}


def run_accuracy(maps: list[str], light_count: int = 256) -> list[dict[str, Any]]:
    out = []
    for name in maps:
        out.append(asyncio.run(_accuracy_one(name, light_count)))
        print(json.dumps(out[-1]), file=sys.stderr, flush=True)
    return out


def run(out_dir: Path, quick: bool = False) -> dict[str, Any]:
    """Run the load benchmark (``quick``: 10 s phases, 10 clients) and the end-to-end accuracy
    check over the shared maps (``quick``: two maps)."""
    seconds, clients = (10.0, 10) if quick else (30.0, 50)
    result = asyncio.run(_bench(seconds, clients, fps=10.0, light_count=256))
    acc = run_accuracy(MAPS[:2] if quick else MAPS)
    result["accuracy"] = acc
    result["summary"]["accuracy_max_rel_err_scaled"] = max(a["max_rel_err_scaled"] for a in acc)
    result["summary"]["accuracy_scale_range"] = [min(a["scale"] for a in acc), max(a["scale"] for a in acc)]
    from bench.cli import machine_info

    result["machine"] = machine_info()
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "service.json").write_text(json.dumps(result, indent=2))
    _plot(result, out_dir / "service.png")
    return result
