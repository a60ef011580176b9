"""``lightprobe bench service``: start-up, reconnect and WebSocket load of the probe service.

Start-up and reconnect (``lightprobe.bench.service_startup``): exec -> API up -> first lights, cold (fresh
state dir: tables built) and warm (tables cached); fresh lights after a 5 s camera disconnect.

Load (bounded in time): ``lightprobe serve --camera sim --scene flashlight`` as a subprocess on
127.0.0.1 (the real pipeline on the simulator), three phases of equal length: ``unloaded`` (no
clients), ``loaded`` (N WebSocket clients), ``unloaded`` again (the two unloaded phases bracket
the loaded one, so drift in the machine's load shows). The clients run in a separate process at
``nice 19``: on a probe they are other machines, and here they must not take the two cores from
the service (their own CPU is reported). Per phase: pipeline fps (frames / wall time, from
``/status``), mean burst time (``timings.total``), the service's RSS (``/proc/PID/status`` VmRSS,
sampled each second), the service's CPU seconds per frame (``/proc/PID/stat``: the fan-out's cost
shows here even when the box is too busy for the fps ratio to mean much), and, loaded, messages
per client and frame-to-client latency (receive time - the light set's timestamp). Writes
``service.json`` and ``service.png``.

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

from lightprobe.core.sphere import LUMINANCE_WEIGHTS

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


def _start_service(state: Path, fps: float, light_count: int, scene: str = "flashlight",
                   cache: Path | None = None) -> tuple[subprocess.Popen[str], str]:
    cfg = state / "config.toml"
    state.mkdir(parents=True, exist_ok=True)
    if cache is not None and not (state / "cache").exists():  # share tables between services
        cache.mkdir(parents=True, exist_ok=True)
        (state / "cache").symlink_to(cache.resolve(), target_is_directory=True)
    cfg.write_text(f"[pipeline]\nfps = {fps!r}\nlight_count = {light_count}\n[mdns]\nenabled = false\n")
    p = subprocess.Popen([sys.executable, "-m", "lightprobe.cli", "serve", "--camera", "sim", "--scene", scene,
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


def _client_load(url: str, clients: int) -> None:
    """Entry point of the load process: ``clients`` WebSocket clients until stdin closes; prints
    one JSON line (messages per client, bytes, latency sample, own CPU)."""
    import threading

    import aiohttp

    async def main() -> dict[str, Any]:
        received = [0] * clients
        latencies: list[float] = []
        nbytes = [0]
        done = asyncio.Event()
        loop = asyncio.get_running_loop()
        threading.Thread(target=lambda: (sys.stdin.read(), loop.call_soon_threadsafe(done.set)),
                         daemon=True).start()

        async def client(session: Any, i: int) -> None:
            async with session.ws_connect(url + "/api/v1/stream", heartbeat=None) as ws:
                while not done.is_set():
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

        async with aiohttp.ClientSession() as session:
            await asyncio.gather(*(client(session, i) for i in range(clients)), return_exceptions=True)
        return {"received": received, "mbytes": nbytes[0] / 1e6, "latencies": latencies,
                "cpu_s": time.process_time()}

    print(json.dumps(asyncio.run(main())), flush=True)


def _spawn_clients(url: str, clients: int) -> subprocess.Popen[str]:
    code = f"from lightprobe.bench.service import _client_load; _client_load({url!r}, {clients})"
    return subprocess.Popen([sys.executable, "-c", code], cwd=ROOT, env={**os.environ, "PYTHONPATH": str(ROOT)},
                            stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True,
                            preexec_fn=lambda: os.nice(19))


async def _phase(session: Any, url: str, pid: int, seconds: float, clients: int) -> dict[str, Any]:
    proc = _spawn_clients(url, clients) if clients else None
    t_wait = time.monotonic()
    while proc is not None and time.monotonic() - t_wait < 60:  # all connected before counting
        if (await _status(session, url))["websocket"]["clients"] >= clients:
            break
        await asyncio.sleep(0.2)
    s0, t0, cpu0 = await _status(session, url), time.monotonic(), _cpu_s(pid)
    rss, totals, seen, conns = [], [], s0["frame"], []
    while time.monotonic() - t0 < seconds:
        await asyncio.sleep(1.0)
        rss.append(_rss_mb(pid))
        st = await _status(session, url)
        conns.append(st["websocket"]["clients"])
        if st["frame"] != seen:
            seen = st["frame"]
            totals.append(st["timings"].get("total", float("nan")))
    s1, t1, cpu1 = await _status(session, url), time.monotonic(), _cpu_s(pid)
    load = os.getloadavg()[0]
    got: dict[str, Any] = {}
    if proc is not None:
        out, _ = await asyncio.to_thread(proc.communicate, "", 60)  # EOF on stdin: stop
        got = json.loads(out.strip().splitlines()[-1])
    frames = s1["frames"] - s0["frames"]
    lat = sorted(got.get("latencies", []))
    received = got.get("received", [])
    return {
        "clients": clients, "seconds": round(t1 - t0, 2), "frames": frames,
        "fps": frames / (t1 - t0), "cpu_s_per_frame": (cpu1 - cpu0) / frames if frames else None,
        "service_cpu_s": cpu1 - cpu0, "bench_clients_cpu_s": got.get("cpu_s"), "loadavg_1min_at_end": load,
        "burst_time_mean_s": sum(totals) / len(totals) if totals else None,
        "rss_mb": rss, "rss_max_mb": max(rss) if rss else None,
        "clients_connected_min": min(conns) if conns else None,
        "messages_per_client_min": min(received) if received else None,
        "messages_per_client_max": max(received) if received else None,
        "mbytes_sent": got.get("mbytes", 0.0),
        "latency_median_s": lat[len(lat) // 2] if lat else None,
        "latency_p95_s": lat[int(0.95 * (len(lat) - 1))] if lat else None,
        "ws_dropped": s1["websocket"]["dropped"], "ws_frames_skipped": s1["websocket"]["frames_skipped"],
    }


def _plot(result: dict[str, Any], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = ["unloaded", "loaded", "unloaded_after"]
    fig, ax = plt.subplots(1, 3, figsize=(14, 3.6))
    for name in names:
        ph = result[name]
        ax[0].plot(ph["rss_mb"], label=f"{name} ({ph['clients']} clients)")
    ax[0].set_xlabel("time in phase (s)")
    ax[0].set_ylabel("service RSS (MB)")
    ax[0].legend()
    ax[0].set_title("memory")
    ax[1].bar(names, [result[n]["fps"] for n in names], color=["#888", "#f2b33d", "#888"])
    ax[1].set_ylabel("pipeline fps")
    ax[1].set_title(f"fps ratio loaded/unloaded = {result['summary']['fps_ratio']:.3f}")
    st = result.get("startup", {})
    kinds = [k for k in ("cold", "warm") if st.get(k)]
    for i, key in enumerate(("api_s", "lights_s")):
        ax[2].bar([x + 0.4 * i for x in range(len(kinds))], [st[f"{k}_summary"][key]["min"] for k in kinds],
                  width=0.4, label=key)
    ax[2].set_xticks([x + 0.2 for x in range(len(kinds))], kinds)
    ax[2].set_ylabel("s after exec (min of runs)")
    ax[2].set_title("start-up")
    ax[2].legend()
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


async def _bench(seconds: float, clients: int, fps: float, light_count: int, cache: Path) -> dict[str, Any]:
    import aiohttp

    with tempfile.TemporaryDirectory(prefix="lp-bench-") as tmp:
        p, url = _start_service(Path(tmp) / "state", fps, light_count, cache=cache)
        try:
            async with aiohttp.ClientSession() as session:
                t_start = time.monotonic()
                while True:  # warm-up: first bursts, bracket settled
                    st = await _status(session, url)
                    if st["frames"] >= 3:
                        break
                    if time.monotonic() - t_start > 400:
                        raise RuntimeError("no frames within 400 s")
                    await asyncio.sleep(0.5)
                warmup = time.monotonic() - t_start
                unloaded = await _phase(session, url, p.pid, seconds, 0)
                loaded = await _phase(session, url, p.pid, seconds, clients)
                after = await _phase(session, url, p.pid, seconds, 0)
            t_stop = time.monotonic()
            p.send_signal(signal.SIGTERM)
            rc = p.wait(10)
            stop_s = time.monotonic() - t_stop
        finally:
            if p.poll() is None:
                p.kill()
                p.wait(5)
    base = 0.5 * (unloaded["fps"] + after["fps"])
    ratio = loaded["fps"] / base if base else float("nan")
    cpu_base = [x["cpu_s_per_frame"] for x in (unloaded, after) if x["cpu_s_per_frame"] is not None]
    summary = {
        "clients": clients, "phase_seconds": seconds, "light_count": light_count, "fps_target": fps,
        "warmup_to_3_frames_s": round(warmup, 1),
        "fps_unloaded": round(unloaded["fps"], 3), "fps_loaded": round(loaded["fps"], 3),
        "fps_unloaded_after": round(after["fps"], 3), "fps_ratio": round(ratio, 3),
        "burst_time_unloaded_s": unloaded["burst_time_mean_s"], "burst_time_loaded_s": loaded["burst_time_mean_s"],
        "cpu_s_per_frame_unloaded": sum(cpu_base) / len(cpu_base) if cpu_base else None,
        "cpu_s_per_frame_loaded": loaded["cpu_s_per_frame"],
        "bench_clients_cpu_s_loaded": loaded["bench_clients_cpu_s"],
        "loadavg_unloaded": unloaded["loadavg_1min_at_end"], "loadavg_loaded": loaded["loadavg_1min_at_end"],
        "rss_max_unloaded_mb": unloaded["rss_max_mb"], "rss_max_loaded_mb": loaded["rss_max_mb"],
        "rss_max_unloaded_after_mb": after["rss_max_mb"],
        "clients_connected_min": loaded["clients_connected_min"],
        "messages_per_client_min": loaded["messages_per_client_min"],
        "latency_median_s": loaded["latency_median_s"], "latency_p95_s": loaded["latency_p95_s"],
        "ws_dropped": loaded["ws_dropped"], "sigterm_exit_s": round(stop_s, 2), "exit_code": rc,
    }
    return {"summary": summary, "unloaded": unloaded, "loaded": loaded, "unloaded_after": after}


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
    from lightprobe.core.sphere import equirect_directions, equirect_solid_angle

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
    w = LUMINANCE_WEIGHTS
    t, e = truth @ w, est @ w
    ok = t > 1e-12 * t.max()
    q = e[ok] / t[ok]
    s = float(q.sum() / (q * q).sum())
    rel = np.abs(s * q - 1.0)
    raw = np.abs(q - 1.0)
    return {"scale": 1.0 / s, "max_rel_err_scaled": float(rel.max()), "rms_rel_err_scaled": float(np.sqrt((rel**2).mean())),
            "max_rel_err_unscaled": float(raw.max())}


async def _accuracy_one(name: str, light_count: int, cache: Path | None = None) -> dict[str, Any]:
    import aiohttp

    from lightprobe.bench.service_startup import stop_service
    from lightprobe.sim.scenarios import load_scene

    with tempfile.TemporaryDirectory(prefix="lp-acc-") as tmp:
        p, url = _start_service(Path(tmp) / "state", 10.0, light_count, scene=name, cache=cache)
        try:
            async with aiohttp.ClientSession() as session, session.ws_connect(url + "/api/v1/stream") as ws:
                first = json.loads((await ws.receive(timeout=400)).data)
                d = first
                while d["frame"] < first["frame"] + SETTLE_FRAMES:  # let the bracket planner adapt
                    d = json.loads((await ws.receive(timeout=120)).data)
        finally:
            stop_service(p)
    truth_map = load_scene(name).radiance_equirect(0.0)
    normals = upper_normals()
    cmp = compare_irradiance(irradiance_truth(truth_map, normals), irradiance_lights(d["lights"], normals))
    return {"map": name, "lights": len(d["lights"]), "unit": d["unit"], "method": d["method"],
            "frames_used": [first["frame"], d["frame"]], **cmp}


def run_accuracy(maps: list[str], light_count: int = 256, cache: Path | None = None) -> list[dict[str, Any]]:
    out = []
    for name in maps:
        out.append(asyncio.run(_accuracy_one(name, light_count, cache)))
        print(json.dumps(out[-1]), file=sys.stderr, flush=True)
    return out


def run(out_dir: Path, quick: bool = False) -> dict[str, Any]:
    """Start-up (cold / warm exec -> API -> first lights), reconnect after a 5 s disconnect, the
    load benchmark and the end-to-end accuracy over the shared maps.

    Full: 3 cold and 8 warm starts, 3 reconnects, 30 s phases with 50 clients, all six maps.
    ``quick`` (< 1 min on a quiet machine): 1 cold and 3 warm starts, 1 reconnect, 6 s phases
    with 10 clients, no accuracy runs."""
    from lightprobe.bench.service_startup import reconnect_latency, startup_summary

    seconds, clients = (6.0, 10) if quick else (30.0, 50)
    startup = startup_summary(reps_warm=3 if quick else 8, reps_cold=1 if quick else 3)
    reconnect = reconnect_latency(1 if quick else 3)
    with tempfile.TemporaryDirectory(prefix="lp-bench-cache-") as cache:
        result = asyncio.run(_bench(seconds, clients, fps=10.0, light_count=256, cache=Path(cache)))
        acc = [] if quick else run_accuracy(MAPS, cache=Path(cache))
    result["startup"], result["reconnect"] = startup, reconnect
    summ = result["summary"]
    for kind in ("cold", "warm"):
        for key in ("api_s", "lights_s", "api_to_lights_s", "service_cpu_s"):
            summ[f"startup_{kind}_{key}"] = startup[f"{kind}_summary"][key]
    summ["startup_loadavg"] = [round(r["loadavg_1min"], 2) for r in startup["warm"]]
    summ["reconnect_resume_s"] = reconnect["resume_s"]
    summ["reconnect_first_burst_capture_s"] = reconnect["first_burst_capture_s"]
    if acc:
        result["accuracy"] = acc
        summ["accuracy_max_rel_err_scaled"] = max(a["max_rel_err_scaled"] for a in acc)
        summ["accuracy_scale_range"] = [min(a["scale"] for a in acc), max(a["scale"] for a in acc)]
    from lightprobe.bench.machine import machine_info

    result["machine"] = machine_info()
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "service.json").write_text(json.dumps(result, indent=2))
    _plot(result, out_dir / "service.png")
    return result
