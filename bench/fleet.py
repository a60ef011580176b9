"""``lightprobe bench fleet [--quick]``: 50 lightweight simulated probes at 10 Hz through one local
mosquitto, one host merging them all (``MergedStream("mqtt://...")``).

Each simulated probe is the service's own :class:`lightprobe.device.service.mqtt.MqttPublisher` (same
topics, will, rate limits and payloads) over a synthetic source: a light set of ``lights`` lights
whose directions turn slowly, stamped with the wall clock when it is published to the probe's
hub. The probes run in a child process (one asyncio loop for all 50), the host in this one, so
the host's CPU is its own. End-to-end latency = the time a merged set containing a probe's frame
is yielded minus that frame's timestamp, over every (merge, probe with a new frame) pair.
Reported: p50 / p99 / max latency, merged sets per second, frames received against published,
and CPU seconds per wall second of the broker, the host and the probe process.
"""

from __future__ import annotations

import asyncio
import json
import math
import os
import shutil
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from lightprobe.core.lightset import LightSet

ROOT = Path(__file__).resolve().parent.parent


class SyntheticProbe:
    """A probe without a camera: a :class:`~lightprobe.device.service.runner.FrameHub` fed at ``rate`` Hz
    with a small light set. Implements :class:`lightprobe.device.service.mqtt.Source`."""

    def __init__(self, probe_id: str, rate: float = 10.0, lights: int = 16, seed: int = 0) -> None:
        from lightprobe.device.service.runner import FrameHub

        self.probe_id, self.rate, self.n = probe_id, float(rate), int(lights)
        self.hub = FrameHub()
        rng = np.random.default_rng(seed)
        d = rng.normal(size=(self.n, 3))
        d[:, 1] = np.abs(d[:, 1])
        self.dirs = d / np.linalg.norm(d, axis=1, keepdims=True)
        self.rgb = rng.uniform(0.5, 2.0, (self.n, 3))
        self.frame = 0
        self.position = rng.uniform(-5, 5, 3).round(3)

    def lightset(self) -> LightSet:
        a = 0.05 * self.frame
        c, s = math.cos(a), math.sin(a)
        rot = np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
        d = self.dirs @ rot.T
        return LightSet(d, self.rgb, np.full(self.n, 0.05), probe=self.probe_id,
                        frame=self.frame, timestamp=time.time(), method="pharr", unit="relative",
                        pose={"rotation": np.eye(3).tolist(), "position": self.position.tolist()})

    async def run(self, seconds: float) -> None:
        t0 = time.monotonic()
        period = 1.0 / self.rate
        k = 0
        while time.monotonic() - t0 < seconds:
            self.frame += 1
            await self.hub.publish(json.dumps(self.lightset().to_json(), separators=(",", ":")))
            k += 1
            await asyncio.sleep(max(0.0, t0 + k * period - time.monotonic()))

    # ---- lightprobe.device.service.mqtt.Source -----------------------------------------------------------
    def status(self) -> dict[str, Any]:
        return {"version": 1, "probe": self.probe_id, "state": "online", "name": f"sim {self.probe_id}",
                "model": "lightprobe-fleet-sim", "sw_version": "0", "sampler": "pharr", "health": "ok",
                "url": "", "timestamp": time.time()}

    def unit(self) -> str:
        return "relative"

    async def sh(self) -> bytes | None:
        return None

    async def sensors(self) -> dict[str, Any] | None:
        return None


async def run_fleet(url: str, count: int, rate: float, seconds: float, lights: int = 16,
                    discovery: bool = False, keepalive: int = 10) -> dict[str, Any]:
    """Run ``count`` synthetic probes publishing to ``url`` for ``seconds``; then stop them
    cleanly (each publishes ``offline``)."""
    from lightprobe.core.mqtt_topics import parse_broker_url
    from lightprobe.device.service.mqtt import MqttPublisher
    from lightprobe.device.service.mqtt_settings import MqttSettings

    settings = MqttSettings(parse_broker_url(url), lights_rate=rate, sh_rate=0.0, sensors_rate=0.2,
                            discovery=discovery, keepalive=keepalive)
    probes = [SyntheticProbe(f"fleet{k:03d}", rate, lights, seed=k) for k in range(count)]
    pubs = [MqttPublisher(p, settings) for p in probes]
    for pub in pubs:
        pub.start()
    t_end = time.monotonic() + 15
    while not all(p.connected for p in pubs) and time.monotonic() < t_end:  # noqa: ASYNC110 (a poll of 50 flags)
        await asyncio.sleep(0.05)
    await asyncio.gather(*(p.run(seconds) for p in probes))
    await asyncio.gather(*(pub.stop() for pub in pubs))
    return {"published": sum(p.counters.published.get("lights", 0) for p in pubs),
            "frames": sum(p.frame for p in probes)}


def _fleet_main() -> None:  # the child process: python -m lightprobe.bench.fleet URL COUNT RATE SECONDS [KEEPALIVE]
    url, count, rate, seconds = sys.argv[1], int(sys.argv[2]), float(sys.argv[3]), float(sys.argv[4])
    keepalive = int(sys.argv[5]) if len(sys.argv) > 5 else 10
    t0 = time.process_time()
    out = asyncio.run(run_fleet(url, count, rate, seconds, keepalive=keepalive))
    out["cpu_s"] = time.process_time() - t0
    print(json.dumps(out), flush=True)


# ---- a broker for tests and benchmarks --------------------------------------------------------------
def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class Mosquitto:
    """Debian's ``mosquitto`` on 127.0.0.1:PORT, no persistence, anonymous (for loopback only)."""

    def __init__(self, port: int | None = None) -> None:
        self.port = port or free_port()
        self.dir = Path(tempfile.mkdtemp(prefix="lightprobe-mosquitto-"))
        self.proc: subprocess.Popen[bytes] | None = None

    @property
    def url(self) -> str:
        return f"mqtt://127.0.0.1:{self.port}"

    def start(self) -> Mosquitto:
        exe = shutil.which("mosquitto") or "/usr/sbin/mosquitto"
        conf = self.dir / "mosquitto.conf"
        conf.write_text(f"listener {self.port} 127.0.0.1\nallow_anonymous true\npersistence false\n"
                        "max_queued_messages 1000\nlog_dest stderr\nlog_type error\n")
        self.proc = subprocess.Popen([exe, "-c", str(conf)], stdout=subprocess.DEVNULL,
                                     stderr=open(self.dir / "log", "wb"))  # noqa: SIM115
        t_end = time.monotonic() + 10
        while time.monotonic() < t_end:
            with socket.socket() as s:
                if s.connect_ex(("127.0.0.1", self.port)) == 0:
                    return self
            if self.proc.poll() is not None:
                raise RuntimeError(f"mosquitto exited: {(self.dir / 'log').read_text()}")
            time.sleep(0.02)
        raise RuntimeError("mosquitto did not listen within 10 s")

    def cpu_seconds(self) -> float:
        assert self.proc is not None
        f = Path(f"/proc/{self.proc.pid}/stat").read_text().rsplit(")", 1)[1].split()
        return (int(f[11]) + int(f[12])) / os.sysconf("SC_CLK_TCK")

    def stop(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(5)
            except subprocess.TimeoutExpired:
                self.proc.kill()
        shutil.rmtree(self.dir, ignore_errors=True)

    def __enter__(self) -> Mosquitto:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()


async def measure(url: str, count: int, rate: float, seconds: float) -> dict[str, Any]:
    """Start the fleet in a child process and merge it here; latency and CPU figures."""
    from lightprobe.hostlink.stream import MergedStream

    lat: list[float] = []
    merges = 0
    seen: dict[str, int] = {}
    received = 0
    cpu0 = time.process_time()
    async with MergedStream(url, count=64, method="index", stale_after=2.0) as ms:
        child = await asyncio.create_subprocess_exec(
            sys.executable, "-m", "lightprobe.bench.fleet", url, str(count), str(rate), str(seconds),
            stdout=asyncio.subprocess.PIPE, cwd=str(ROOT))
        t_start = time.monotonic()
        cpu_start = time.process_time()
        full = 0
        try:
            async for merged in ms.updates(idle=5.0):
                now = time.time()
                merges += 1
                for pid, ls in ms.latest().items():
                    if seen.get(pid) != ls.frame:
                        seen[pid] = ls.frame
                        received += 1
                        lat.append(now - ls.timestamp)
                full = max(full, len(merged.extra.get("merged_from", [])))
                if time.monotonic() - t_start > seconds + 1.0:
                    break
        except TimeoutError:
            pass
        wall = time.monotonic() - t_start
        host_cpu = time.process_time() - cpu_start
        out, _ = await child.communicate()
    fleet = json.loads(out.decode().strip().splitlines()[-1])
    a = np.array(lat) * 1e3
    return {"probes": count, "rate_hz": rate, "seconds": seconds,
            "latency_ms": {"p50": round(float(np.percentile(a, 50)), 1),
                           "p99": round(float(np.percentile(a, 99)), 1),
                           "max": round(float(a.max()), 1)} if len(a) else None,
            "merged_sets_per_s": round(merges / wall, 1), "max_probes_in_one_merge": full,
            "frames_published": fleet["published"], "frames_seen_by_host": received,
            "host_cpu_per_s": round(host_cpu / wall, 3), "fleet_cpu_per_s": round(fleet["cpu_s"] / wall, 3),
            "host_cpu_total_s": round(time.process_time() - cpu0, 2)}


class Subscriber:
    """``mosquitto_sub -v`` on topics (QoS 1), lines collected with their arrival
    (``time.monotonic``) by a reader thread: ``lines`` is a list of (t, topic, payload). Used by
    :func:`measure_start` and by ``tests/test_mqtt.py``."""

    def __init__(self, url: str, *topics: str) -> None:
        import threading

        host, _, port = url.removeprefix("mqtt://").partition(":")
        args = ["mosquitto_sub", "-h", host, "-p", port or "1883", "-v", "-q", "1"]
        for t in topics:
            args += ["-t", t]
        self.proc = subprocess.Popen(args, stdout=subprocess.PIPE, text=True)
        self.lines: list[tuple[float, str, str]] = []
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            t, _, payload = line.rstrip("\n").partition(" ")
            self.lines.append((time.monotonic(), t, payload))

    def wait(self, pred: Any, timeout: float) -> tuple[float, str, str]:
        """The first line (from the start) whose ``pred(topic, payload)`` holds; TimeoutError
        naming the topics seen if none comes within ``timeout`` s."""
        end = time.monotonic() + timeout
        k = 0
        while time.monotonic() < end:
            while k < len(self.lines):
                if pred(self.lines[k][1], self.lines[k][2]):
                    return self.lines[k]
                k += 1
            time.sleep(0.005)
        raise TimeoutError(f"no matching message within {timeout} s; got topics "
                           f"{sorted({t for _, t, _ in self.lines})}")

    def close(self) -> None:
        self.proc.terminate()
        self.proc.wait(5)


def measure_start(url: str, runs: int = 3) -> dict[str, Any]:
    """The real service (``lightprobe serve --camera sim --mqtt URL``) started as a user starts it,
    ``mosquitto_sub -t 'lightprobe/#'`` already running: exec -> the retained ``online`` status,
    exec -> the first light set, the first light set's own timestamp -> its arrival at the
    subscriber (the MQTT path alone), and a subscriber started later -> the retained lights.
    The first start (projection tables, kernel caches) is run and reported apart; ``runs`` warm
    starts follow on the same state dir."""
    with tempfile.TemporaryDirectory() as tmp:
        state = Path(tmp) / "state"
        state.mkdir()
        (state / "config.toml").write_text('[mdns]\nenabled = false\n[probe]\nid = "start-1"\n')
        env = {**os.environ, "PYTHONUNBUFFERED": "1"}
        rows = []
        for k in range(runs + 1):
            sub = Subscriber(url, "lightprobe/start-1/#")
            time.sleep(0.3)  # the subscriber is connected before the probe starts
            sub.lines.clear()  # retained messages of the previous run
            wall_minus_mono = time.time() - time.monotonic()
            t0 = time.monotonic()
            p = subprocess.Popen([sys.executable, "-m", "lightprobe.cli", "serve", "--camera", "sim", "--port", "0",
                                  "--state-dir", str(state), "--mqtt", url, "--log-format", "json"],
                                 cwd=str(ROOT), env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
            try:
                online = sub.wait(lambda t, b: t.endswith("/status") and '"online"' in b, 120)
                lights = sub.wait(lambda t, b: t.endswith("/lights"), 120)
                stamp = json.loads(lights[2])["timestamp"]
                late = Subscriber(url, "lightprobe/start-1/lights")
                t_late = time.monotonic()
                got = late.wait(lambda t, b: True, 10)
                late.close()
            finally:
                p.terminate()
                p.wait(15)
                sub.close()
            rows.append({"warm": k > 0, "exec_to_online_s": round(online[0] - t0, 3),
                         "exec_to_first_lights_s": round(lights[0] - t0, 3),
                         "lights_timestamp_to_subscriber_ms": round(1e3 * (lights[0] + wall_minus_mono - stamp), 1),
                         "late_subscriber_to_retained_lights_ms": round(1e3 * (got[0] - t_late), 1)})
    return {"runs": rows}


def run(out_dir: Path, quick: bool) -> dict[str, Any]:
    count, rate, seconds = (50, 10.0, 5.0) if quick else (50, 10.0, 20.0)
    with Mosquitto() as broker:
        b0 = broker.cpu_seconds()
        t0 = time.monotonic()
        res = asyncio.run(measure(broker.url, count, rate, seconds))
        res["broker_cpu_per_s"] = round((broker.cpu_seconds() - b0) / (time.monotonic() - t0), 3)
        res["probe_start"] = measure_start(broker.url, 1 if quick else 3)
    res["summary"] = {"latency_ms": res["latency_ms"], "merged_sets_per_s": res["merged_sets_per_s"],
                      "host_cpu_per_s": res["host_cpu_per_s"], "broker_cpu_per_s": res["broker_cpu_per_s"],
                      "probe_start": res["probe_start"]["runs"]}
    (out_dir / "fleet.json").write_text(json.dumps(res, indent=2))
    return res


if __name__ == "__main__":
    _fleet_main()
