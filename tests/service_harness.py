"""Test harness of the probe service: the real service on a real aiohttp server on 127.0.0.1,
running the real pipeline on the simulated camera, wired by the same bootstrap as ``lightprobe
serve`` (``lightprobe.device.bootstrap``: ``--camera sim``, calibration from the state dir's store or
the simulator's own).

Projection tables and the simulator's lens matrices are built by the real code on first use and
kept in one cache directory per test session (every state dir links to it), so a service after
the first starts in well under a second. Faults come from the simulator itself
(``camera.faults.inject``); a test that needs a fault the simulator cannot make (a factory that
hangs) wraps a real factory.

Run as a script (``python tests/service_harness.py serve-args...``) it is ``lightprobe serve``
with the session cache linked into its state dir.
"""

from __future__ import annotations

import atexit
import os
import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

SCENE = "flashlight"  # a moving lamp: frames differ, so the pipeline samples every frame
_CACHE: list[Path] = []


def shared_cache() -> Path:
    """The session's table cache (projection tables, lens matrices), made on first use."""
    if not _CACHE:
        d = Path(os.environ.get("LIGHTPROBE_TEST_CACHE") or tempfile.mkdtemp(prefix="lightprobe-cache-"))
        d.mkdir(parents=True, exist_ok=True)
        if "LIGHTPROBE_TEST_CACHE" not in os.environ:
            atexit.register(shutil.rmtree, d, True)
            os.environ["LIGHTPROBE_TEST_CACHE"] = str(d)  # subprocesses share it
        _CACHE.append(d)
    return _CACHE[0]


def state_dir(root: Path) -> Path:
    """``root/state`` with its ``cache`` linked to the session cache."""
    state = Path(root) / "state"
    state.mkdir(parents=True, exist_ok=True)
    link = state / "cache"
    if not link.exists():
        link.symlink_to(shared_cache(), target_is_directory=True)
    return state


def sim_factories(root: Path, probe_id: str = "probetest0001", scene: str = SCENE) -> tuple[Any, Any]:
    """(make_camera, make_pipeline) of ``lightprobe serve --camera sim --scene SCENE`` with its
    state in ``root/state``."""
    from lightprobe.device.bootstrap import camera_factory, pipeline_factory

    state = state_dir(root)
    return camera_factory("sim", scene, state / "cache"), pipeline_factory(state, probe_id)


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
        from lightprobe.device.service.state import STATE

        return self.app[STATE]

    @property
    def auth(self) -> dict[str, str]:
        return {"Authorization": f"Bearer {self.token}"}


def service_config(tmp_path: Any, **tables: dict[str, Any]) -> Any:
    """A config (file in tmp_path) with mDNS off unless asked, and the given overrides."""
    from lightprobe.device.service.config import ServiceConfig

    patch: dict[str, dict[str, Any]] = {"mdns": {"enabled": False}, "pipeline": {"fps": 20.0, "light_count": 64}}
    for t, kv in tables.items():
        patch.setdefault(t, {}).update(kv)
    return ServiceConfig(path=tmp_path / "config.toml").with_patch(patch)


class running_service:
    """Start ``create_app`` on 127.0.0.1 (real sockets). Without factories: the real pipeline on
    the simulator (:func:`sim_factories`, state next to the config file)."""

    def __init__(self, cfg: Any, make_camera: Any = None, make_pipeline: Any = None, *,
                 backoff: tuple[float, float] = (0.1, 0.5), token: str = "test-token-0123456789",
                 probe_id: str = "probetest0001", scene: str = SCENE, port: int | None = None,
                 **app_options: Any) -> None:
        if make_camera is None or make_pipeline is None:
            root = Path(cfg.path).parent if cfg.path is not None else Path(tempfile.mkdtemp())
            sim_camera, sim_pipeline = sim_factories(root, probe_id, scene)
            make_camera, make_pipeline = make_camera or sim_camera, make_pipeline or sim_pipeline
        self.cfg, self.make_camera, self.make_pipeline = cfg, make_camera, make_pipeline
        self.backoff, self.token, self.probe_id = backoff, token, probe_id
        self.app_options = app_options  # more of create_app's keywords (mqtt=, osc=, ...)
        self.port = port  # None: a free one

    async def __aenter__(self) -> RunningService:
        from aiohttp import web

        from lightprobe.device.service.app import create_app

        port = self.port or free_port()
        app = create_app(self.cfg, self.make_camera, self.make_pipeline, token=self.token,
                         probe_id=self.probe_id, port=port, backoff=self.backoff, **self.app_options)
        self._runner = web.AppRunner(app, shutdown_timeout=0.5, access_log=None)
        await self._runner.setup()
        await web.TCPSite(self._runner, "127.0.0.1", port).start()
        url = f"http://127.0.0.1:{port}"
        return RunningService(url, url + "/api/v1", self.token, app, self._runner, port)

    async def __aexit__(self, *exc: object) -> None:
        await self._runner.cleanup()


def _serve(argv: list[str]) -> int:
    """``lightprobe serve`` with the session cache linked into ``--state-dir``."""
    from lightprobe.cli.serve import main

    if "--state-dir" in argv:
        state = Path(argv[argv.index("--state-dir") + 1])
        if not (state / "cache").exists():
            state.mkdir(parents=True, exist_ok=True)
            (state / "cache").symlink_to(shared_cache(), target_is_directory=True)
    return main(argv)


if __name__ == "__main__":
    import sys

    sys.exit(_serve(sys.argv[1:]))
