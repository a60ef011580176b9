"""hostlink against three probes running the REAL pipeline on the simulated camera
(``device.pipeline.Pipeline`` + ``sim.camera.SimCamera``, scene ``flashlight``), each a real
service with its own zeroconf on 127.0.0.1: discovery, the Q2-Tree the probe serves from its
HEALPix map, the merged stream, and one probe stopping. Slow: the simulator's tables take tens
of seconds to build on this shared box."""

from __future__ import annotations

import contextlib
import time
from collections.abc import AsyncIterator
from pathlib import Path

import numpy as np
import pytest
from aiohttp import web
from service_fakes import RunningService, free_port, service_config

from device.service import q2tree_api
from hostlink import Discovery, MergedStream, ProbeClient
from hostlink.merge import merge_q2trees

pytestmark = pytest.mark.slow
pytest.importorskip("device.pipeline")
pytest.importorskip("sim.camera")

LOOPBACK = ["127.0.0.1"]
NSIDE = 16


@contextlib.asynccontextmanager
async def sim_probe(tmp_path: Path, pid: str, name: str) -> AsyncIterator[RunningService]:
    from device.service.app import create_app
    from device.service.cli import camera_factory, pipeline_factory

    d = tmp_path / pid
    d.mkdir()
    cfg = service_config(d, mdns={"enabled": True, "interfaces": LOOPBACK},
                         probe={"name": name, "id": pid},
                         pipeline={"fps": 2.0, "light_count": 64, "sampler": "q2tree",
                                   "equirect_height": 32, "nside": NSIDE, "max_exposures": 2})
    port = free_port()
    app = create_app(cfg, camera_factory("sim", "flashlight"), pipeline_factory(d / "state", pid),
                     token="test-token-0123456789", probe_id=pid, port=port, backoff=(0.1, 0.25))
    q2tree_api.add_routes(app)
    runner = web.AppRunner(app, shutdown_timeout=0.5, access_log=None)
    await runner.setup()
    await web.TCPSite(runner, "127.0.0.1", port).start()
    url = f"http://127.0.0.1:{port}"
    try:
        yield RunningService(url, url + "/api/v1", "test-token-0123456789", app, runner, port)
    finally:
        if runner.server is not None:
            await runner.cleanup()


@pytest.mark.timeout(300)
async def test_three_simulated_probes(tmp_path: Path) -> None:
    ids = ["simprobe00a1", "simprobe00b2", "simprobe00c3"]
    async with contextlib.AsyncExitStack() as stack:
        services = [await stack.enter_async_context(sim_probe(tmp_path, pid, f"Sim {pid[-2:]}"))
                    for pid in ids]
        t0 = time.monotonic()
        disc = await stack.enter_async_context(Discovery(interfaces=LOOPBACK))
        await disc.wait_for(lambda p: set(ids) <= set(p), within=3.0)
        assert time.monotonic() - t0 < 3.0
        stream = await stack.enter_async_context(MergedStream(disc, count=64, stale_after=10.0,
                                                              ids=ids))
        updates = stream.updates(idle=240.0)  # the first frames wait for the simulator's tables
        merged = await anext(updates)
        while sorted(merged.extra["merged_from"]) != ids:
            merged = await anext(updates)
        assert len(merged) == 64
        assert merged.extra["merge"] == "q2tree"

        # the probe's tree comes from its HEALPix map: same energy, and merging it with itself
        # gives back the probe's own q2tree lights of the same frame (hysteresis 0, jitter)
        async with ProbeClient(services[0].url) as c:
            for _ in range(20):  # a tree and the map it was built from (same frame)
                tree = await c.q2tree(64)
                r = services[0].state.runner.result
                if r.frame == tree.meta["frame"]:
                    break
        assert r.frame == tree.meta["frame"]
        assert 64 <= len(tree) <= 66
        omega = 4 * np.pi / (12 * NSIDE * NSIDE)
        clean = np.where(np.isfinite(r.healpix) & (r.healpix > 0), r.healpix, 0.0)
        np.testing.assert_allclose(tree.total, clean.astype(np.float64).sum(axis=0) * omega,
                                   rtol=1e-6)
        assert tree.max_level == 4
        self_merge = merge_q2trees([tree, tree], 64)
        np.testing.assert_allclose(self_merge.total, tree.total, rtol=1e-12)

        # one probe stops: the merged stream continues from the two others within 2 s
        t_stop = time.monotonic()
        await services[1].runner.cleanup()
        m = await anext(updates)
        while sorted(m.extra["merged_from"]) != [ids[0], ids[2]]:
            m = await anext(updates)
        assert time.monotonic() - t_stop < 2.0
        await disc.wait_for(lambda p: ids[1] not in p, within=3.0)
        await updates.aclose()
