"""The capture pipeline end to end on the simulator: stages wired, energy kept, skipping works.
One ``step`` is one sensor frame (one exposure of the schedule) through every stage."""

from __future__ import annotations

import numpy as np
import pytest

from lightprobe.core.errors import InputError
from lightprobe.core.sphere import angles_from_directions, equirect_integral
from lightprobe.device.pipeline import Pipeline, PipelineConfig, lights_on_demand
from lightprobe.device.tonemap import tone_map
from lightprobe.sim.camera import SimCamera

pytestmark = pytest.mark.slow


async def _run(scene: str, frames: int, **cfg) -> tuple[Pipeline, list]:  # type: ignore[no-untyped-def]
    cam = SimCamera(scene, seed=5)
    pipe = Pipeline(cam, cam.truth_calibration(), PipelineConfig(**cfg))
    await pipe.start()
    try:
        out = [await pipe.step() for _ in range(frames)]
    finally:
        await pipe.stop()
    return pipe, out


async def test_static_scene_publishes_conserved_lights_then_skips_resampling():
    pipe, results = await _run("room", 40, sampler="pharr", light_count=64)
    first = results[0]
    assert first.equirect.dtype == np.float32
    assert np.isfinite(first.equirect).all()
    assert len(first.lights) == 64
    # Every light is a share of the map: the light set integrates to the map it was drawn from
    np.testing.assert_allclose(first.lights.total, equirect_integral(first.equirect), rtol=1e-5)
    # Nothing below the horizon: the lower hemisphere is empty by the default policy
    theta, _ = angles_from_directions(first.lights.directions)
    assert (theta <= np.pi / 2 + np.radians(3)).all()
    # The scene does not change: once the schedule has settled, frames are skipped
    assert any(r.skipped for r in results[20:]), [r.skipped for r in results]
    assert pipe.stats["frames_skipped"] >= 1
    skipped = next(r for r in results if r.skipped)
    assert skipped.lights.frame == skipped.frame
    assert {"capture", "prepare", "fusion", "sampling", "total", "capture_cpu", "process_cpu"} <= set(skipped.timings)
    # and every frame's lights still integrate to that frame's map
    for r in results[20:]:
        np.testing.assert_allclose(r.lights.total, equirect_integral(r.equirect), rtol=0.02)
    assert first.histogram.sum() > 0
    assert first.preview.dtype == np.uint8


async def test_flashlight_power_follows_the_flashlight():
    """Frame after frame, the lights' power in a cone around the flashlight (where it is at that
    frame's sensor time) matches the true map's power there: Pharr's sampler, the rolling estimate
    updated by every exposure of the schedule, long ones that see the lamp only saturated included."""
    from lightprobe.core.sphere import equirect_directions, equirect_solid_angle, luminance

    cam = SimCamera("flashlight", seed=2)
    pipe = Pipeline(cam, cam.truth_calibration(), PipelineConfig(sampler="pharr", light_count=256))
    await pipe.start()
    try:
        for _ in range(30):  # the metering sweep and the first cycles of the schedule
            await pipe.step()
        ratios, shares, exposures = [], [], set()
        for _ in range(12):
            r = await pipe.step()
            exposures.add((r.exposure_s, r.gain))
            when = cam.scene_time(r.sensor_time_s + 0.5 * r.exposure_s)  # what `captured` says
            axis = cam.scene.lights[0].direction_at(when)
            truth = cam.truth_radiance(when)
            dirs = equirect_directions(truth.shape[0])
            cone = dirs @ axis > np.cos(np.radians(15))
            true_power = float((luminance(truth.astype(np.float64)) * equirect_solid_angle(truth.shape[0]))[cone].sum())
            light_lum = luminance(r.lights.rgb)
            in_cone = r.lights.directions @ axis > np.cos(np.radians(15))
            ratios.append(light_lum[in_cone].sum() / true_power)
            shares.append(light_lum[in_cone].sum() / light_lum.sum())
    finally:
        await pipe.stop()
    assert len(exposures) >= 3, exposures  # the frames span the schedule
    # The flashlight dominates its cone: the lights put the right power there, every frame
    assert min(shares) > 0.1, shares
    assert all(0.9 < q < 1.1 for q in ratios), ratios


def test_config_rejects_bad_values_naming_them():
    with pytest.raises(InputError, match="light_count"):
        PipelineConfig(light_count=0)
    with pytest.raises(InputError, match="sampler"):
        PipelineConfig(sampler="nope")
    with pytest.raises(InputError, match="nside"):
        PipelineConfig(nside=48)


def test_tone_map_handles_black_nan_and_huge_values():
    img = np.zeros((48, 64, 3), np.float32)
    assert tone_map(img).max() == 0
    img[0, 0] = np.nan
    img[1, 1] = 1e30
    img[2, 2] = 1.0
    out = tone_map(img)
    assert out.dtype == np.uint8
    assert out[1, 1].max() == 255


async def test_tree_sampler_publishes_exactly_the_requested_useful_lights():
    """Q2-Tree keeps leaves over the empty lower hemisphere; none is published, and the count
    still comes out exact."""
    _pipe, results = await _run("room", 2, sampler="q2tree", light_count=100)
    for r in results:
        assert len(r.lights) == 100
        assert (r.lights.rgb.sum(axis=1) > 0).all()
        np.testing.assert_allclose(r.lights.total, equirect_integral(r.equirect), rtol=1e-5)


async def test_reopen_after_a_fault_keeps_tables_and_the_last_bracket():
    """After a camera fault the pipeline reopens with its tables and its schedule (no metering
    sweep): every frame after the reopen is used, one frame per step."""
    cam = SimCamera("lebombo", seed=4)
    pipe = Pipeline(cam, cam.truth_calibration(), PipelineConfig(sampler="median-cut", light_count=16))
    await pipe.start()
    try:
        first = [await pipe.step() for _ in range(20)]
        geo = pipe._geo
        schedule = list(first[-1].exposures)
        await pipe.stop()  # what the service does on CameraDisconnected
        await pipe.start()
        seq0 = cam.sequence
        again = [await pipe.step() for _ in range(3)]
        assert pipe._schedule is not None
        assert not pipe._schedule.sweep
    finally:
        await pipe.stop()
    lo = cam.capabilities.exposure_range[0]
    assert any(r.exposure_s == lo for r in first[:8])  # the first frames sweep the whole range
    assert pipe._geo is geo
    assert again[0].exposures == pytest.approx(schedule)
    assert cam.sequence - seq0 == len(again)
    assert all(not r.skipped or r.lights.frame == r.frame for r in again)


async def test_on_demand_lights_need_the_published_frame_only():
    """On-demand sampling works from a published frame alone (no pipeline: the service keeps
    serving it while the camera reconnects, a calibration session holds the camera or a rebuilt
    pipeline waits for its first frame): the set carries that frame's number, unit, probe and
    pose, keeps its energy, and bad parameters are named."""
    _pipe, results = await _run("room", 3, sampler="pharr", light_count=16, probe_id="probe-a")
    published = results[-1]
    ls = lights_on_demand(published, "median-cut", 8)
    assert len(ls) == 8
    assert (ls.frame, ls.timestamp) == (published.frame, published.timestamp)
    assert (ls.unit, ls.probe, ls.pose) == (published.unit, "probe-a", published.lights.pose)
    np.testing.assert_allclose(ls.total, equirect_integral(published.equirect), rtol=1e-5)
    tree = lights_on_demand(published, "q2tree", 50)  # useful lights only, exactly as many
    assert len(tree) == 50
    assert (tree.rgb.sum(axis=1) > 0).all()
    with pytest.raises(InputError) as e:
        lights_on_demand(published, "nope", 8)
    assert e.value.param == "method"
    with pytest.raises(InputError) as e:
        lights_on_demand(published, "pharr", 0)
    assert e.value.param == "count"


def test_published_maps_are_never_rewritten_while_held() -> None:
    """The per-frame map buffers are reused only when nothing holds them (a result, a view, a
    memoryview): a held map keeps its frame's values, a released one is reused with zeros below."""
    from lightprobe.device.projection.output import OutputGeometry

    geo = OutputGeometry.__new__(OutputGeometry)  # only the map buffers: no projector needed
    geo.height, geo._maps = 8, []
    frame = np.ones((4 * 16, 3), np.float32)
    a = geo.equirect_map(frame)
    b = geo.equirect_map(2 * frame)
    assert a is not b
    assert a[0, 0, 0] == 1.0
    assert not a[4:].any()
    a[4:] = 9.0  # a careless consumer
    held = memoryview(b)
    del a
    c = geo.equirect_map(3 * frame)  # a's buffer, nothing holds it
    assert c[0, 0, 0] == 3.0
    assert not c[4:].any()
    assert np.asarray(held)[0, 0, 0] == 2.0
    view = c[:2]
    del c, held, b
    d = geo.equirect_map(4 * frame)  # b's buffer again; c's is held by the view
    assert d[0, 0, 0] == 4.0
    assert view[0, 0, 0] == 3.0
    assert len(geo._maps) == 2
