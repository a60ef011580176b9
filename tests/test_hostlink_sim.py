"""hostlink against three probes running the REAL pipeline on the simulated camera
(``lightprobe.device.pipeline.Pipeline`` + ``lightprobe.sim.camera.SimCamera``, scene ``flashlight``), each a real
service with its own zeroconf on 127.0.0.1: discovery, the Q2-Tree the probe serves from its
published map, the merged stream, and one probe stopping."""

from __future__ import annotations

import contextlib
from collections.abc import AsyncIterator
from pathlib import Path

import numpy as np
import pytest
from aiohttp import web
from service_harness import RunningService, free_port, service_config, sim_factories

from lightprobe.device.service.routes import q2tree as q2tree_api
from lightprobe.hostlink import Discovery, MergedStream, ProbeClient
from lightprobe.hostlink.merge import merge_q2trees

pytestmark = pytest.mark.slow
pytest.importorskip("lightprobe.device.pipeline")
pytest.importorskip("lightprobe.sim.camera")

LOOPBACK = ["127.0.0.1"]
NSIDE = 16


@contextlib.asynccontextmanager
async def sim_probe(tmp_path: Path, pid: str, name: str) -> AsyncIterator[RunningService]:
    from lightprobe.device.service.app import create_app

    d = tmp_path / pid
    d.mkdir()
    cfg = service_config(d, mdns={"enabled": True, "interfaces": LOOPBACK},
                         probe={"name": name, "id": pid},
                         pipeline={"fps": 2.0, "light_count": 64, "sampler": "q2tree",
                                   "equirect_height": 32, "nside": NSIDE, "max_exposures": 2})
    port = free_port()
    app = create_app(cfg, *sim_factories(d, pid),
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
        disc = await stack.enter_async_context(Discovery(interfaces=LOOPBACK))
        await disc.wait_for(lambda p: set(ids) <= set(p), within=10.0)
        stream = await stack.enter_async_context(MergedStream(disc, count=64, stale_after=10.0,
                                                              ids=ids))
        updates = stream.updates(idle=240.0)  # the first frames wait for the simulator's tables
        merged = await anext(updates)
        while sorted(merged.extra["merged_from"]) != ids:
            merged = await anext(updates)
        assert len(merged) == 64
        assert merged.extra["merge"] == "q2tree"

        # the probe's tree is the tree of its published map: same energy, and merging it with itself
        # gives back the probe's own q2tree lights of the same frame (hysteresis 0, jitter)
        async with ProbeClient(services[0].url) as c:
            for _ in range(20):  # a tree and the map it was built from (same frame)
                tree = await c.q2tree(64)
                r = services[0].state.runner.result
                if r.frame == tree.meta["frame"]:
                    break
        assert r.frame == tree.meta["frame"]
        assert 64 <= len(tree) <= 66
        from lightprobe.core.sphere import equirect_integral
        from lightprobe.device.sampling.q2tree import auto_nside

        np.testing.assert_allclose(tree.total, equirect_integral(r.equirect), rtol=1e-6)
        assert 2**tree.max_level == auto_nside(r.equirect.shape[0])
        self_merge = merge_q2trees([tree, tree], 64)
        np.testing.assert_allclose(self_merge.total, tree.total, rtol=1e-12)

        # one probe stops: the merged stream continues from the two others
        await services[1].runner.cleanup()
        m = await anext(updates)
        while sorted(m.extra["merged_from"]) != [ids[0], ids[2]]:
            m = await anext(updates)
        await disc.wait_for(lambda p: ids[1] not in p, within=3.0)
        await updates.aclose()
