"""Staged start (issue 14): a fresh state dir serves its first lights from a coarse projection
table (no solid-angle balancing) and builds the balanced one behind the running pipeline, which
swaps it in, keeps its rolling estimate, and writes it to the state dir, so the next start loads
the balanced table at once and never serves a coarse one."""

from __future__ import annotations

import asyncio
import gc
import os
from pathlib import Path

import numpy as np
import pytest

from lightprobe.core.sphere import equirect_integral
from lightprobe.device.pipeline import Pipeline, PipelineConfig
from lightprobe.sim.camera import SimCamera

pytestmark = pytest.mark.slow


async def _run(cache: Path, frames: int, until_balanced: bool) -> tuple[Pipeline, list, list[bool]]:  # type: ignore[type-arg]
    cam = SimCamera("rooitou_park", seed=3, read_ahead=False)
    pipe = Pipeline(cam, cam.truth_calibration(),
                    PipelineConfig(sampler="q2tree", light_count=64, cache_dir=str(cache), staged_start=True,
                                   equirect_height=64))
    await pipe.start()
    out, balanced = [], []
    try:
        for _ in range(frames):
            out.append(await pipe.step())
            balanced.append(pipe._geo.projector.balanced)
        while until_balanced and pipe._refine:
            await asyncio.sleep(0.05)
            out.append(await pipe.step())
            balanced.append(pipe._geo.projector.balanced)
    finally:
        await pipe.stop()
    return pipe, out, balanced


async def test_a_fresh_state_dir_starts_coarse_then_swaps_in_the_balanced_table(tmp_path: Path) -> None:
    from lightprobe.device.projection.projector import TABLE_CACHE

    TABLE_CACHE.clear()  # a fresh process: nothing built yet
    pipe, results, balanced = await _run(tmp_path, 3, until_balanced=True)
    assert balanced[0] is False  # the first lights came from the coarse table
    assert balanced[-1] is True
    assert pipe._geo.projector.balanced
    assert not pipe._refine
    assert [p for p in os.listdir(tmp_path) if p.startswith("projection-")]  # on disk for the next start
    # every frame's lights integrate to that frame's map, coarse or balanced
    for r in results:
        if not r.skipped:  # (a skipped frame republishes the last sampled set)
            np.testing.assert_allclose(r.lights.total, equirect_integral(r.equirect), rtol=1e-5)
    assert results[0].lights.total.sum() > 0
    # the coarse table is not kept once the balanced one serves (memory on the board); a frame
    # result keeps the table it was made with (its preview), so the old results go first
    assert any(k[-1] != "coarse" for k in TABLE_CACHE)
    del results, r
    gc.collect()
    assert not [k for k in TABLE_CACHE if k[-1] == "coarse"]
    # the next start loads the balanced table from the state dir: no coarse table, no rebuild
    TABLE_CACHE.clear()
    pipe2, _, balanced2 = await _run(tmp_path, 1, until_balanced=False)
    assert balanced2 == [True]
    assert pipe2._geo.projector.balanced
    assert not pipe2._refine
