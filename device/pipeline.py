"""The capture pipeline: camera -> burst -> fusion -> projection -> sampler, one frame per step.

:class:`Pipeline` owns the per-probe state that lives across frames (the bracket planner's view of
the scene, the projector's remap tables, the stateful sampler, the last published lights) and runs
one frame per :meth:`Pipeline.step`. Capture is async (the camera protocol); every whole-frame
numpy stage runs in a worker thread, so the event loop only ever waits.

Start-up and restarts are short: :meth:`Pipeline.start` only opens the camera; the projection
tables (loaded from ``PipelineConfig.cache_dir``, built once per calibration otherwise) and the
numba kernels load in a worker thread while the first burst is captured, and the first fused
frame is published. After a camera fault the pipeline keeps its tables, sampler and the last good
frame's exposure rates, so the first burst after the reconnect is planned, not a metering sweep.

It skips what a scene does not need:

- exposures: the planner brackets only the dynamic range the previous frame showed;
- resampling: when the lighting changed less than ``PipelineConfig.change_threshold`` (relative L1
  change of a coarse HEALPix energy map, well above sensor noise) the previous light set is
  republished with the new frame number and ``FrameResult.skipped`` is True;
- lights below the horizon: with the default ``lower="zero"`` the published equirect map and the
  light sets stand for the upper hemisphere only (the thin band the ~185 degree lens sees below
  the horizon is left out, so the lights integrate exactly to the published map); samplers place
  no lights there. The HEALPix and polar maps keep everything the lens saw.
"""

from __future__ import annotations

import asyncio
import logging
import math
import threading
import time
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from device.core.calibration import Calibration
from device.core.errors import InputError
from device.core.sphere import luminance
from drivers.base import Camera, Frame

__all__ = ["HISTOGRAM_EDGES_LOG2", "FrameResult", "Pipeline", "PipelineConfig", "tone_map"]

log = logging.getLogger(__name__)

# Histogram of log2 luminance (fused fisheye image, calibrated unit): 64 bins, fixed edges.
HISTOGRAM_EDGES_LOG2 = np.linspace(-16.0, 24.0, 65)
_PREVIEW_WIDTH = 320
_CHANGE_NSIDE = 8


@dataclass
class PipelineConfig:
    """What the pipeline does per frame. Validated on construction (InputError names the field)."""

    fps: float = 10.0
    sampler: str = "q2tree"
    light_count: int = 256
    max_exposures: int = 8  # the planner uses only what the scene needs (lebombo: 4)
    ev_step: float = 2.0
    equirect_height: int = 256
    nside: int = 64
    probe_id: str = ""
    change_threshold: float = 0.02  # relative L1 change of coarse energy that triggers resampling
    max_skip_s: float = 5.0  # resample at least this often even if nothing changed
    gain: float = 1.0
    capture_timeout_s: float = 5.0  # per exposure of a burst
    lower: str = "zero"
    cache_dir: str | None = None  # keep projection tables on disk here (fast restarts)
    sampler_params: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        from device.sampling.registry import SAMPLERS

        checks = [
            ("fps", 0 < self.fps <= 120),
            ("light_count", 1 <= int(self.light_count) <= 10000),
            ("max_exposures", 1 <= int(self.max_exposures) <= 16),
            ("ev_step", 0.25 <= self.ev_step <= 6),
            ("equirect_height", 8 <= int(self.equirect_height) <= 2048),
            ("nside", 1 <= int(self.nside) <= 1024 and not int(self.nside) & (int(self.nside) - 1)),
            ("change_threshold", 0 <= self.change_threshold <= 1),
            ("max_skip_s", self.max_skip_s >= 0),
            ("gain", self.gain > 0),
            ("capture_timeout_s", self.capture_timeout_s > 0),
        ]
        for name, ok in checks:
            if not ok:
                raise InputError(f"pipeline setting {name}={getattr(self, name)!r} is out of range", param=name)
        if self.sampler not in SAMPLERS:
            raise InputError(f"sampler {self.sampler!r} is not one of {sorted(SAMPLERS)}", param="sampler")


@dataclass
class FrameResult:
    """One frame through all stages (what the service publishes)."""

    frame: int
    timestamp: float
    equirect: np.ndarray  # (He, 2He, 3) float32, probe frame, calibrated unit
    polar: np.ndarray  # (90, 360, 3) float32
    healpix: np.ndarray  # (12 nside^2, 3) float32 NESTED
    lights: Any  # device.sampling.base.LightSet
    exposures: list[float]
    timings: dict[str, float]
    histogram: np.ndarray  # (64,) counts of log2 luminance, edges HISTOGRAM_EDGES_LOG2
    preview: np.ndarray  # (h, w, 3) uint8 sRGB tone-mapped fisheye view
    skipped: bool
    calibration_id: str
    unit: str
    saturated_fraction: float = 0.0


def tone_map(radiance: np.ndarray, valid: np.ndarray | None = None, width: int = _PREVIEW_WIDTH) -> np.ndarray:
    """The dashboard's fisheye preview: :func:`device.tonemap.tone_map` (hue-preserving
    luminance Reinhard, robust log-average key) at most ``width`` pixels wide."""
    from device.tonemap import tone_map as _tone_map

    return _tone_map(radiance, valid, width)


def _coarse_energy(healpix: np.ndarray) -> np.ndarray:
    """Luminance energy per HEALPix pixel at nside 8 (NESTED children are contiguous)."""
    lum = luminance(np.asarray(healpix, np.float64))
    n = lum.shape[0] // (12 * _CHANGE_NSIDE * _CHANGE_NSIDE)
    return lum.reshape(-1, max(n, 1)).sum(axis=1) if n >= 1 else lum


class Pipeline:
    """One probe's capture pipeline. See the module docstring.

    ``step()`` raises :class:`drivers.base.CameraError` on camera faults; the caller (the service's
    frame loop) reconnects with backoff and keeps serving the last good result.
    """

    def __init__(self, camera: Camera, calibration: Calibration, config: PipelineConfig | None = None) -> None:
        if calibration.fisheye is None or calibration.response is None:
            raise InputError("calibration needs fisheye and response sections", param="calibration")
        self.camera = camera
        self.calibration = calibration
        self.config = config or PipelineConfig()
        self.latest: FrameResult | None = None
        self.stats: dict[str, Any] = {"frames": 0, "frames_skipped": 0, "fps": 0.0, "exposures_saved": 0}
        self._projector: Any = None
        self._planner: Any = None
        self._sampler: Any = None
        self._fov_mask: np.ndarray | None = None
        self._prev: tuple[np.ndarray, np.ndarray] | None = None  # (rates, saturated) for the planner
        # (coarse energy, time, from a metering sweep) of the last frame that was sampled
        self._last_sampled: tuple[np.ndarray, float, bool] | None = None
        self._frame = 0
        self._current_exposure: float | None = None
        self._extra_lights = 0  # leaves a tree sampler spends on empty regions (see _sample)
        self._started = False
        self._stream_on = False  # the next frame is the first after the camera opened
        self._tables: asyncio.Future[tuple[Any, np.ndarray]] | None = None

    # ---- lifecycle ----------------------------------------------------------------------------
    async def start(self) -> None:
        """Open the camera; start building the per-calibration tables in a worker thread.

        The first burst is captured while the tables load (or, on a cold start, are built: seconds),
        and :meth:`step` waits for them only before fusion. The first frame after stream-on gets
        a long timeout (slow on real sensors; the simulator loads its lens tables then)."""
        from device.burst import BracketPlanner

        await self.camera.open()
        fe = self.calibration.fisheye
        assert fe is not None
        mode = self.camera.mode
        if (mode.width, mode.height) != tuple(fe.image_size):
            match = [m for m in self.camera.capabilities.modes if (m.width, m.height) == tuple(fe.image_size)
                     and m.format == mode.format]
            if not match:
                raise InputError(f"calibration image size {fe.image_size} matches no camera mode", param="calibration")
            await self.camera.set_mode(match[0])
        if self._projector is None and self._tables is None:
            self._tables = asyncio.ensure_future(asyncio.to_thread(self._build_tables))
        caps = self.camera.capabilities
        self._planner = BracketPlanner(caps.exposure_range, max_exposures=self.config.max_exposures,
                                       ev_step=self.config.ev_step, gain=self.config.gain)
        self._stream_on = True
        self._started = True

    def _build_tables(self) -> tuple[Any, np.ndarray]:
        """Projector (remap tables: from ``cache_dir`` when built before) and field-of-view mask;
        then one projection of a black frame with one invalid pixel, one fusion of a tiny burst
        and two samplings of a small map (a full build, then the incremental update the first
        frame also runs), so every numba kernel of the first frame is loaded (from numba's cache)
        here, in parallel with the first burst, rather than after it; the preview module is
        imported."""
        import cv2  # noqa: F401  (tone_map)

        from device.burst import field_of_view_mask
        from device.projection import Projector

        cfg, fe = self.config, self.calibration.fisheye
        assert fe is not None
        projector = Projector(self.calibration, equirect_height=cfg.equirect_height, nside=cfg.nside,
                              lower=cfg.lower, cache_dir=cfg.cache_dir)
        mask = field_of_view_mask(fe)
        w, h = fe.image_size
        one_bad = mask.copy()
        one_bad[h // 2, w // 2] = False  # also loads the kernel for invalid pixels (saturated lamps)
        projector.project(np.zeros((h, w, 3), np.float32), valid=one_bad)
        try:  # warm-up only: a failure here costs the first frame time, nothing else
            self._warm_fusion()
            warm = np.zeros((16, 32, 3), np.float32)
            warm[:8] = 1.0  # lit upper hemisphere, black below (as published)
            sampler = self._make_sampler(cfg.sampler)
            sampler.sample(warm, 13)
            warm[:4, :8] = 3.0
            sampler.sample(warm, 13)
        except Exception as e:
            log.debug("kernel warm-up failed: %s", e)
        return projector, mask

    def _warm_fusion(self) -> None:
        """Fuse a tiny two-frame burst in the camera's pixel format (loads the merge kernel)."""
        from device.hdr.fusion import fuse_frames
        from drivers.base import Frame, FrameMetadata

        fmt = self.camera.mode.format
        if fmt.is_raw:
            data, white = np.zeros((2, 2, 3), np.uint16), float((1 << fmt.bit_depth) - 1)
        else:
            data, white = np.zeros((2, 2, 3), np.uint8), 255.0
        frames = [Frame(data + 1, FrameMetadata(t, 1.0, 0.0, i), fmt, 0.0, white)
                  for i, t in enumerate((1e-3, 4e-3))]
        fuse_frames(frames, self.calibration.response)

    async def _ensure_tables(self) -> None:
        """Wait for the tables (started by :meth:`start`, or now after a geometry change)."""
        if self._projector is None:
            if self._tables is None:
                self._tables = asyncio.ensure_future(asyncio.to_thread(self._build_tables))
            task = self._tables
            try:
                self._projector, self._fov_mask = await asyncio.shield(task)
            finally:
                if task.done():
                    self._tables = None
        if self._sampler is None:
            self._sampler = self._make_sampler(self.config.sampler)

    async def stop(self) -> None:
        self._started = False
        self._current_exposure = None  # a reopened camera starts from its default exposure
        await self.camera.close()

    async def reopen(self) -> None:
        """Close and open the camera again after a fault; keeps tables and sampler state."""
        try:
            await self.camera.close()
        finally:
            await self.start()

    def reconfigure(self, config: PipelineConfig) -> None:
        """Apply new settings; tables are rebuilt on the next ``start()`` only if geometry changed."""
        old = self.config
        self.config = config
        if (config.sampler, config.sampler_params) != (old.sampler, old.sampler_params):
            self._sampler = self._make_sampler(config.sampler)
            self._last_sampled = None
        if (config.equirect_height, config.nside, config.lower) != (old.equirect_height, old.nside, old.lower):
            self._projector, self._tables = None, None  # rebuilt (in a thread) by the next step()
        if self._planner is not None:
            self._planner.max_exposures = config.max_exposures
            self._planner.ev_step = config.ev_step
            self._planner.max_ev_step = max(self._planner.max_ev_step, config.ev_step)
            self._planner.gain = config.gain
        if config.light_count != old.light_count:
            self._last_sampled = None

    def _make_sampler(self, name: str) -> Any:
        from device.sampling.registry import make_sampler

        return make_sampler(name, **self.config.sampler_params)

    # ---- one frame ----------------------------------------------------------------------------
    async def step(self) -> FrameResult:
        """Capture one burst and push it through every stage."""
        from device.burst import capture_burst, order_exposures

        if not self._started:
            await self.start()
        t0 = time.perf_counter()
        prev = self._prev
        exposures = self._planner.plan(*((prev[0],) if prev else ()),
                                       saturated=prev[1] if prev else None, mask=self._fov_mask)
        exposures = order_exposures(exposures, self._current_exposure)
        first = max(30.0, self.config.capture_timeout_s) if self._stream_on else None
        frames = await capture_burst(self.camera, exposures, gain=self.config.gain,
                                     timeout=self.config.capture_timeout_s, first_timeout=first)
        self._stream_on = False
        self._current_exposure = exposures[-1]
        t1 = time.perf_counter()
        await self._ensure_tables()  # built in parallel with the burst (or after reconfigure())
        t2 = time.perf_counter()
        result = await asyncio.to_thread(self._process, frames, prev is None)
        result.timings = {"capture": t1 - t0, "tables_wait": t2 - t1, **result.timings,
                          "total": time.perf_counter() - t0}
        self._update_stats(result)
        self.latest = result
        return result

    def _process(self, frames: list[Frame], sweep: bool) -> FrameResult:
        """Fusion, projection, change test and sampling (runs in a worker thread)."""
        from device.burst import exposure_rates
        from device.hdr.fusion import fuse_frames

        cal = self.calibration
        assert cal.response is not None
        t0 = time.perf_counter()
        fused = fuse_frames(frames, cal.response)
        full_scale = cal.response.inverse[-1] if not frames[0].format.is_raw else 1.0
        valid = self._fov_mask
        scale = 1.0 if cal.photometric is None else cal.photometric.scale
        side: dict[str, Any] = {}

        def side_work() -> None:
            """What the lights do not need (the next burst's plan, histogram, preview), on the
            other core while this thread projects and samples."""
            try:
                side["rates"] = exposure_rates(fused.radiance, full_scale)
                lum = luminance(fused.radiance[valid] * np.float32(scale))
                with np.errstate(divide="ignore"):
                    side["hist"] = np.histogram(np.log2(lum[lum > 0]), bins=HISTOGRAM_EDGES_LOG2)[0]
                side["preview"] = tone_map(fused.radiance, valid)
                side["sat"] = float(fused.saturated[valid].mean()) if valid is not None and valid.any() else 0.0
            except BaseException as e:  # re-raised by the frame's thread
                side["error"] = e

        helper = threading.Thread(target=side_work, name="lightprobe-frame-side", daemon=True)
        helper.start()
        t1 = time.perf_counter()
        maps = self._projector.project(fused.radiance, valid=~fused.invalid)
        equirect = maps.equirect
        if self.config.lower == "zero":  # Upper hemisphere only (rows of an even-height map)
            equirect = equirect.copy()
            equirect[equirect.shape[0] // 2:] = 0.0
        t2 = time.perf_counter()
        self._frame += 1
        now = time.time()
        coarse = _coarse_energy(maps.healpix)
        skipped = self._unchanged(coarse, now)
        if skipped:
            lights = replace(self.latest.lights, frame=self._frame, timestamp=now, stale=False)  # type: ignore[union-attr]
        else:
            lights = self._sample(self._sampler, equirect, self.config.light_count)
            lights.frame, lights.timestamp = self._frame, now
            self._last_sampled = (coarse, now, sweep)
        t3 = time.perf_counter()
        helper.join()
        if "error" in side:
            raise side["error"]
        self._prev = (side["rates"], fused.saturated)
        hist, preview, sat = side["hist"], side["preview"], side["sat"]
        return FrameResult(
            frame=self._frame, timestamp=now, equirect=equirect, polar=maps.polar, healpix=maps.healpix,
            lights=lights, exposures=[float(f.meta.exposure_s) for f in frames],
            timings={"fusion": t1 - t0, "projection": t2 - t1, "sampling": t3 - t2},
            histogram=hist, preview=preview, skipped=skipped, calibration_id=cal.id,
            unit=self.unit, saturated_fraction=sat)

    def _unchanged(self, coarse: np.ndarray, now: float) -> bool:
        if self._last_sampled is None or self.latest is None:
            return False
        ref, when, was_sweep = self._last_sampled
        if was_sweep or now - when > self.config.max_skip_s:
            return False  # a metering sweep is a coarse estimate: the first planned burst replaces it
        denom = float(np.abs(ref).sum())
        if denom <= 0:
            return float(np.abs(coarse).sum()) <= 0
        return float(np.abs(coarse - ref).sum()) / denom < self.config.change_threshold

    @property
    def unit(self) -> str:
        return "relative" if self.calibration.photometric is None else self.calibration.photometric.unit

    def _sample(self, sampler: Any, equirect: np.ndarray, count: int) -> Any:
        """``count`` lights that carry energy. A tree sampler keeps leaves over the empty lower
        hemisphere (its 12 base quads cannot merge); those are not published, and the sampler
        is asked for as many more as it wasted last time, so hosts get ``count`` useful lights."""
        for _ in range(8):  # converges in 1-3 calls; later frames reuse the estimate
            lights = sampler.sample(equirect, count + self._extra_lights)
            keep = lights.rgb.sum(axis=1) > 0
            wasted = int((~keep).sum())
            short = count - (len(lights) - wasted)
            if short == 0 or keep.sum() == 0 or (short > 0 and wasted == 0):
                break
            self._extra_lights = max(0, self._extra_lights + short)
        if not keep.all():
            lights = replace(lights, directions=lights.directions[keep], rgb=lights.rgb[keep],
                             solid_angle=lights.solid_angle[keep], ids=lights.ids[keep])
        lights.probe = self.config.probe_id
        lights.unit = self.unit
        if self.calibration.pose is not None:
            lights.pose = self.calibration.pose.to_json()
        return lights

    def lights_on_demand(self, method: str, count: int) -> Any:
        """A light set from the current map with a fresh sampler (blocking: call in a thread)."""
        if self.latest is None:
            raise InputError("no frame captured yet", param="frame")
        from device.sampling.registry import SAMPLERS

        if method not in SAMPLERS:
            raise InputError(f"method {method!r} is not one of {sorted(SAMPLERS)}", param="method")
        if not 1 <= int(count) <= 10000:
            raise InputError(f"count={count!r} must be in [1, 10000]", param="count")
        latest = self.latest
        lights = self._sample(self._make_sampler(method), latest.equirect, int(count))
        lights.frame, lights.timestamp = latest.frame, latest.timestamp
        return lights

    def _update_stats(self, r: FrameResult) -> None:
        s = self.stats
        s["frames"] += 1
        s["frames_skipped"] += int(r.skipped)
        s["exposures_saved"] += max(0, self.config.max_exposures - len(r.exposures))
        s["last_timings"] = r.timings
        s["exposures"] = r.exposures
        total = r.timings.get("total", 0.0)
        if total > 0:
            inst = 1.0 / total
            s["fps"] = inst if s["fps"] == 0 else 0.8 * s["fps"] + 0.2 * inst
        s["fps"] = float(s["fps"]) if math.isfinite(s["fps"]) else 0.0
