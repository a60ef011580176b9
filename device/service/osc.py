"""OSC output (``[osc] targets`` or ``lightprobe serve --osc udp://HOST:PORT``, repeatable; off by
default): the live lighting as Open Sound Control messages over UDP, for Unreal Engine's OSC
plugin, TouchDesigner's OSC In and any other OSC host.

Per published light set (every set by default; ``[osc] rate`` caps the sets per second, the
newest wins), one OSC message per address below, in this order, to every target. All under
``/lightprobe/<probe id>/``; floats are 32-bit, ``d`` a 64-bit double (times), ``i`` a 32-bit
int. Directions point *towards* the light, unit vectors in the light sets' probe frame (+y up,
CONVENTIONS.md), exactly as ``/api/v1/lights`` and ``/api/v1/sh`` give them; the probe's pose in
the room travels beside them (``pose``), so a host converts both to its own axes (README: "OSC").

=============================  ======  ======================================================
address (after the prefix)     types   value
=============================  ======  ======================================================
``frame``                      i       the set's frame number (first: a host may group by it)
``captured``                   d       wall-clock s, middle of the newest frame's exposure
``timestamp``                  d       wall-clock s, when the set was published
``stale``                      i       1 while the camera is away (these are the last lights)
``settling``                   i       1 in the first frames after start
``primary/direction``          fff     the primary light's direction (0 1 0 when there is none)
``primary/color``              fff     its colour, linear RGB scaled to a largest channel of 1
``primary/intensity``          f       its luminance (rgb's Y: lux on a surface facing it in
                                       ``nit`` units; 0 when there is none)
``primary/rgb``                fff     its rgb (radiance x solid angle, the unit of ``unit``)
``sh/ambient``                 27 f    the SH without the primary light, three.js convention
                                       (coefficient-major: c0 r g b, c1 r g b, ...)
``sh/all``                     27 f    the SH of all light, same layout
``illuminance``                f       on a horizontal surface at the probe (as MQTT's sensor)
``cct``                        f       that light's correlated colour temperature, K (sent only
                                       when defined)
``pose``                       12 f    world-from-probe rotation (row-major 3x3) then position
``unit``                       s       ``relative`` or ``nit``
=============================  ======  ======================================================

UDP costs the pipeline nothing it waits on: a target that is down (ICMP refused) or a name that
does not resolve is retried each second, counted in ``stats()``, never raised.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import time
import urllib.parse
from dataclasses import dataclass
from typing import Any

import numpy as np

from lightprobe.core.errors import InputError

__all__ = ["ADDRESSES", "OscSender", "OscSettings", "osc_messages", "parse_osc_target"]

log = logging.getLogger(__name__)

# every address a set is sent on, in order ("cct" only when defined)
ADDRESSES = ("frame", "captured", "timestamp", "stale", "settling", "primary/direction", "primary/color",
             "primary/intensity", "primary/rgb", "sh/ambient", "sh/all", "illuminance", "cct", "pose", "unit")


def parse_osc_target(url: str, param: str = "osc") -> tuple[str, int]:
    """``udp://HOST:PORT`` (an IPv6 host in brackets) -> (host, port); bad input names ``param``."""
    u = urllib.parse.urlsplit(str(url).strip())
    try:
        port = u.port
    except ValueError:
        port = None
    if u.scheme != "udp" or not u.hostname or port is None or not 0 < port < 65536 or u.path not in ("", "/"):
        raise InputError(f"{param}={url!r} is not udp://HOST:PORT", param=param)
    return u.hostname, port


@dataclass(frozen=True)
class OscSettings:
    targets: tuple[tuple[str, int], ...]
    rate: float = 0.0  # sets per second at most; 0 = every set

    @classmethod
    def from_config(cls, cfg: Any, urls: list[str] | None = None) -> OscSettings | None:
        """``[osc]`` with ``--osc`` URLs (they replace ``[osc] targets``); ``None`` when off."""
        chosen = list(urls) if urls else list(cfg.get("osc", "targets"))
        param = "--osc" if urls else "osc.targets"
        if not chosen:
            return None
        return cls(tuple(parse_osc_target(u, param) for u in chosen), float(cfg.get("osc", "rate")))


def _f(values: Any) -> list[float]:
    return [float(v) if math.isfinite(float(v)) else 0.0 for v in np.asarray(values, np.float64).reshape(-1)]


def osc_messages(prefix: str, lights: Any, env: Any, illuminance_rgb: np.ndarray | None) -> list[bytes]:
    """The OSC messages of one set (module docstring), as datagrams. ``lights``: the published
    :class:`lightprobe.core.lightset.LightSet`; ``env``: its frame's SH + primary light
    (:class:`lightprobe.device.formats.sh_primary.Environment`, canonical) or ``None``;
    ``illuminance_rgb``: :func:`lightprobe.device.sensors.horizontal_illuminance` of its map."""
    from pythonosc.osc_message_builder import OscMessageBuilder

    from lightprobe.core.sh import to_convention
    from lightprobe.core.sphere import LUMINANCE_WEIGHTS
    from lightprobe.device.sensors import cct_mccamy

    out: list[bytes] = []

    def send(address: str, *args: tuple[Any, str]) -> None:
        b = OscMessageBuilder(address=f"{prefix}/{address}")
        for value, kind in args:
            b.add_arg(value, kind)
        out.append(b.build().dgram)

    captured = lights.captured if lights.captured is not None else lights.timestamp
    send("frame", (int(lights.frame) & 0x7FFFFFFF, "i"))
    send("captured", (float(captured), "d"))
    send("timestamp", (float(lights.timestamp), "d"))
    send("stale", (int(bool(lights.stale)), "i"))
    send("settling", (int(bool(lights.settling)), "i"))
    prim = None if env is None else env.primary
    if prim is not None:
        rgb = np.asarray(prim.rgb, np.float64)
        direction, peak = np.asarray(prim.direction, np.float64), float(rgb.max())
        colour = rgb / peak if peak > 0 else np.ones(3)
        intensity = float(rgb @ LUMINANCE_WEIGHTS)
    else:
        direction, colour, rgb, intensity = np.array([0.0, 1.0, 0.0]), np.ones(3), np.zeros(3), 0.0
    send("primary/direction", *[(v, "f") for v in _f(direction)])
    send("primary/color", *[(v, "f") for v in _f(colour)])
    send("primary/intensity", (intensity if math.isfinite(intensity) else 0.0, "f"))
    send("primary/rgb", *[(v, "f") for v in _f(rgb)])
    if env is not None:
        send("sh/ambient", *[(v, "f") for v in _f(to_convention(env.ambient, "threejs"))])
        send("sh/all", *[(v, "f") for v in _f(to_convention(env.coefficients, "threejs"))])
    if illuminance_rgb is not None:
        e = float(np.asarray(illuminance_rgb, np.float64) @ LUMINANCE_WEIGHTS)
        send("illuminance", (e if math.isfinite(e) else 0.0, "f"))
        cct = cct_mccamy(illuminance_rgb)
        if cct is not None:
            send("cct", (float(cct), "f"))
    pose = lights.pose or {}
    rot = np.asarray(pose.get("rotation", np.eye(3)), np.float64).reshape(3, 3)
    pos = np.asarray(pose.get("position", [0.0, 0.0, 0.0]), np.float64).reshape(3)
    send("pose", *[(v, "f") for v in _f(np.concatenate([rot.reshape(-1), pos]))])
    send("unit", (str(lights.unit), "s"))
    return out


class _Target:
    """One UDP destination: its socket, opened on first use and again after a failure."""

    def __init__(self, host: str, port: int) -> None:
        self.host, self.port = host, port
        self.transport: asyncio.DatagramTransport | None = None
        self.retry_at = 0.0
        self.sent = 0
        self.errors = 0
        self.last_error: str | None = None

    async def send(self, datagrams: list[bytes]) -> None:
        if self.transport is None or self.transport.is_closing():
            if time.monotonic() < self.retry_at:
                return
            try:
                self.transport, _ = await asyncio.get_running_loop().create_datagram_endpoint(
                    asyncio.DatagramProtocol, remote_addr=(self.host, self.port))
            except OSError as e:  # a name that does not resolve, no route: try again in a second
                self._failed(e)
                return
        try:
            for d in datagrams:
                self.transport.sendto(d)
            self.sent += 1
        except OSError as e:
            self._failed(e)

    def _failed(self, e: OSError) -> None:
        self.errors += 1
        if self.last_error != str(e):
            log.info("osc: udp://%s:%d: %s (retrying)", self.host, self.port, e)
        self.last_error = str(e)
        self.retry_at = time.monotonic() + 1.0
        if self.transport is not None:
            self.transport.close()
            self.transport = None

    def close(self) -> None:
        if self.transport is not None:
            self.transport.close()
            self.transport = None


class OscSender:
    """Send each published set of the service ``st`` (:class:`ServiceState`) to the targets of
    ``settings`` until :meth:`stop`."""

    def __init__(self, st: Any, settings: OscSettings) -> None:
        self.st, self.settings = st, settings
        self.prefix = f"/lightprobe/{st.probe_id}"
        self.targets = [_Target(h, p) for h, p in settings.targets]
        self.sets_sent = 0
        self.sets_dropped = 0  # sets the sender fell too far behind to send
        self._queue: asyncio.Queue[tuple[Any, Any]] = asyncio.Queue(maxsize=8)
        self._task: asyncio.Task[None] | None = None

    def start(self) -> None:
        self._task = asyncio.create_task(self.run(), name="osc")

    async def stop(self) -> None:
        if self._task is not None:
            self._task.cancel()
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await self._task
            self._task = None
        for t in self.targets:
            t.close()

    def stats(self) -> dict[str, Any]:
        return {"targets": [{"url": f"udp://{t.host}:{t.port}", "sent": t.sent, "errors": t.errors,
                             "last_error": t.last_error} for t in self.targets],
                "sets_sent": self.sets_sent, "sets_dropped": self.sets_dropped, "rate": self.settings.rate}

    def _on_set(self, lights: Any, result: Any) -> None:
        """The runner's listener: every published set, in order (a lagging sender drops the
        oldest it holds, never the newest)."""
        q = self._queue
        if q.full():
            q.get_nowait()
            self.sets_dropped += 1
        q.put_nowait((lights, result))

    async def run(self) -> None:
        from lightprobe.device.sensors import horizontal_illuminance

        runner = self.st.runner
        interval = 1.0 / self.settings.rate if self.settings.rate > 0 else 0.0
        last = -math.inf
        runner.listeners.append(self._on_set)
        try:
            while True:
                lights, result = await self._queue.get()
                if interval:
                    wait = interval - (time.monotonic() - last)
                    if wait > 0:
                        await asyncio.sleep(wait)
                    while not self._queue.empty():  # the newest set when the interval is over
                        lights, result = self._queue.get_nowait()
                try:
                    env = await runner.environment(result, lights)
                    equirect = getattr(result, "equirect", None)
                    e_rgb = None if equirect is None else await asyncio.to_thread(horizontal_illuminance, equirect)
                    datagrams = osc_messages(self.prefix, lights, env, e_rgb)
                except Exception:  # a bad frame costs OSC that frame, nothing else
                    log.exception("osc: messages for frame %s failed", getattr(lights, "frame", None))
                    continue
                last = time.monotonic()
                for t in self.targets:
                    await t.send(datagrams)
                self.sets_sent += 1
        finally:
            with contextlib.suppress(ValueError):
                runner.listeners.remove(self._on_set)
