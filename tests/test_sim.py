"""SimCamera: protocol conformance, control latency, clock, determinism, faults, ground truth."""

from __future__ import annotations

import asyncio
import json
from pathlib import Path

import numpy as np
import pytest

from lightprobe.core.calibration import Calibration
from lightprobe.core.errors import InputError
from lightprobe.core.sphere import CAMERA_TO_PROBE, directions_from_angles
from lightprobe.drivers.base import (
    Camera,
    CameraDisconnected,
    CameraError,
    CameraUnavailable,
    CaptureTimeout,
    ControlNotSupported,
    ControlOutOfRange,
    Controls,
    Mode,
    PixelFormat,
)
from lightprobe.sim.camera import SimCamera
from lightprobe.sim.scenarios import SCENARIOS, load_scene
from lightprobe.sim.scene import DynamicLight, Scene


def flat_scene(level: float = 1.0, height: int = 512) -> Scene:
    return Scene(np.full((height, 2 * height, 3), level, np.float32), name="flat")


def vga(fmt: PixelFormat = PixelFormat.RGB8) -> Mode:
    return Mode(640, 480, fmt, 30.0)


# ---- protocol conformance -----------------------------------------------------------------------
async def test_protocol_conformance(shared_data: Path) -> None:
    cam = SimCamera(shared_data=shared_data)
    assert isinstance(cam, Camera)
    with pytest.raises(CameraUnavailable):
        await cam.capture()
    with pytest.raises(CameraUnavailable):
        await cam.apply(Controls(exposure_s=0.01))
    async with cam:
        caps = cam.capabilities
        assert caps.has_frame_metadata
        assert caps.control_latency_frames == 2
        assert caps.exposure_range == (1e-5, 1.0)
        assert cam.mode == vga()
        assert cam.mode in caps.modes
        assert {(m.width, m.height, m.format) for m in caps.modes} >= {
            (640, 480, PixelFormat.RGB8), (640, 480, PixelFormat.RAW12), (1280, 960, PixelFormat.RGB8)}
        for bad in (Controls(exposure_s=0.0), Controls(exposure_s=2.0), Controls(gain=0.5),
                    Controls(gain=100.0), Controls(exposure_s=-1.0)):
            with pytest.raises(ControlOutOfRange):
                await cam.apply(bad)
        with pytest.raises(ControlNotSupported):
            await cam.set_mode(Mode(320, 240))
        f = await cam.capture()
        assert f.data.shape == (480, 640, 3)
        assert f.data.dtype == np.uint8
        assert f.format is PixelFormat.RGB8
        assert f.white_level == 255.0
        assert f.meta.exposure_verified
        assert f.meta.sequence == 0
        # a streaming sensor's exposure ends with its frame: frame 0 is [0, 1/30)
        assert cam.scene_time(f.meta.timestamp_s) + f.meta.exposure_s == pytest.approx(1 / 30, abs=1e-12)
        await cam.set_mode(vga(PixelFormat.RAW12))
        f = await cam.capture()
        assert f.data.dtype == np.uint16
        assert f.format is PixelFormat.RAW12
        assert (f.black_level, f.white_level) == (256.0, 4095.0)
        assert int(f.data.max()) <= 4095
        await cam.set_mode(Mode(1280, 960, PixelFormat.RGB8, 15.0))
        f = await cam.capture()
        assert f.data.shape == (960, 1280, 3)
        assert cam.truth_calibration().fisheye.image_size == (1280, 960)
    await cam.close()  # safe twice
    with pytest.raises(CameraUnavailable):
        await cam.capture()


@pytest.mark.parametrize("k", [0, 1, 2, 4])
async def test_control_latency_is_exactly_k_frames(k: int) -> None:
    cam = SimCamera(flat_scene(0.5), latency_frames=k)
    async with cam:
        await cam.set_mode(vga(PixelFormat.RAW12))
        for _ in range(3):
            await cam.capture()
        old = cam.capabilities.exposure_range[0] * 0 + 1.0 / 60.0
        await cam.apply(Controls(exposure_s=1e-3, gain=2.0))
        frames = [await cam.capture() for _ in range(k + 2)]
    for i, f in enumerate(frames):
        assert f.meta.sequence == 3 + i
        if i < k:
            assert (f.meta.exposure_s, f.meta.gain) == (old, 1.0)
        else:
            assert (f.meta.exposure_s, f.meta.gain) == (1e-3, 2.0)
    # The pixels tell the same story as the metadata: signal ~ exposure x gain
    c = frames[-1].data[200:280, 280:360].astype(float).mean() - 256
    if k > 0:
        o = frames[0].data[200:280, 280:360].astype(float).mean() - 256
        assert c / o == pytest.approx(1e-3 * 2.0 / old, rel=0.03)


async def test_virtual_clock_and_dropped_frames() -> None:
    cam = SimCamera(flat_scene(), latency_frames=0)
    async with cam:
        seqs, times = [], []
        for _ in range(3):
            f = await cam.capture()
            seqs.append(f.meta.sequence)
            times.append(cam.scene_time(f.meta.timestamp_s) + f.meta.exposure_s)
        cam.faults.inject("drop", count=3)
        f = await cam.capture()
        seqs.append(f.meta.sequence)
        times.append(cam.scene_time(f.meta.timestamp_s) + f.meta.exposure_s)
    assert seqs == [0, 1, 2, 6]
    assert times == pytest.approx([1 / 30, 2 / 30, 3 / 30, 7 / 30])  # each exposure ends with its frame
    assert f.extra["sim_time_s"] == cam.scene_time(f.meta.timestamp_s)


async def test_deterministic_for_a_seed(shared_data: Path) -> None:
    async def run(seed: int) -> list[np.ndarray]:
        cam = SimCamera("flicker", seed=seed, shared_data=shared_data)
        async with cam:
            await cam.apply(Controls(exposure_s=2e-3))
            return [(await cam.capture()).data for _ in range(4)]

    a, b, c = await run(7), await run(7), await run(8)
    assert all(np.array_equal(x, y) for x, y in zip(a, b, strict=True))
    assert not np.array_equal(a[3], c[3])


async def test_capture_runs_off_the_event_loop() -> None:
    cam = SimCamera(flat_scene())
    ticks = 0

    async def ticker() -> None:
        nonlocal ticks
        while True:
            ticks += 1
            await asyncio.sleep(0)

    async with cam:
        task = asyncio.create_task(ticker())
        await cam.capture()
        task.cancel()
    assert ticks > 1


async def test_realtime_pacing_returns_frames_in_order() -> None:
    cam = SimCamera(flat_scene(), realtime=True)
    async with cam:
        seq = [(await cam.capture(timeout=1.0)).meta.sequence for _ in range(3)]
    assert seq == [0, 1, 2]


# ---- fault injection ----------------------------------------------------------------------------
async def test_capture_error_and_timeout_faults() -> None:
    cam = SimCamera(flat_scene())
    async with cam:
        cam.faults.inject("capture_error", count=2)
        for _ in range(2):
            with pytest.raises(CameraError):
                await cam.capture()
        assert (await cam.capture()).meta.sequence == 2  # lost frames leave a gap
        cam.faults.inject("timeout", count=1, after=1)
        assert (await cam.capture()).meta.sequence == 3
        with pytest.raises(CaptureTimeout):
            await cam.capture(timeout=0.01)
        assert (await cam.capture()).meta.sequence == 5
        cam.faults.inject("capture_error", count=None)
        for _ in range(3):
            with pytest.raises(CameraError):
                await cam.capture()
        cam.faults.clear()
        await cam.capture()
    assert [k for _, k in cam.faults.log] == ["capture_error"] * 2 + ["timeout"] + ["capture_error"] * 3
    with pytest.raises(ValueError, match="nosuch"):
        cam.faults.inject("nosuch")


async def test_disconnect_fault_outage_then_reopen() -> None:
    cam = SimCamera(flat_scene())
    async with cam:
        await cam.apply(Controls(exposure_s=1e-3))
        cam.faults.inject("disconnect", duration_s=0.3)
        with pytest.raises(CameraDisconnected):
            await cam.capture()
        with pytest.raises(CameraDisconnected):
            await cam.capture()
        with pytest.raises(CameraUnavailable):
            await cam.open()
        await cam.close()
        await asyncio.sleep(0.35)
        await cam.open()
        f = await cam.capture()
        # Replugged: controls are back at their defaults (re-apply after reconnect)
        assert f.meta.exposure_s == pytest.approx(1 / 60)
        assert f.meta.sequence > 0


async def test_hot_pixel_and_lens_cap_faults() -> None:
    cam = SimCamera(flat_scene(0.5), latency_frames=0)
    async with cam:
        await cam.apply(Controls(exposure_s=1e-2))
        normal = await cam.capture()
        cam.faults.inject("hot_pixel", count=None, pixels=((320, 240), (10, 5)))
        cam.faults.inject("lens_cap", count=1)
        capped = await cam.capture()
        hot = await cam.capture()
        await cam.set_mode(vga(PixelFormat.RAW12))
        raw = await cam.capture()
    assert normal.data[240, 320].max() < 255
    assert capped.data[240, 320].tolist() == [255, 255, 255]
    assert capped.data[5, 10].tolist() == [255, 255, 255]
    # lens cap: only read noise through the response toe
    mask = np.ones(capped.data.shape[:2], bool)
    mask[240, 320] = mask[5, 10] = False
    assert capped.data[mask].mean() < 3 < normal.data[200:280, 280:360].mean()
    assert hot.data[200:280, 280:360].mean() == pytest.approx(normal.data[200:280, 280:360].mean(), abs=2)
    assert raw.data[240, 320].tolist() == [4095] * 3


# ---- ground truth -------------------------------------------------------------------------------
async def test_truth_calibration_round_trips(shared_data: Path) -> None:
    cam = SimCamera(shared_data=shared_data)
    for mode in (vga(), vga(PixelFormat.RAW12)):
        cal = cam.truth_calibration(mode)
        back = Calibration.from_json(json.loads(json.dumps(cal.to_json())))
        assert back.id == cal.id
        assert back.source == "truth"
        assert back.fisheye is not None
        assert cal.fisheye is not None
        np.testing.assert_allclose(back.fisheye.K, cal.fisheye.K)
        np.testing.assert_allclose(back.fisheye.D, cal.fisheye.D)
        assert back.fisheye.fov_deg == pytest.approx(185.0)
        assert back.response is not None
        assert back.response.method == "truth"
        np.testing.assert_allclose(back.response.inverse, cal.response.inverse, rtol=1e-9, atol=1e-12)
        assert np.all(np.diff(back.response.inverse, axis=0) > 0) or mode.format.is_raw
        assert back.photometric is not None
        assert back.photometric.scale == pytest.approx(cam.sensor.full_well / cam.sensitivity)
        assert back.vignetting is not None
        assert cal.vignetting is not None
        v = back.vignetting.factor(np.array([319.5, 319.5 + 236.0]), np.array([239.5, 239.5]))
        assert v == pytest.approx([1.0, 0.65])


async def test_truth_geometry_locates_a_light() -> None:
    """A small light lands where the truth intrinsics project its direction."""
    for theta_deg, phi_deg in ((0.0, 0.0), (40.0, 30.0), (80.0, 200.0), (89.0, 300.0)):
        d = directions_from_angles(np.deg2rad(theta_deg), np.deg2rad(phi_deg))
        base = np.zeros((512, 1024, 3), np.float32)
        scene = Scene(base, lights=[DynamicLight("l", np.deg2rad(1.0), (1.0, 1.0, 1.0), lambda t, d=d: d)])
        cam = SimCamera(scene)
        img = cam.render_radiance_image(0.0)[..., 1].astype(np.float64)
        om = cam.pixel_solid_angle()
        w = img * om
        vv, uu = np.mgrid[0 : img.shape[0], 0 : img.shape[1]]
        centroid = np.array([(w * uu).sum(), (w * vv).sum()]) / w.sum()
        cal = cam.truth_calibration()
        assert cal.fisheye is not None
        expect = cal.fisheye.project(CAMERA_TO_PROBE.T @ d)
        assert np.linalg.norm(centroid - expect) < 0.5, (theta_deg, centroid, expect)


@pytest.mark.parametrize("fmt", [PixelFormat.RAW12, PixelFormat.RGB8])
async def test_truth_chain_recovers_radiance(fmt: PixelFormat, shared_data: Path) -> None:
    """Inverting one frame with the truth calibration gives the scene radiance (fused x scale)."""
    cam = SimCamera("room", seed=3, latency_frames=0, shared_data=shared_data)
    async with cam:
        await cam.set_mode(vga(fmt))
        t_exp = 400.0 / cam.sensitivity  # the same electron counts whatever the sensitivity
        await cam.apply(Controls(exposure_s=t_exp, gain=1.0))
        f = await cam.capture()
    cal = cam.truth_calibration()
    assert cal.response
    assert cal.vignetting
    assert cal.photometric
    x = cal.response.inverse[f.data.astype(np.int64), np.arange(3)]
    h, w = f.data.shape[:2]
    vv, uu = np.mgrid[0:h, 0:w]
    vig = cal.vignetting.factor(uu, vv)[..., None]
    est = x / t_exp / vig * cal.photometric.scale
    truth = cam.render_radiance_image(cam.scene_time(f.meta.timestamp_s))
    ok = (f.data > 0.1 * f.white_level) & (f.data < 0.9 * f.white_level) & (truth > 0)
    ok &= (np.hypot(uu - 319.5, vv - 239.5) < 220)[..., None]
    assert ok.sum() > 50000
    ratio = est[ok] / truth[ok]
    # Unbiased: the median ratio is 1 (shot noise is symmetric at these counts)
    assert np.median(ratio) == pytest.approx(1.0, abs=0.01)
    # Scatter as the noise model predicts: sigma_e = sqrt(mu + read^2) electrons
    mu = (truth * vig * t_exp * cam.sensitivity)[ok]
    z = (ratio - 1) * mu / np.sqrt(mu + cam.sensor.read_noise**2)
    spread = 1.4826 * np.median(np.abs(z))  # robust standard deviation
    if fmt.is_raw:
        assert spread == pytest.approx(1.0, rel=0.05)
    else:  # 8-bit quantisation adds to the noise in the highlights
        assert 1.0 < spread < 2.0


# ---- scenarios ----------------------------------------------------------------------------------
@pytest.mark.parametrize("name", list(SCENARIOS))
def test_scenarios_load_and_evolve(name: str, shared_data: Path) -> None:
    scene = load_scene(name, seed=1, shared_data=shared_data)
    assert scene.base.shape == (512, 1024, 3)
    assert scene.name == name
    maps = [scene.radiance_equirect(t) for t in np.linspace(0.0, 6.0, 13)]
    for m in maps:
        assert m.dtype == np.float32
        assert np.all(np.isfinite(m))
        assert m.min() >= 0
    changed = [not np.array_equal(maps[0], m) for m in maps[1:]]
    assert any(changed) == (name != "room")


def test_scenario_dynamics(shared_data: Path) -> None:
    sw = load_scene("switch", seed=2, shared_data=shared_data)
    energies = {round(float(sw.true_integral(t)[1]), 3) for t in np.arange(0, 12, 0.25)}
    assert len(energies) == 2  # off and on, nothing in between
    swing = load_scene("swing", seed=2, shared_data=shared_data).lights[0]
    angles = [np.degrees(np.arccos(np.clip(swing.direction_at(t) @ swing.direction_at(0.4), -1, 1)))
              for t in np.linspace(0, 1.6, 33)]
    assert max(angles) == pytest.approx(8.0, abs=0.01)  # +-4 deg: a subtle movement
    fl = load_scene("flicker", seed=2, shared_data=shared_data).lights[0]
    frames = [fl.intensity(i / 30) for i in range(60)]
    assert min(frames) > 0.5
    assert max(frames) < 1.5
    assert np.ptp(frames) > 0.3
    averaged = [fl.mean_intensity(i / 30, 0.05, samples=64) for i in range(30)]
    assert np.ptp(averaged) < 0.25 * np.ptp(frames)  # long exposures average the ripple
    torch = load_scene("flashlight", seed=2, shared_data=shared_data).lights[0]
    assert torch.direction_at(0.0) @ torch.direction_at(4.0) < 0  # half a turn later: far side
    sun = load_scene("daylight", seed=2, shared_data=shared_data).lights[0]
    step = np.degrees(np.arccos(np.clip(sun.direction_at(0.0) @ sun.direction_at(10.0), -1, 1)))
    assert 1.0 < step < 10.0


def test_unknown_scenario_and_paths(shared_data: Path, tmp_path: Path, envmap_paths: dict[str, Path]) -> None:
    with pytest.raises(InputError, match="nosuchscene") as ei:
        load_scene("nosuchscene", shared_data=shared_data)
    assert all(n in str(ei.value) for n in SCENARIOS)
    with pytest.raises(InputError, match=r"missing\.exr"):
        load_scene(str(tmp_path / "missing.exr"))
    interior = load_scene(str(envmap_paths["interior_blender.exr"]))
    assert interior.clamped_pixels >= 1
    assert interior.base.min() >= 0
    assert load_scene("rooitou_park", shared_data=shared_data).base.max() > 6e4
    fallback = load_scene("flashlight", shared_data=tmp_path)  # no data: procedural room
    assert fallback.base.shape == (256, 512, 3)
    assert fallback.base.max() == pytest.approx(8.0)
    assert len(fallback.lights) == 1


async def test_scene_scale_scales_truth_and_pixels() -> None:
    scene = flat_scene(0.2)
    one, four = SimCamera(scene, latency_frames=0), SimCamera(scene, latency_frames=0, scene_scale=4.0)
    assert scene.scale == 1.0  # the caller's scene is not modified
    frames = []
    for cam in (one, four):
        async with cam:
            await cam.set_mode(vga(PixelFormat.RAW12))
            await cam.apply(Controls(exposure_s=0.05))
            frames.append((await cam.capture()).data[200:280, 280:360].astype(float).mean() - 256)
    assert frames[1] / frames[0] == pytest.approx(4.0, rel=0.02)
    assert four.truth_radiance(0.0).mean() == pytest.approx(0.8, rel=1e-6)
    assert four.truth_calibration().photometric == one.truth_calibration().photometric


async def test_realtime_frames_are_stamped_on_the_clock_and_a_slow_consumer_loses_frames() -> None:
    """Paced, the stamps are CLOCK_MONOTONIC's start of exposure (a frame is delivered after its
    exposure and readout), and a consumer more than BUFFERS frames behind gets a sequence gap, not
    ever older frames (a driver's queue drops them)."""
    import time

    from lightprobe.sim.camera import BUFFERS

    cam = SimCamera(flat_scene(), latency_frames=0, realtime=True)
    async with cam:
        f = await cam.capture()
        now = time.monotonic()
        assert f.meta.timestamp_s + f.meta.exposure_s <= now + 1e-3
        assert now - f.meta.timestamp_s < 0.2
        await asyncio.sleep(0.5)  # 15 frame times away
        g = await cam.capture()
        now = time.monotonic()
        assert g.meta.sequence - f.meta.sequence >= 15 - BUFFERS
        assert now - g.meta.timestamp_s <= (BUFFERS + 2) / 30
        assert cam.scene_time(g.meta.timestamp_s) == pytest.approx(g.extra["sim_time_s"], abs=1e-9)
