"""The live capture pipeline: every sensor frame updates the published lighting.

:class:`Pipeline` runs one *frame* per :meth:`Pipeline.step`: the camera delivers one exposure of
the current schedule; that frame is fused and projected at once into the output map (the equirect
map's upper hemisphere, :func:`lightprobe.device.hdr.rolling.frame_to_map`), merged with the latest estimate
of every other exposure in use (:class:`lightprobe.device.hdr.rolling.RollingMerge`: a lamp switching or a
flashlight moving replaces the stale samples in this very frame), sampled into lights, and
published. A light set per sensor frame; nothing at full sensor resolution that no output reads.

The schedule (the exposures and gains the camera cycles through) is planned *for the lighting*
(:class:`lightprobe.device.burst.BracketPlanner`, ``target="lighting"``): the shortest exposure keeps the
brightest thing in view unsaturated, read from the sensor's own pixels in the shortest exposure
(a sun smaller than an output pixel is brighter there than in the map) with a margin and with
hysteresis (headroom too for what the scene showed in the last few seconds, a lamp that
switches), the longest is only as long as the light the scene sends needs
(its darkest corners, which carry less than ``dark_energy`` of the light, may stay noisy),
exposures beyond the sensor's frame time take gain first, and every exposure lies on the
camera's own grid (V4L2/UVC 100 us units, libcamera microseconds) so it lands and verifies. The
shortest exposure comes every other frame, so a lamp switching on is measured unsaturated within
two frames whatever the cycle. The first cycle is a metering sweep over the camera's range.

Cameras with per-frame metadata (libcamera, the simulator) take one control request per frame, a
control latency ahead; each frame says which exposure it shows. Cameras without it (V4L2, UVC)
settle each exposure by the verified-capture rule (:func:`lightprobe.device.burst.capture_burst`), one
usable frame per exposure.

It skips what a scene does not need:

- exposures: the schedule brackets only the light the scene sends (above);
- resampling: when the fused map's coarse energy changed less than ``change_threshold``
  (relative L1, well above noise) since the last sampled frame, and so did the pixels the
  rolling estimate found changed beyond noise since then (a small lamp moving within a coarse
  block changes no block's energy, but its pixels), the last sampled map held no energy by
  guess (a moving lamp a long exposure saw only saturated), and that was less than ``max_skip_s`` ago
  (monotonic clock), the last light set is republished with the new frame number; a change
  beyond it is sampled in the frame that shows it, never later;
- lights below the horizon: the published map and light sets stand for the upper hemisphere.

Previews and the exposure histogram are made when the API asks for them, not per frame.

Start-up: :meth:`Pipeline.start` only opens the camera; the projection table (the equirect map
only; from ``PipelineConfig.cache_dir`` when built before, else in under a second) and the numba
kernels load in a worker thread while the first frame is captured.
"""

from __future__ import annotations

import asyncio
import functools
import logging
import math
import time
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Any

import numpy as np

from lightprobe.core.calibration import Calibration
from lightprobe.core.errors import InputError
from lightprobe.core.sphere import luminance
from lightprobe.device.burst import ExposureSchedule, frame_peak_rate, keep_in_use
from lightprobe.device.sampling.change import ChangeTest
from lightprobe.drivers.base import Camera, Controls, Frame, captured_at, exposure_middle

if TYPE_CHECKING:
    from lightprobe.device.projection.output import OutputGeometry

__all__ = ["HISTOGRAM_EDGES_LOG2", "FrameResult", "Pipeline", "PipelineConfig", "lights_on_demand"]

log = logging.getLogger(__name__)

# Histogram of log2 luminance (the fused map, calibrated unit): 64 bins, fixed edges.
HISTOGRAM_EDGES_LOG2 = np.linspace(-16.0, 24.0, 65)
PREVIEW_WIDTH = 320  # the dashboard's previews are at most this many pixels wide
_REPLAN_S = 1.0  # replan the schedule at least this often (sensor seconds)
_MEMORY_S = 10.0  # the shortest exposure keeps headroom for what was brightest this long ago
_PEAK_DROP = 2.0  # ... and is lengthened only when that fell below the planned peak by this factor,
_PEAK_RISE = 1.5  # ... shortened when it rose above it by this one
RELEASE_AFTER_FRAMES = 150  # frames after which the start's memory is handed back (5 s at 30 fps)
# whether a pipeline of this process handed back its start's memory: a pipeline rebuilt later (a
# recording's fresh start, a calibration reload, a reconnect) links no kernel anew and skips it
# (the collection holds the interpreter 40-80 ms: a paced camera drops a frame for it)
_START_RELEASED = [False]


@dataclass
class PipelineConfig:
    """What the pipeline does per frame. Validated on construction (InputError names the field)."""

    fps: float = 30.0  # at most this many light sets per second (the camera paces below it)
    sampler: str = "q2tree"
    light_count: int = 256
    max_exposures: int = 8
    ev_step: float = 2.0
    equirect_height: int = 256
    nside: int = 64  # HEALPix resolution of the maps served on request
    probe_id: str = ""
    change_threshold: float = 0.01  # relative L1 change of coarse energy that triggers resampling
    max_skip_s: float = 5.0  # resample at least this often even if nothing changed
    gain: float = 1.0
    capture_timeout_s: float = 5.0  # per frame (plus the exposure itself)
    lower: str = "zero"
    cache_dir: str | None = None  # keep projection tables on disk here (fast restarts)
    # a fresh state dir serves from a coarse table first and builds the balanced one behind it
    # (the service; off by default: which frames see which table then depends on wall time)
    staged_start: bool = False
    # frames each exposure is held on a camera without per-frame metadata (V4L2, UVC): a change
    # costs the control latency plus a verified brightness step, a repeat costs nothing
    hold_frames: int = 4
    dark_energy: float = 0.005  # share of the light the longest exposure may leave noisy
    sampler_params: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        from lightprobe.device.sampling.registry import SAMPLERS

        checks = [
            ("fps", 0 < self.fps <= 240),
            ("light_count", 1 <= int(self.light_count) <= 10000),
            ("max_exposures", 1 <= int(self.max_exposures) <= 16),
            ("ev_step", 0.25 <= self.ev_step <= 6),
            ("equirect_height", 8 <= int(self.equirect_height) <= 2048 and int(self.equirect_height) % 2 == 0),
            ("nside", 1 <= int(self.nside) <= 1024 and not int(self.nside) & (int(self.nside) - 1)),
            ("change_threshold", 0 <= self.change_threshold <= 1),
            ("max_skip_s", self.max_skip_s >= 0),
            ("gain", self.gain > 0),
            ("capture_timeout_s", self.capture_timeout_s > 0),
            ("dark_energy", 0 <= self.dark_energy < 0.5),
        ]
        for name, ok in checks:
            if not ok:
                raise InputError(f"pipeline setting {name}={getattr(self, name)!r} is out of range", param=name)
        if self.sampler not in SAMPLERS:
            raise InputError(f"sampler {self.sampler!r} is not one of {sorted(SAMPLERS)}", param="sampler")
        if self.lower != "zero":
            raise InputError(f"lower={self.lower!r}: the live pipeline publishes the upper hemisphere "
                             "only ('zero')", param="lower")


class FrameResult:
    """One frame through every stage (what the service publishes). The fisheye preview and the
    histogram are computed on first use (the API asks for them now and then, frames come 30 a
    second)."""

    def __init__(self, *, frame: int, timestamp: float, equirect: np.ndarray, lights: Any,
                 exposures: list[float], gains: list[float], exposure_s: float, gain: float,
                 timings: dict[str, float], skipped: bool, calibration_id: str, unit: str,
                 saturated_fraction: float, sensor_time_s: float, captured: float | None = None,
                 coverage: np.ndarray | None = None, preview_source: Any = None) -> None:
        self.frame, self.timestamp, self.equirect, self.lights = frame, timestamp, equirect, lights
        self.captured = captured  # wall-clock middle of this frame's exposure (LightSet.captured)
        # (H, 2H) share of each map pixel the lens sees, when it does not see the whole upper
        # hemisphere (a camera that is not a fisheye): 0 is unseen, not black. None: all seen
        self.coverage = coverage
        self.exposures, self.gains = exposures, gains  # the schedule in use (ascending t g)
        self.exposure_s, self.gain = exposure_s, gain  # this frame's
        self.timings, self.skipped = timings, skipped
        self.calibration_id, self.unit = calibration_id, unit
        self.saturated_fraction, self.sensor_time_s = saturated_fraction, sensor_time_s
        self._preview_source = preview_source

    @functools.cached_property
    def preview(self) -> np.ndarray:
        """(h, w, 3) uint8 sRGB tone-mapped fisheye view of the latest mid-bracket frame (what the
        camera sees, for aiming), or of the fused map when there is no frame."""
        from lightprobe.device.tonemap import tone_map

        src = self._preview_source
        if src is None:
            return tone_map(self.equirect, None, PREVIEW_WIDTH)
        radiance, valid = src()
        return tone_map(radiance, valid, PREVIEW_WIDTH)

    @functools.cached_property
    def histogram(self) -> np.ndarray:
        """(64,) counts of log2 luminance of the fused map's lit pixels, edges HISTOGRAM_EDGES_LOG2."""
        lum = luminance(self.equirect[: self.equirect.shape[0] // 2])
        lum = lum[np.isfinite(lum) & (lum > 0)]
        with np.errstate(divide="ignore"):
            return np.histogram(np.log2(lum), bins=HISTOGRAM_EDGES_LOG2)[0]


class Pipeline:
    """One probe's live pipeline (see the module docstring).

    ``step()`` raises :class:`lightprobe.drivers.base.CameraError` on camera faults; the caller (the
    service's frame loop) reconnects with backoff and keeps serving the last good result; the
    rolling estimate and the schedule survive the reconnect.
    """

    def __init__(self, camera: Camera, calibration: Calibration, config: PipelineConfig | None = None) -> None:
        if calibration.fisheye is None or calibration.response is None:
            raise InputError("calibration needs fisheye and response sections", param="calibration")
        self.camera = camera
        self.calibration = calibration
        self._calibration_id = calibration.id  # a content hash: once, not per frame (0.4 ms)
        self.config = config or PipelineConfig()
        self.latest: FrameResult | None = None
        self.stats: dict[str, Any] = {"frames": 0, "frames_skipped": 0, "frames_drained": 0, "fps": 0.0}
        self._tables: asyncio.Future[Any] | None = None
        self._sampler_warm: asyncio.Future[Any] | None = None  # (see _warm_sampler)
        self._geo: Any = None  # projection table and per-pixel constants (OutputGeometry)
        self._refine = False  # a coarse table serves: build the balanced one behind it
        self._settled: tuple[float, float] | None = None  # controls a metadata-less camera runs now
        self._refining: asyncio.Future[Any] | None = None
        self._merge: Any = None
        self._sampler: Any = None
        self._schedule: ExposureSchedule | None = None
        self._planner: Any = None
        self._frame = 0
        self._started = False
        self._steps = 0  # frames processed (the start's memory is handed back once, see step)
        self._release_due = not _START_RELEASED[0]
        self._stream_on = False
        self._change = ChangeTest()  # whether a frame may republish the last light set
        self._extra_lights = 0
        self._planned_at = -math.inf  # sensor time of the last plan
        self._first_cycle = False  # the first planned bracket's first cycle is still running
        self.frames_drained = 0  # queued frames skipped to stay live (Camera.drain)
        self._bright: list[tuple[float, float]] = []  # (sensor time, brightest rate) history
        self._peaks: list[tuple[float, bool]] = []  # the sensor pixels' peak rates since the last plan
        self._planned_peak = 0.0  # the peak rate the bracket in use is planned for
        self._preview: tuple[Frame, np.ndarray] | None = None
        self._t_last: float | None = None
        # the last frame's schedule bookkeeping (a replan: 5-20 ms), run at the start of the next
        # step, after its light set went out (step)
        self._deferred: tuple[Any, ...] | None = None

    # ---- lifecycle ----------------------------------------------------------------------------
    async def start(self) -> None:
        """Open the camera (matching the calibration's image size); the projection table loads
        (or is built) in a worker thread while the first frame is captured."""
        from lightprobe.device.burst import BracketPlanner

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
        if self._geo is None and self._tables is None:
            self._tables = asyncio.ensure_future(asyncio.to_thread(self._build_geometry))
        if self._sampler is None and self._sampler_warm is None:
            self._sampler_warm = asyncio.ensure_future(asyncio.to_thread(self._warm_sampler))
        caps = self.camera.capabilities
        cfg = self.config
        frame_time = 1.0 / max(self.camera.mode.max_fps, 1e-3)
        self._planner = BracketPlanner(caps.exposure_range, max_exposures=cfg.max_exposures, ev_step=cfg.ev_step,
                                       gain=max(cfg.gain, caps.gain_range[0]), target="lighting",
                                       dark_energy=cfg.dark_energy, frame_time_s=frame_time,
                                       gain_range=caps.gain_range, step_s=caps.exposure_step_s)
        if self._schedule is None:
            self._schedule = ExposureSchedule(self._sweep(), sweep=True)
        self._stream_on = True
        self._settled = None  # a (re)opened stream: settle the first controls again
        self._started = True

    def _hold(self) -> int:
        """Frames per exposure: 1 with per-frame metadata (each frame says what it shows), else
        ``PipelineConfig.hold_frames`` (a change is settled by skipping frames)."""
        return 1 if self.camera.capabilities.has_frame_metadata else max(1, int(self.config.hold_frames))

    def _sweep(self) -> list[tuple[float, float]]:
        return self._planner.to_controls(self._planner.metering_sweep())

    async def stop(self) -> None:
        self._started = False
        await self.camera.close()

    async def reopen(self) -> None:
        """Close and open the camera again after a fault; keeps tables, schedule and estimate."""
        try:
            await self.camera.close()
        finally:
            await self.start()

    def reconfigure(self, config: PipelineConfig) -> None:
        """Apply new settings; the table is rebuilt on the next step only if the geometry changed."""
        old = self.config
        self.config = config
        if (config.sampler, config.sampler_params) != (old.sampler, old.sampler_params):
            self._sampler = self._make_sampler(config.sampler)
            self._change.reset()
        if config.equirect_height != old.equirect_height:
            self._geo, self._tables, self._merge = None, None, None
            self._deferred = None  # a map of the old size
            self._refine, self._refining = False, None
        if self._planner is not None:
            self._planner.max_exposures = config.max_exposures
            self._planner.ev_step = config.ev_step
            self._planner.max_ev_step = max(self._planner.max_ev_step, config.ev_step)
            self._planner.dark_energy = config.dark_energy
            self._planned_at = -math.inf
        if config.light_count != old.light_count:
            self._change.reset()

    def _make_sampler(self, name: str) -> Any:
        from lightprobe.device.sampling.registry import make_sampler

        return make_sampler(name, **self.config.sampler_params)

    # ---- tables -------------------------------------------------------------------------------
    def _build_geometry(self, coarse_first: bool | None = None) -> OutputGeometry:
        """The equirect table (from ``cache_dir`` when built before), per output pixel constants,
        and one warm-up of every kernel the first frame runs (numba's cache loads them here, in
        parallel with the first capture).

        Staged start: when the balanced table is not on disk yet (a fresh state dir) and
        ``coarse_first`` (default ``PipelineConfig.staged_start``), a coarse one is built now (no solid-angle balancing, one subpixel per
        fisheye pixel: ~1 s less) so the first lights come sooner, and the balanced table is
        built behind the running pipeline (:meth:`_refine_tables`), which swaps it in."""
        from lightprobe.device.projection import Projector
        from lightprobe.device.projection.output import OutputGeometry

        cfg = self.config
        if coarse_first is None:
            coarse_first = cfg.staged_start
        kw: dict[str, Any] = {"equirect_height": cfg.equirect_height, "nside": cfg.nside, "lower": "zero",
                              "cache_dir": cfg.cache_dir, "maps": ("equirect",)}
        try:
            projector = Projector(self.calibration, subdiv=2, load_only=coarse_first, **kw)
        except LookupError:
            projector = Projector(self.calibration, subdiv=1, balance=False, **kw)
            self._refine = True
        geo = OutputGeometry(projector, self.calibration, cfg.equirect_height)
        try:  # warm-up only: a failure costs the first frame time, nothing else
            self._warm(geo)
        except Exception as e:
            log.debug("kernel warm-up failed: %s", e)
        # the table build's temporaries; a table loaded from disk leaves none, and the
        # collection cost 60-80 ms of a warm start (the frames release memory once they run)
        if projector.built_now:
            from lightprobe.device.allocator import release_memory

            release_memory()
        return geo

    def _warm(self, geo: OutputGeometry) -> None:
        from lightprobe.device.hdr.rolling import RollingMerge, frame_to_map

        fe = self.calibration.fisheye
        assert fe is not None
        w, h = fe.image_size
        fmt = self.camera.mode.format
        img = np.zeros((h, w, 3), np.uint16 if fmt.is_raw else np.uint8)
        codes = img.reshape(-1, 3)
        lut, dark = geo.lut(1e-3, 1.0, fmt)
        frame_to_map(geo.table, geo.geo_n, geo.mean_gain, codes, lut, dark, geo.rows)
        # width set: the moving-lamp hold kernels load too
        # (and resum_every=1: the periodic re-summation's kernel too, not 256 frames in)
        merge = RollingMerge(geo.rows, width=2 * geo.height, max_slots=2, resum_every=1)
        # and the tracker's: a small lamp off the zenith saturated in a long exposure (the top
        # code), then measured by a short one (160, below the LUT's white of 255)
        spot = img[h // 2 - 3:h // 2 + 3, w // 2 + h // 6 - 3:w // 2 + h // 6 + 3]
        spot[:] = (1 << fmt.bit_depth) - 1 if fmt.is_raw else 255
        merge.update((1e-2, 1.0), 0, geo.table, geo.geo_n, geo.mean_gain, codes, *geo.lut(1e-2, 1.0, fmt))
        spot[:] = 160
        fused = merge.update((1e-3, 1.0), 1, geo.table, geo.geo_n, geo.mean_gain, codes, lut, dark)
        geo.weighted_luminance(fused)

    def _warm_sampler(self) -> None:
        """One throwaway sampler samples a map of the pipeline's size twice (a whole pass, then
        an incremental one), in its own thread beside the tables' and the first capture: its
        kernels load and its per-size tables are made (the Q2-Tree's binning of a 256 x 512 map,
        60 ms, is kept by ``equirect_tables``' memo), so the first frame samples warm. The
        pipeline's own sampler starts fresh: a stateful one's filters never see this map."""
        h = self.config.equirect_height
        warm = np.zeros((h, 2 * h, 3), np.float32)
        warm[: h // 2] = 1.0
        sampler = self._make_sampler(self.config.sampler)
        sampler.sample(warm, self.config.light_count)
        warm[: h // 8, : h // 4] = 3.0
        sampler.sample(warm, self.config.light_count)

    async def _ensure_tables(self) -> None:
        from lightprobe.device.hdr.rolling import RollingMerge

        if self._geo is None:
            if self._tables is None:
                self._tables = asyncio.ensure_future(asyncio.to_thread(self._build_geometry))
            task = self._tables
            try:
                self._geo = await asyncio.shield(task)
            finally:
                if task.done():
                    self._tables = None
        if self._refine and self._refining is None and self.latest is not None:
            # the balanced table, behind the live one, once the first lights are out
            self._refining = asyncio.ensure_future(asyncio.to_thread(self._build_geometry, False))
        if self._refining is not None and self._refining.done():
            task, self._refining, self._refine = self._refining, None, False
            try:
                geo = task.result()
            except Exception as e:  # the coarse table keeps serving; the next start builds again
                log.warning("balanced projection table failed: %s", e)
            else:
                if geo.rows == self._geo.rows:  # same output pixels: the rolling estimate carries over
                    self._geo = geo
                    self._steps = 0  # its frames link kernels for its arrays: release after them
                    self._release_due = True
                    log.info("balanced projection table in use")
        if self._merge is None:
            self._merge = RollingMerge(self._geo.rows, width=2 * self._geo.height,
                                       max_slots=self.config.max_exposures + 2,
                                       by_response=self._geo.weighs_by_response(self.camera.mode.format))
        if self._sampler is None:
            if self._sampler_warm is not None:
                task = self._sampler_warm
                try:  # warm-up only: a failure costs the first frame time, nothing else
                    await asyncio.shield(task)
                except Exception as e:
                    log.debug("sampler warm-up failed: %s", e)
                finally:
                    if task.done():
                        self._sampler_warm = None
            self._sampler = self._make_sampler(self.config.sampler)

    # ---- one frame ----------------------------------------------------------------------------
    async def step(self) -> FrameResult:
        """Capture one frame and push it through every stage."""
        if not self._started:
            await self.start()
        t0, c0 = time.perf_counter(), time.process_time()
        if self._deferred is not None:
            # the last frame's replan, now that its light set is published: it held that set
            # back by its 5-20 ms (glass-to-host p99); before this frame's controls are chosen,
            # so the frames and controls are the same as with the replan in its own step
            deferred, self._deferred = self._deferred, None
            await asyncio.to_thread(self._advance_schedule, *deferred)
        t_plan = time.perf_counter()
        frame, exposure, gain = await self._capture()
        t1, c1 = time.perf_counter(), time.process_time()
        await self._ensure_tables()
        t2, c2 = time.perf_counter(), time.process_time()
        result = await asyncio.to_thread(self._process, frame, exposure, gain)
        # wall seconds per stage, and the process's CPU seconds while the camera delivered the
        # frame (a simulator's rendering; a real camera's driver) and while the frame was processed
        result.timings = {"plan": t_plan - t0, "capture": t1 - t_plan, "tables_wait": t2 - t1, **result.timings,
                          "total": time.perf_counter() - t0, "capture_cpu": c1 - c0,
                          "process_cpu": time.process_time() - c2}
        self._update_stats(result)
        self._steps += 1
        if self._steps == RELEASE_AFTER_FRAMES and self._release_due:
            # the start is over (every kernel the frames use is linked, the tables swapped in):
            # hand back its garbage and the start's library pages once (lightprobe.device.allocator)
            from lightprobe.device.allocator import release_memory

            self._release_due, _START_RELEASED[0] = False, True
            await asyncio.to_thread(release_memory)
        self.latest = result
        return result

    async def _capture(self) -> tuple[Frame, float, float]:
        """One usable frame and the (exposure, gain) it shows."""
        from lightprobe.device.burst import capture_burst

        assert self._schedule is not None
        caps = self.camera.capabilities
        t, g = self._schedule.next()
        first = max(30.0, self.config.capture_timeout_s) if self._stream_on else None
        if caps.has_frame_metadata:
            await self.camera.apply(Controls(exposure_s=t, gain=g))
            wait = (first or self.config.capture_timeout_s) + 4 * max(c[0] for c in self._schedule.controls)
            # live: the newest frame, not the oldest queued (every frame says what it shows)
            self.frames_drained += await self.camera.drain()
            frame = await self.camera.capture(wait)
            self._stream_on = False
            if frame.meta.exposure_verified:
                return frame, float(frame.meta.exposure_s), float(frame.meta.gain)
        if self._settled == (t, g) and not self._stream_on:
            # the sensor already runs these controls (the last frame verified them): the next
            # frame shows them, no settling
            frame = await self.camera.capture(self.config.capture_timeout_s + 4 * t)
            return frame, t, g
        frames = await capture_burst(self.camera, [t], gain=g, timeout=self.config.capture_timeout_s,
                                     first_timeout=first, pipelined=False)
        self._stream_on = False
        self._settled = (t, g)
        return frames[0], t, g

    def _process(self, frame: Frame, exposure: float, gain: float) -> FrameResult:
        """Fuse and project the frame, merge, test for change, sample (in a worker thread)."""
        geo, merge = self._geo, self._merge
        t0 = time.perf_counter()
        self._frame += 1
        lut, dark = geo.lut(exposure, gain, frame.format, frame.black_level, frame.white_level)
        codes = np.ascontiguousarray(frame.data).reshape(-1, 3)
        if codes.dtype not in (np.uint8, np.uint16):
            from lightprobe.device.hdr.fusion import as_index

            codes = as_index(codes, lut.shape[0] - 1).reshape(-1, 3)
        t1 = time.perf_counter()
        fused = merge.update((exposure, gain), self._frame, geo.table, geo.geo_n, geo.mean_gain, codes,
                             lut, dark, geo.sharing, exposure_middle(frame.meta))
        equirect = geo.equirect_map(fused)
        t2 = time.perf_counter()
        sensor_t = float(frame.meta.timestamp_s)
        now = time.time()
        captured = captured_at(frame)
        lum_w = geo.weighted_luminance(fused)
        coarse = geo.coarse_energy(lum_w)
        self._change.observe(merge.changed, merge.held)
        skipped = self._unchanged(coarse, fused)
        settling = self._settling()
        if skipped:
            lights = replace(self.latest.lights, frame=self._frame, timestamp=now, stale=False,  # type: ignore[union-attr]
                             settling=settling, captured=captured)
        else:
            lights = self._sample(self._sampler, equirect, self.config.light_count)
            lights.frame, lights.timestamp, lights.settling = self._frame, now, settling
            lights.captured = captured
            if geo.coverage is not None:  # a lens that is not a fisheye: what it does not see is unknown
                lights.extra["seen"] = round(geo.seen, 4)
            self._change.sampled(coarse, lum_w, merge.held)
        t3 = time.perf_counter()
        if self._is_preview_exposure(exposure, gain):
            self._preview = (frame, lut)
        # the fused map stays valid through the next step's start (the merge's buffers swap)
        self._deferred = (fused, sensor_t, (exposure, gain), codes.reshape(np.shape(frame.data)), lut)
        sched = self._schedule
        assert sched is not None
        bounded = float(merge.bounded.mean())
        preview = self._preview
        return FrameResult(
            frame=self._frame, timestamp=now, equirect=equirect, lights=lights,
            exposures=[c[0] for c in sched.controls], gains=[c[1] for c in sched.controls],
            exposure_s=exposure, gain=gain,
            timings={"prepare": t1 - t0, "fusion": t2 - t1, "sampling": t3 - t2},
            skipped=skipped, calibration_id=self._calibration_id, unit=self.unit,
            saturated_fraction=bounded, sensor_time_s=sensor_t, captured=captured, coverage=geo.coverage,
            preview_source=(lambda p=preview, g_=geo: g_.linear_frame(*p)) if preview is not None else None)

    def _is_preview_exposure(self, exposure: float, gain: float) -> bool:
        sched = self._schedule
        if sched is None or not sched.controls:
            return True
        mid = sched.controls[len(sched.controls) // 2]
        return (exposure, gain) == mid or self._preview is None

    def _advance_schedule(self, fused: np.ndarray, sensor_t: float, key: tuple[float, float],
                          codes: np.ndarray, lut: np.ndarray) -> None:
        """Replan from the fused map when a cycle is done (or a second passed): the planner's
        rates are the map's radiance per unit exposure at each output pixel; its peak is also
        the sensor pixels' of the frame just taken, the shortest exposure
        (:func:`lightprobe.device.burst.frame_peak_rate`: a sun smaller than an output pixel
        saturates sensor pixels the map's mean does not show)."""
        sched = self._schedule
        assert sched is not None
        if sched.sweep:  # the sensor pixels' peak of each frame of a metering sweep
            self._peaks.append(frame_peak_rate(codes, lut, self._geo.full_scale,
                                               max_isolation=self._planner.max_isolation))
        if not sched.cycle_done and sensor_t - self._planned_at < _REPLAN_S:
            return
        if not sched.cycle_done and sched.sweep:
            return  # a metering sweep runs to its end
        if not sched.sweep and key != sched.controls[0]:
            return  # plan right after the shortest exposure: what no exposure measures is saturated
                    # in it too (a lamp's edge a long frame saw move is not)
        geo, merge = self._geo, self._merge
        if not sched.sweep:  # the sensor pixels' peak of this frame, the shortest exposure
            self._peaks.append(frame_peak_rate(codes, lut, geo.full_scale, max_isolation=self._planner.max_isolation))
        shape = (geo.height // 2, 2 * geo.height)
        # the brightest channel (three strided passes: numpy's max over a length-3 axis is 4x slower)
        top = np.maximum(np.maximum(fused[:, 0], fused[:, 1]), np.maximum(fused[:, 2], 0.0))
        rates = (top * geo.inv_gain_out / geo.full_scale).reshape(shape)
        saturated = merge.bounded.reshape(shape).copy()
        weights = geo.solid_angle_out.reshape(shape)
        # keep headroom for the brightest the scene showed lately (a lamp that switches)
        measured = self._planner.measured_levels(rates, saturated=saturated, weights=weights)
        levels = self._planner.scene_levels(rates, measured=measured)
        peak = self._sensor_peak(sched.sweep)
        self._bright = [(t, s) for t, s in self._bright if sensor_t - t <= _MEMORY_S]
        self._bright.append((sensor_t, max(levels[1] if levels else 0.0, peak)))
        recent = max(s for _, s in self._bright)
        # hysteresis on the peak the bracket is planned for (with the sensor peak's margin): kept
        # while the peak stays within [1 / _PEAK_DROP, _PEAK_RISE] of it, so a peak's scatter (a
        # sun between pixels) re-times no exposure; beyond, replanned at once (well before a
        # clip: the planned peak sits at the bright target with sensor_peak_margin to spare)
        if not sched.sweep and self._planned_peak / _PEAK_DROP <= recent <= self._planned_peak * _PEAK_RISE:
            recent = self._planned_peak
        self._planned_peak = recent
        controls = self._planner.controls(rates, saturated=saturated, weights=weights, min_peak=recent,
                                          measured=measured)
        if not sched.sweep:  # hysteresis: an exposure within ~15% of one in use stays as it is
            controls = keep_in_use(controls, sched.controls)
        keep = set(controls)
        merge.forget(keep, older_than=self._frame - 2 * len(controls))
        self._first_cycle = sched.sweep  # the first planned bracket starts its first cycle
        self._schedule = ExposureSchedule(controls, hold=self._hold())
        self._planned_at = sensor_t

    def _settling(self) -> bool:
        """Whether the set made from this frame is marked ``settling``: through the metering
        sweep and the first cycle of the bracket planned from it, when the estimate of each
        exposure rests on one frame (a sun measured once by the sweep's shortest exposure carries
        that frame's shot noise: ~1.4% of a 3e4:1 scene's diffuse light, gone after one cycle of
        the planned bracket averages it). A start-up state, never a hiding place: the cycle is
        at most ``2 (max_exposures - 1)`` frames with per-frame metadata, and any replan (at the
        latest ``_REPLAN_S`` of sensor time after the plan) ends it."""
        sched = self._schedule
        if sched is None:
            return False
        return sched.sweep or (self._first_cycle and not sched.cycle_done)

    def _sensor_peak(self, sweep: bool) -> float:
        """The peak rate the sensor pixels showed for this plan: the shortest exposure's just
        taken, or of a sweep's frames the brightest that was not saturated (a saturated
        pixel's rate is a lower bound: ``saturated_headroom`` x it when nothing better was seen)."""
        peaks, self._peaks = self._peaks, []
        if not peaks:
            return 0.0
        planner = self._planner
        if not sweep:
            rate, saturated = peaks[-1]
            return rate * (planner.saturated_headroom if saturated else planner.sensor_peak_margin)
        measured = [r for r, sat in peaks if not sat]
        return (max(measured) * planner.sensor_peak_margin if measured
                else max(r for r, _ in peaks) * planner.saturated_headroom)

    def _unchanged(self, coarse: np.ndarray, fused: np.ndarray) -> bool:
        if self.latest is None:
            return False
        sched = self._schedule
        if sched is not None and (sched.sweep or sched.pos <= len(sched.order)):
            return False  # the estimate is still taking in a new schedule's exposures
        return self._change.unchanged(coarse, fused, self._geo.solid_angle_out,
                                      threshold=self.config.change_threshold, max_skip_s=self.config.max_skip_s)

    @property
    def unit(self) -> str:
        return "relative" if self.calibration.photometric is None else self.calibration.photometric.unit

    def _sample(self, sampler: Any, equirect: np.ndarray, count: int) -> Any:
        lights, self._extra_lights = _useful_lights(sampler, equirect, count, self._extra_lights)
        lights.probe = self.config.probe_id
        lights.unit = self.unit
        if self.calibration.pose is not None:
            lights.pose = self.calibration.pose.to_json()
        return lights

    def _update_stats(self, r: FrameResult) -> None:
        s = self.stats
        s["frames"] += 1
        s["frames_skipped"] += int(r.skipped)
        s["frames_drained"] = self.frames_drained  # queued frames skipped to stay live
        s["last_timings"] = r.timings
        s["exposures"] = r.exposures
        now = time.monotonic()
        if self._t_last is not None:
            inst = 1.0 / max(now - self._t_last, 1e-6)
            s["fps"] = inst if s["fps"] == 0 else 0.9 * s["fps"] + 0.1 * inst
        self._t_last = now
        s["fps"] = float(s["fps"]) if math.isfinite(s["fps"]) else 0.0


def _useful_lights(sampler: Any, equirect: np.ndarray, count: int, extra: int) -> tuple[Any, int]:
    """``count`` lights that carry energy, and the new ``extra``. A tree sampler keeps leaves
    over the empty lower hemisphere (its 12 base quads cannot merge); those are not published,
    and the sampler is asked for ``extra`` more (as many as it wasted last time), so hosts get
    ``count`` useful lights."""
    for _ in range(8):  # converges in 1-3 calls; later frames reuse the estimate
        lights = sampler.sample(equirect, count + extra)
        keep = lights.rgb.sum(axis=1) > 0
        wasted = int((~keep).sum())
        short = count - (len(lights) - wasted)
        if short == 0 or keep.sum() == 0 or (short > 0 and wasted == 0):
            break
        extra = max(0, extra + short)
    if not keep.all():
        lights = replace(lights, directions=lights.directions[keep], rgb=lights.rgb[keep],
                         solid_angle=lights.solid_angle[keep], ids=lights.ids[keep])
    return lights, extra


def lights_on_demand(result: FrameResult, method: str, count: int) -> Any:
    """A light set of ``count`` lights from a published frame's map with a fresh ``method``
    sampler (blocking: call in a thread). It needs the frame only, not the pipeline that made
    it: a camera reconnecting, a calibration session or a pipeline rebuilt after a change all
    keep the last good frame sampleable. The set carries that frame's number, time, probe, unit
    and pose."""
    from lightprobe.device.sampling.registry import SAMPLERS, make_sampler

    if method not in SAMPLERS:
        raise InputError(f"method {method!r} is not one of {sorted(SAMPLERS)}", param="method")
    if not 1 <= int(count) <= 10000:
        raise InputError(f"count={count!r} must be in [1, 10000]", param="count")
    lights, _ = _useful_lights(make_sampler(method), result.equirect, int(count), 0)
    published = result.lights
    lights.frame, lights.timestamp, lights.captured = result.frame, result.timestamp, result.captured
    lights.probe, lights.unit = published.probe, result.unit
    lights.pose = published.pose
    return lights
