"""The service with the REAL pipeline (device.pipeline.Pipeline) on the simulated probe
(sim.camera.SimCamera, scene ``flashlight``), real aiohttp server on 127.0.0.1: lights stream,
the brightest light follows the flashlight, a 5 s simulated disconnect turns lights stale and fresh
lights resume after the camera comes back. One service instance (the pipeline's remap tables take
tens of seconds to build on this shared box), so it is one slow test with several phases."""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

import aiohttp
import numpy as np
import pytest
from service_fakes import running_service, service_config

pytestmark = pytest.mark.slow

pytest.importorskip("device.pipeline")
pytest.importorskip("sim.camera")


def _angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip(np.dot(a, b) / np.linalg.norm(a) / np.linalg.norm(b), -1, 1))))


async def _next_lights(ws: aiohttp.ClientWebSocketResponse, within: float) -> dict[str, Any]:
    msg = await ws.receive(timeout=within)
    assert msg.type == aiohttp.WSMsgType.TEXT, msg
    return json.loads(msg.data)  # type: ignore[no-any-return]


@pytest.mark.timeout(600)
async def test_real_pipeline_stream_flashlight_and_disconnect(tmp_path: Path) -> None:
    from device.service.cli import camera_factory, pipeline_factory

    cfg = service_config(tmp_path, pipeline={"fps": 30.0, "light_count": 64, "sampler": "q2tree"})
    async with running_service(cfg, camera_factory("sim", "flashlight"),
                               pipeline_factory(tmp_path / "state", "simprobe0001"),
                               backoff=(0.1, 0.25)) as s, aiohttp.ClientSession() as c, \
            c.ws_connect(s.api + "/stream") as ws:
        first = await _next_lights(ws, within=300)  # remap tables: tens of seconds here
        assert first["stale"] is False
        assert len(first["lights"]) == 64
        assert first["probe"] == "simprobe0001"
        cam = s.state.camera
        flash = next(li for li in cam.scene.lights if li.name == "flashlight")

        # ---- the brightest light follows the flashlight --------------------------------------
        errors, azimuths = [], []
        for _ in range(8):
            d = await _next_lights(ws, within=30)
            t_sim = cam.time_s  # virtual time just after the burst's last frame
            truth = np.asarray(flash.direction(t_sim), np.float64)
            rgb = np.array([li["rgb"] for li in d["lights"]])
            brightest = np.array(d["lights"][int(np.argmax(rgb @ [0.2126, 0.7152, 0.0722]))]["direction"])
            errors.append(_angle_deg(brightest, truth))
            azimuths.append(np.degrees(np.arctan2(brightest[0], -brightest[2])) % 360)
        assert np.median(errors) < 15.0, errors
        assert np.ptp(np.unwrap(np.radians(azimuths))) > np.radians(10), azimuths  # it moved

        # ---- a 5 s disconnect: status shows it, lights turn stale, fresh lights resume ------------
        cam.faults.inject("disconnect", duration_s=5.0)
        t_inject = time.monotonic()
        stale_msg = None
        while stale_msg is None:
            d = await _next_lights(ws, within=30)
            if d["stale"]:
                stale_msg = d
        async with c.get(s.api + "/status") as r:
            st = await r.json()
        assert st["stale"] is True
        assert st["camera"]["state"] == "reconnecting"
        async with c.get(s.api + "/lights") as r:
            ls = await r.json()
        assert ls["stale"] is True
        assert len(ls["lights"]) == 64
        while True:
            d = await _next_lights(ws, within=30)
            if not d["stale"]:
                break
        t_fresh = time.monotonic()
        back = t_inject + 5.0
        resume = t_fresh - back
        print(f"fresh lights {resume:.2f} s after the camera came back; timings {st_timings(s)}")
        async with c.get(s.api + "/status") as r:
            st = await r.json()
        assert st["camera"]["state"] == "running"
        assert st["camera"]["reconnects"] >= 1
        assert st["stale"] is False
        # The service's share (backoff + reopen) must stay under 2 s; the first fresh set also
        # needs one full burst, which on this shared 2-core box takes ~2-3 s of simulator capture.
        burst = float(s.state.runner.result.timings["total"])
        assert resume - burst <= 2.0, (resume, st["timings"])


def st_timings(s: Any) -> dict[str, float]:
    r = s.state.runner.result
    return {k: round(v, 3) for k, v in (r.timings if r is not None else {}).items()}
