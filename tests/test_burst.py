"""Burst capture (lightprobe.device.burst): adaptive bracketing and verified capture on the simulated probe."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from lightprobe.device.burst import (
    BracketPlanner,
    capture_burst,
    exposure_rates,
    field_of_view_mask,
    order_exposures,
    rates_from_frame,
)
from lightprobe.drivers.base import Capabilities, CaptureTimeout, Controls, Frame, PixelFormat
from lightprobe.sim.camera import SimCamera

RANGE = (1e-5, 1.0)


def ev_span(exps: list[float]) -> float:
    return math.log2(max(exps) / min(exps))


# ---- planner ------------------------------------------------------------------------------------
def test_no_history_is_a_metering_sweep_over_the_range() -> None:
    p = BracketPlanner(RANGE, max_exposures=5)
    sweep = p.plan(None)
    assert 2 <= len(sweep) <= 5
    assert sweep[0] == pytest.approx(RANGE[0])
    assert sweep[-1] == pytest.approx(RANGE[1])
    assert sweep == sorted(sweep)


def test_dim_low_range_scene_needs_one_exposure() -> None:
    rates = np.full((60, 80), 2.0)  # e = 2 t: everything fits one exposure
    rates[10:20, 10:20] = 3.0
    exps = BracketPlanner(RANGE).plan(rates)
    assert len(exps) == 1
    assert 3.0 * exps[0] == pytest.approx(0.8, rel=1e-6)  # brightest region at the target


def test_high_range_scene_needs_more_but_never_more_than_max() -> None:
    rng = np.random.default_rng(0)
    rates = np.exp(rng.uniform(np.log(1.0), np.log(1e5), (60, 80)))
    p = BracketPlanner((1e-7, 10.0), max_exposures=4, ev_step=2.0, max_ev_step=3.0)
    exps = p.plan(rates)
    assert len(exps) == 4
    steps = np.diff(np.log2(exps))
    assert np.all(steps <= 3.0 + 1e-9)
    assert np.all(steps > 0)
    bright = np.sort(rates.ravel())[-p.bright_pixels]
    assert bright * exps[0] == pytest.approx(p.bright_target, rel=1e-6)  # Unsaturated
    wide = BracketPlanner((1e-7, 10.0), max_exposures=12).plan(rates)
    assert len(exps) < len(wide) <= 12
    dark = np.percentile(rates, p.dark_percentile)
    assert dark * max(wide) == pytest.approx(p.dark_target, rel=1e-6)  # Above the noise floor


def test_plan_is_clamped_to_the_camera_range() -> None:
    p = BracketPlanner((1e-3, 0.1))
    assert p.plan(np.full((8, 8), 1e6)) == [pytest.approx(1e-3)]
    assert p.plan(np.full((8, 8), 1e-6)) == [pytest.approx(0.1)]
    assert p.plan(np.zeros((8, 8))) == [pytest.approx(0.1)]  # Black: the longest exposure


def test_single_hot_pixel_does_not_drive_the_shortest_exposure() -> None:
    rates = np.full((40, 40), 1.0)
    rates[3, 4] = 1e6
    assert BracketPlanner(RANGE).plan(rates) == [pytest.approx(0.8)]


def test_saturated_pixels_push_the_next_burst_shorter() -> None:
    rates = np.full((40, 40), 1.0)
    rates[:5, :5] = 50.0  # Only a lower bound: saturated in every exposure
    sat = np.zeros_like(rates, bool)
    sat[:5, :5] = True
    p = BracketPlanner(RANGE)
    assert min(p.plan(rates, saturated=sat)) < min(p.plan(rates)) / 4


def test_mask_excludes_the_housing_ring() -> None:
    rates = np.full((40, 40), 1.0)
    rates[:, :4] = 1e-6  # Black lens frame
    mask = np.ones_like(rates, bool)
    mask[:, :4] = False
    p = BracketPlanner(RANGE)
    assert len(p.plan(rates, mask=mask)) == 1
    assert len(p.plan(rates)) > 1


def test_order_alternates_between_bursts() -> None:
    exps = [0.001, 0.01, 0.1]
    first = order_exposures(exps, current=1 / 60)
    assert first == [0.1, 0.01, 0.001]
    assert order_exposures(exps, current=first[-1]) == [0.001, 0.01, 0.1]


def test_exposure_rates_divide_by_full_scale_and_drop_non_finite() -> None:
    rad = np.array([[[1.0, 2.0, 0.5], [np.nan, 1.0, 1.0]]])
    np.testing.assert_allclose(exposure_rates(rad, 2.0), [[1.0, 0.0]])


def test_planner_validates_its_configuration() -> None:
    with pytest.raises(ValueError, match="exposure_range"):
        BracketPlanner((0.0, 1.0))
    with pytest.raises(ValueError, match="max_exposures"):
        BracketPlanner(RANGE, max_exposures=0)


# ---- capture on the simulator -------------------------------------------------------------------
async def test_capture_accepts_only_frames_showing_the_requested_exposure() -> None:
    cam = SimCamera("lebombo", seed=1, latency_frames=3)
    async with cam:
        exps = [0.002, 0.008, 0.032]
        start = cam.sequence
        frames = await capture_burst(cam, exps, gain=1.0, timeout=60)
    assert [f.meta.exposure_s for f in frames] == exps
    seqs = [f.meta.sequence for f in frames]
    # Pipelined: one request per frame, each lands 3 frames later; only the first 3 are stale
    assert seqs == [start + 3, start + 4, start + 5]
    assert cam.sequence == start + 6  # n + latency frames in all
    means = [float(f.data.mean()) for f in frames]
    assert means[0] < means[1] < means[2]


async def test_sequential_capture_waits_for_each_exposure() -> None:
    cam = SimCamera("lebombo", seed=1, latency_frames=3)
    async with cam:
        exps = [0.002, 0.008, 0.032]
        start = cam.sequence
        frames = await capture_burst(cam, exps, gain=1.0, timeout=60, pipelined=False)
    assert [f.meta.exposure_s for f in frames] == exps
    # Each exposure lands 3 frames after its request: 3 stale frames dropped before each
    assert [f.meta.sequence for f in frames] == [start + 3, start + 7, start + 11]


async def test_pipelined_burst_reasks_a_request_the_camera_lost() -> None:
    class LosesOneRequest(SimCamera):
        lost = False

        async def apply(self, controls: Controls) -> None:
            if controls.exposure_s == 0.008 and not self.lost:
                self.lost = True  # dropped on the floor, like a request that missed its frame
                return
            await super().apply(controls)

    cam = LosesOneRequest("lebombo", seed=1, latency_frames=2)
    async with cam:
        exps = [0.002, 0.008, 0.032]
        frames = await capture_burst(cam, exps, gain=1.0, timeout=60)
    assert cam.lost
    assert [f.meta.exposure_s for f in frames] == exps  # in the requested order
    seqs = [f.meta.sequence for f in frames]
    assert seqs[1] > seqs[2]  # 0.008 landed after 0.032, on the repeated request


async def test_pipelined_sweep_costs_n_plus_latency_frames() -> None:
    cam = SimCamera("lebombo", seed=1, latency_frames=2)
    planner = BracketPlanner(cam.capabilities.exposure_range)
    sweep = planner.plan(None)
    async with cam:
        start = cam.sequence
        frames = await capture_burst(cam, sweep, gain=1.0, timeout=60)
    assert len(frames) == len(sweep) == 6
    assert cam.sequence - start == len(sweep) + 2, (start, cam.sequence)


async def test_exposure_that_never_lands_times_out() -> None:
    cam = SimCamera("lebombo", seed=1, latency_frames=12)
    async with cam:
        with pytest.raises(CaptureTimeout, match=r"0\.004"):
            await capture_burst(cam, [0.004], max_frames=5)


async def test_camera_timeouts_propagate_as_typed_errors() -> None:
    cam = SimCamera("lebombo", seed=1, latency_frames=0)
    async with cam:
        cam.faults.inject("timeout", count=1)
        with pytest.raises(CaptureTimeout):
            await capture_burst(cam, [0.004], timeout=0.05)


class NoMetadataSim(SimCamera):
    """A V4L2-like camera built on the simulator: frames report the *requested* exposure, not
    verified, and the declared latency is shorter than the real one."""

    def __init__(self, *a: object, declared_latency: int, **kw: object) -> None:
        super().__init__(*a, **kw)  # type: ignore[arg-type]
        self.declared_latency = declared_latency
        self.requested = 1 / 60

    @property
    def capabilities(self) -> Capabilities:
        return replace(super().capabilities, has_frame_metadata=False,
                       control_latency_frames=self.declared_latency)

    async def apply(self, controls):  # type: ignore[no-untyped-def]
        await super().apply(controls)
        if controls.exposure_s is not None:
            self.requested = controls.exposure_s

    async def capture(self, timeout: float = 1.0) -> Frame:  # noqa: ASYNC109 (the protocol)
        f = await super().capture(timeout)
        self.true_exposure = f.meta.exposure_s
        meta = replace(f.meta, exposure_s=self.requested, exposure_verified=False)
        return replace(f, meta=meta, extra={**f.extra, "true_exposure": f.meta.exposure_s})


@pytest.mark.parametrize("fmt", [PixelFormat.RGB8, PixelFormat.RAW12])
async def test_settling_rule_without_metadata_waits_for_the_brightness_step(fmt: PixelFormat) -> None:
    cam = NoMetadataSim("lebombo", seed=2, latency_frames=4, declared_latency=1)
    async with cam:
        await cam.set_mode(next(m for m in cam.capabilities.modes if m.format is fmt and m.width == 640))
        exps = [0.003, 0.012, 0.048]
        frames = await capture_burst(cam, exps, gain=1.0, timeout=60)
    # Declared latency 1 < real 4: the brightness check must reject the stale frames
    assert [f.extra["true_exposure"] for f in frames] == exps


def test_field_of_view_mask_is_the_clean_image_circle() -> None:
    cam = SimCamera("lebombo", seed=0)
    cal = cam.truth_calibration()
    assert cal.fisheye is not None
    mask = field_of_view_mask(cal.fisheye)
    w, h = cal.fisheye.image_size
    assert mask.shape == (h, w)
    assert mask[h // 2, w // 2]
    assert not mask[0, 0]
    assert not mask[h - 1, w - 1]
    truth = cam.render_radiance_image()
    assert (truth[mask].max(axis=-1) > 0).all()  # No housing-ring or outside pixels


async def test_planning_from_one_frame_histogram() -> None:
    """No fused history: one over-exposed frame of the simulator says 'go shorter'."""
    cam = SimCamera("rooitou_park", seed=3, latency_frames=0)
    async with cam:
        cal = cam.truth_calibration()
        (frame,) = await capture_burst(cam, [0.05], gain=1.0, timeout=60)
    rates, sat = rates_from_frame(frame, cal.response)
    assert sat.sum() > 100  # The sky is saturated at 1/20 s
    p = BracketPlanner(cam.capabilities.exposure_range)
    exps = p.plan(rates, saturated=sat, mask=field_of_view_mask(cal.fisheye))
    assert min(exps) < 0.05 / p.saturated_headroom
    assert len(exps) <= p.max_exposures


def test_a_small_lamp_carrying_much_of_the_light_is_not_clipped() -> None:
    # One pixel carries ~10% of the scene's light with a neighbour at half its level: a lamp
    # (real optics spread it), not a hot pixel. The shortest exposure keeps it unsaturated.
    rates = np.full((40, 40), 1.0)
    rates[20, 20] = 400.0
    rates[20, 21] = 200.0
    exps = BracketPlanner(RANGE).plan(rates)
    assert 400.0 * min(exps) == pytest.approx(0.8, rel=1e-6)



async def test_simulator_read_ahead_gives_the_same_frames() -> None:
    """The simulator computes frames whose controls are fixed in worker threads: the pixels
    must be exactly those of a camera computing every frame on demand."""
    exps = [1e-4, 4e-3, 0.03, 0.2]
    out = []
    for read_ahead in (True, False):
        cam = SimCamera("flashlight", seed=3, latency_frames=2, read_ahead=read_ahead)
        async with cam:
            frames = await capture_burst(cam, exps, gain=2.0, timeout=60)
            frames += await capture_burst(cam, exps[::-1], gain=1.0, timeout=60, pipelined=False)
        out.append(frames)
    for a, b in zip(*out, strict=True):
        assert (a.meta.sequence, a.meta.exposure_s, a.meta.gain) == (b.meta.sequence, b.meta.exposure_s, b.meta.gain)
        np.testing.assert_array_equal(a.data, b.data)


def test_the_sensor_peak_is_the_brightest_pixel_that_is_not_isolated() -> None:
    """frame_peak_rate: a sun of two sensor pixels is read at its brightest pixel (the planner's
    map averages it into an output pixel), a lone bright pixel among dark ones (a hot pixel, a
    glint) is passed over, and a clipped peak says it is a lower bound, alone or not (one frame
    cannot tell a sun beyond the sensor's range from a stuck pixel: the shorter exposure costs an
    exposure, a clipped sun its light)."""
    from lightprobe.device.burst import frame_peak_rate

    levels = 256
    lut = np.zeros((levels, 3, 5), np.float32)
    lut[..., 0] = (np.arange(levels, dtype=np.float32) / 255.0)[:, None] * 1000.0  # value per unit exposure
    lut[250:, :, 3] = 1.0  # saturated codes
    codes = np.full((48, 64, 3), 5, np.uint8)  # a dark room
    codes[10, 10] = 200  # the sun's brightest pixel ...
    codes[10, 11] = 120  # ... and its neighbour
    codes[40, 50] = 240  # a lone bright pixel among dark ones
    rate, saturated = frame_peak_rate(codes, lut, full_scale=1000.0)
    assert rate == pytest.approx(200 / 255)
    assert saturated is False
    codes[10, 10] = 252
    rate, saturated = frame_peak_rate(codes, lut, full_scale=1000.0)
    assert rate == pytest.approx(252 / 255)
    assert saturated is True
    # only isolated pixels, none clipped: no peak (the map's own levels decide)
    lone = np.zeros((16, 16, 3), np.uint8)
    lone[5, 5] = 240
    assert frame_peak_rate(lone, lut, full_scale=1000.0) == (0.0, False)
    lone[5, 5] = 255  # clipped: a lower bound, alone or not
    assert frame_peak_rate(lone, lut, full_scale=1000.0) == (pytest.approx(1.0), True)
