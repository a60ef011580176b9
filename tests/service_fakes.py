"""TEST-ONLY stand-in for ``device.pipeline.Pipeline`` while the real glue is being written.

It implements the agreed Pipeline API over a synthetic scene (a sky gradient plus a sun disc that
moves with the frame number) and a trivial energy-conserving sampler (equal row/column blocks).
It is never used by the service itself; integration tests switch to the real
``device.pipeline.Pipeline`` + ``sim.camera.SimCamera`` when those exist (see ``real_pipeline``).
``FakeCamera.disconnect(seconds)`` makes capture fail with CameraDisconnected and open fail with
CameraUnavailable for that long: the same observable behaviour as the simulator's fault switch.
"""

from __future__ import annotations

import asyncio
import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from device.sampling.base import LightSet
from device.sphere import equirect_directions, equirect_solid_angle, luminance
from drivers.base import CameraDisconnected, CameraUnavailable


@dataclass
class FakeFrameResult:
    frame: int
    timestamp: float
    equirect: np.ndarray
    polar: np.ndarray
    lights: LightSet
    exposures: list[float]
    timings: dict[str, float]
    histogram: np.ndarray
    preview: np.ndarray
    skipped: bool
    calibration_id: str
    unit: str


class FakeCamera:
    name = "fake"

    def __init__(self) -> None:
        self.opened = False
        self.closed_count = 0
        self._down_until = 0.0

    def disconnect(self, seconds: float) -> None:
        self._down_until = time.monotonic() + seconds

    @property
    def down(self) -> bool:
        return time.monotonic() < self._down_until

    async def open(self) -> None:
        if self.down:
            raise CameraUnavailable("fake camera is unplugged", device="fake")
        self.opened = True

    async def close(self) -> None:
        self.opened = False
        self.closed_count += 1

    async def capture_check(self) -> None:
        if self.down:
            self.opened = False
            raise CameraDisconnected("fake camera went away", device="fake")


def synthetic_map(h: int, frame: int) -> np.ndarray:
    """Sky gradient + a 5-degree sun whose azimuth advances 6 degrees per frame."""
    d = equirect_directions(h)
    sky = (0.2 + 0.8 * np.clip(d[..., 1], 0, 1))[..., None] * np.array([0.6, 0.8, 1.0])
    phi = np.deg2rad(6.0 * frame)
    sun_dir = np.array([np.sin(0.6) * np.sin(phi), np.cos(0.6), -np.sin(0.6) * np.cos(phi)])
    sun = (d @ sun_dir > np.cos(np.deg2rad(5.0)))[..., None] * np.array([400.0, 380.0, 350.0])
    return (sky + sun).astype(np.float32)


def block_lights(img: np.ndarray, count: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Equal row x column blocks; each light carries its block's radiance x solid angle sum
    (float64) at its energy centroid direction. Energy is conserved exactly."""
    h, w = img.shape[:2]
    divisors = [r for r in range(1, h + 1) if count % r == 0 and count // r <= w]
    rows = min(divisors, key=lambda r: abs(r - np.sqrt(count / 2)))  # exactly `count` blocks
    cols = count // rows
    sa = equirect_solid_angle(h, w)
    e = img.astype(np.float64) * sa[..., None]
    wts = e @ np.array([0.2126, 0.7152, 0.0722]) + 1e-12
    dirs = equirect_directions(h).astype(np.float64) * wts[..., None]
    r0 = [int(b[0]) for b in np.array_split(np.arange(h), rows)]
    c0 = [int(b[0]) for b in np.array_split(np.arange(w), cols)]

    def blocks(x: np.ndarray) -> np.ndarray:
        return np.add.reduceat(np.add.reduceat(x, r0, axis=0), c0, axis=1)

    dd = blocks(dirs).reshape(-1, 3)
    return (dd / np.linalg.norm(dd, axis=1, keepdims=True), blocks(e).reshape(-1, 3),
            blocks(sa).reshape(-1))


@dataclass
class FakeConfig:
    sampler: str = "q2tree"
    light_count: int = 64
    equirect_height: int = 32
    probe_id: str = "fake"


class FakePipeline:
    """The Pipeline API over :func:`synthetic_map` (test stand-in only)."""

    def __init__(self, camera: FakeCamera, config: FakeConfig, step_delay: float = 0.01) -> None:
        self.camera, self.config, self.step_delay = camera, config, step_delay
        self.frame = 0
        self.stats: dict[str, Any] = {"frames": 0, "frames_skipped": 0}
        self._map: np.ndarray | None = None
        self.events: list[str] = []

    async def start(self) -> None:
        await self.camera.open()
        self.events.append("start")

    async def stop(self) -> None:
        await self.camera.close()
        self.events.append("stop")

    def _compute(self, frame: int) -> FakeFrameResult:
        t0 = time.perf_counter()
        img = synthetic_map(self.config.equirect_height, frame)
        d, rgb, sa = block_lights(img, self.config.light_count)
        ls = LightSet(d, rgb, sa, method=self.config.sampler, probe=self.config.probe_id, frame=frame,
                      timestamp=time.time())
        lum = luminance(img).ravel()
        hist = np.histogram(np.log2(np.maximum(lum, 1e-6)), bins=64, range=(-16, 16))[0]
        prev = (np.clip(img / (1 + img), 0, 1) * 255).astype(np.uint8)
        dt = time.perf_counter() - t0
        return FakeFrameResult(frame, time.time(), img, img[: img.shape[0] // 2], ls, [1e-3, 1e-2],
                               {"capture": 0.0, "fusion": 0.0, "projection": dt, "sampling": 0.0,
                                "total": dt}, hist, prev, False, "fakecalib0000000", "relative")

    async def step(self) -> FakeFrameResult:
        await self.camera.capture_check()
        if not self.camera.opened:
            raise CameraDisconnected("fake camera not open", device="fake")
        await asyncio.sleep(self.step_delay)
        self.frame += 1
        res = await asyncio.to_thread(self._compute, self.frame)
        self._map = res.equirect
        self.stats["frames"] = self.frame
        return res

    def lights_on_demand(self, method: str, count: int) -> LightSet:
        assert self._map is not None
        d, rgb, sa = block_lights(self._map, count)
        return LightSet(d, rgb, sa, method=method, probe=self.config.probe_id, frame=self.frame)


def fake_factories() -> tuple[Any, Any]:
    """(make_camera, make_pipeline) for ``create_app`` with the stand-in."""

    def make_camera() -> FakeCamera:
        return FakeCamera()

    def make_pipeline(camera: FakeCamera, cfg: Any) -> FakePipeline:
        fc = FakeConfig(sampler=cfg.get("pipeline", "sampler"), light_count=cfg.get("pipeline", "light_count"),
                        equirect_height=32 if cfg.get("pipeline", "light_count") <= 512 else 128,
                        probe_id=cfg.get("probe", "id") or "fake")
        return FakePipeline(camera, fc)

    return make_camera, make_pipeline


# ---- a real server on loopback ---------------------------------------------------------------------
def free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@dataclass
class RunningService:
    url: str
    api: str
    token: str
    app: Any
    runner: Any
    port: int

    @property
    def state(self) -> Any:
        from device.service.app import STATE

        return self.app[STATE]

    @property
    def auth(self) -> dict[str, str]:
        return {"Authorization": f"Bearer {self.token}"}


def service_config(tmp_path: Any, **tables: dict[str, Any]) -> Any:
    """A config (file in tmp_path) with mDNS off unless asked, and the given overrides."""
    from device.service.config import ServiceConfig

    patch: dict[str, dict[str, Any]] = {"mdns": {"enabled": False}, "pipeline": {"fps": 20.0, "light_count": 64}}
    for t, kv in tables.items():
        patch.setdefault(t, {}).update(kv)
    return ServiceConfig(path=tmp_path / "config.toml").with_patch(patch)


class running_service:
    """Start ``create_app`` on 127.0.0.1 (real sockets) with the given factories."""

    def __init__(self, cfg: Any, make_camera: Any = None, make_pipeline: Any = None, *,
                 backoff: tuple[float, float] = (0.1, 0.5), token: str = "test-token-0123456789",
                 probe_id: str = "probetest0001") -> None:
        if make_camera is None or make_pipeline is None:
            make_camera, make_pipeline = fake_factories()
        self.cfg, self.make_camera, self.make_pipeline = cfg, make_camera, make_pipeline
        self.backoff, self.token, self.probe_id = backoff, token, probe_id

    async def __aenter__(self) -> RunningService:
        from aiohttp import web

        from device.service.app import create_app

        port = free_port()
        app = create_app(self.cfg, self.make_camera, self.make_pipeline, token=self.token,
                         probe_id=self.probe_id, port=port, backoff=self.backoff)
        self._runner = web.AppRunner(app, shutdown_timeout=0.5, access_log=None)
        await self._runner.setup()
        await web.TCPSite(self._runner, "127.0.0.1", port).start()
        url = f"http://127.0.0.1:{port}"
        return RunningService(url, url + "/api/v1", self.token, app, self._runner, port)

    async def __aexit__(self, *exc: object) -> None:
        await self._runner.cleanup()


def _serve_with_fakes(argv: list[str]) -> int:
    """``python tests/service_fakes.py serve-args...``: the real ``lightprobe serve`` code path
    with the stand-in camera/pipeline (for subprocess tests before device.pipeline exists)."""
    import device.service.cli as cli

    make_camera, make_pipeline = fake_factories()
    cli.camera_factory = lambda spec, scene, cache_dir=None: make_camera  # type: ignore[assignment]
    cli.pipeline_factory = lambda state_dir, probe_id: make_pipeline  # type: ignore[assignment]
    return cli.main(argv)


if __name__ == "__main__":
    import sys

    sys.exit(_serve_with_fakes(sys.argv[1:]))
