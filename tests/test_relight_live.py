"""Live relighting against the REAL probe service on loopback: ``lightprobe.device.pipeline.Pipeline`` on the
simulated camera (``lightprobe.sim.camera.SimCamera``, scene ``flashlight``: a light carried around the
probe, so every frame's light set differs), the real aiohttp app with its WebSocket stream, and
``lightprobe.hostlink.relight.cuts.live.run_live`` re-rendering a small scene for each light set it receives.
Slow: the simulator's tables take tens of seconds to build on a shared box."""

from __future__ import annotations

import asyncio
import contextlib
import json
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from aiohttp import web
from service_harness import RunningService, free_port, service_config

pytestmark = pytest.mark.slow
pytest.importorskip("lightprobe.device.pipeline")
pytest.importorskip("lightprobe.sim.camera")

TOKEN = "test-token-0123456789"
CUBE = """v -0.5 0 -0.5
v 0.5 0 -0.5
v 0.5 1 -0.5
v -0.5 1 -0.5
v -0.5 0 0.5
v 0.5 0 0.5
v 0.5 1 0.5
v -0.5 1 0.5
f 1 4 3 2
f 5 6 7 8
f 1 2 6 5
f 4 8 7 3
f 1 5 8 4
f 2 3 7 6
"""


@contextlib.asynccontextmanager
async def sim_probe(tmp_path: Path) -> AsyncIterator[RunningService]:
    from lightprobe.device.bootstrap import camera_factory, pipeline_factory
    from lightprobe.device.service.app import create_app

    pid = "relightprobe1"
    cfg = service_config(tmp_path, probe={"name": "relight", "id": pid},
                         pipeline={"fps": 4.0, "light_count": 32, "sampler": "q2tree",
                                   "equirect_height": 32, "nside": 16, "max_exposures": 2})
    port = free_port()
    app = create_app(cfg, camera_factory("sim", "flashlight"), pipeline_factory(tmp_path / "state", pid),
                     token=TOKEN, probe_id=pid, port=port, backoff=(0.1, 0.25))
    runner = web.AppRunner(app, shutdown_timeout=0.5, access_log=None)
    await runner.setup()
    await web.TCPSite(runner, "127.0.0.1", port).start()
    url = f"http://127.0.0.1:{port}"
    try:
        yield RunningService(url, url + "/api/v1", TOKEN, app, runner, port)
    finally:
        await runner.cleanup()


@pytest.mark.timeout(300)
async def test_live_rerenders_when_the_real_probe_lights_change(tmp_path: Path) -> None:
    from lightprobe.core.imageio import read_hdr_image
    from lightprobe.hostlink.relight.cuts.live import run_live
    from lightprobe.hostlink.relight.cuts.precompute import precompute
    from lightprobe.hostlink.relight.cuts.render import Relighter
    from lightprobe.hostlink.relight.scene import load_scene

    (tmp_path / "cube.obj").write_text(CUBE)
    doc = {"version": 1, "materials": {"floor": {"type": "lambert", "kd": [0.5, 0.5, 0.5]},
                                       "paint": {"type": "blinn-phong", "kd": [0.5, 0.4, 0.3],
                                                 "ks": [0.2, 0.2, 0.2], "exponent": 30}},
           "objects": [{"name": "cube", "mesh": "cube.obj", "material": "paint", "scale": 0.5}],
           "ground": {"y": "auto", "size": 3.0, "resolution": 8, "material": "floor"},
           "camera": {"position": [1.5, 1.5, 2.5], "look_at": [0, 0.2, 0], "width": 48, "height": 36}}
    (tmp_path / "scene.json").write_text(json.dumps(doc))
    scene = load_scene(tmp_path / "scene.json")
    pre = precompute(scene, cache_dir=tmp_path / "cache", progress=False)
    rl = Relighter(scene, pre)
    out = tmp_path / "live.exr"
    seen: list[tuple[Any, np.ndarray]] = []
    async with sim_probe(tmp_path) as probe:
        n = await asyncio.wait_for(
            run_live(probe.url, TOKEN, rl, out, 3, True, on_frame=lambda ls, img: seen.append((ls, img.copy()))),
            timeout=240)
    assert n == 0
    assert len(seen) == 3
    frames = [ls.frame for ls, _ in seen]
    assert frames == sorted(set(frames))                         # three distinct probe frames
    for ls, img in seen:
        assert np.isfinite(img).all()
        assert img.max() > 0
        fresh = Relighter(scene, pre)                            # each frame = a fresh render of its lights
        fresh.set_lightset(ls)
        np.testing.assert_allclose(img, fresh.render()[0], rtol=1e-5, atol=1e-9)
    # the flashlight moves: the light sets, and so the images, differ from frame to frame
    assert not np.allclose(seen[0][0].rgb, seen[-1][0].rgb) or not np.allclose(seen[0][0].directions, seen[-1][0].directions)
    assert np.abs(seen[0][1] - seen[-1][1]).max() > 1e-6 * seen[0][1].max()
    np.testing.assert_allclose(read_hdr_image(out), seen[-1][1], rtol=1e-6)   # the file holds the last one
