"""SimCamera: the simulated probe camera, implementing :class:`lightprobe.drivers.base.Camera` exactly.

A frame is: scene truth at the frame's virtual time (light intensities averaged over the
exposure) -> lens render (:mod:`lightprobe.sim.lens`; the static base map once per lens, each dynamic light
as its own small sensor image scaled by its intensity: the render is linear) -> vignetting ->
sensor noise and quantisation in one compiled pass (:mod:`lightprobe.sim.sensor`) -> faults
(:mod:`lightprobe.sim.faults`). About 10 ms of CPU per VGA frame, so the simulator costs what a camera
costs. Heavy numpy work runs in ``asyncio.to_thread``.

Clock and latency. Frame ``i`` (sequence ``i``) occupies the virtual time ``[t_i, t_i + d_i)``,
``d_i = max(1 / mode.max_fps, exposure)`` (a sensor's frame time stretches to fit a longer
exposure; dropped frames advance ``t`` too), so with a fixed mode and short exposures ``t_i = i /
fps``. Its exposure is the end of that interval, ``[t_i + d_i - exposure, t_i + d_i)``: a
streaming sensor ends each frame's exposure at its readout, one frame time after the last one's,
whatever the exposure (the sensor is a global shutter: every row sees the same window, as the
render does). ``apply()`` called when the next frame is ``s`` lands on frame ``s + k`` (``k =
control_latency_frames``, default 2): frames ``s .. s + k - 1`` carry, truthfully, the old
exposure and gain in their metadata. Sequence numbers and the clock continue across close/open.
With ``realtime=True`` frames are paced (``asyncio.sleep``): a frame is delivered when its
exposure and its readout (``readout_s``, default 8 ms: a binned mode of a Pi camera module, e.g.
the IMX708's 2x2 mode, which reads out at 120 fps) are over, at ``t_i + d_i + readout_s``, so
frames come one frame time apart, a short exposure after a long one included; a consumer that
falls more than ``BUFFERS`` frames behind loses the frames it missed (sequence gaps, as a
driver's full buffer queue drops them). By default frames are returned as fast as they are
computed.

Timestamps. ``FrameMetadata.timestamp_s`` is the start of the frame's exposure, ``epoch + t_i +
d_i - exposure``. With ``realtime`` (how the service runs it) the epoch is set when the first
frame after each ``open()`` is out (not counting what the simulator spent loading its lens), so
that the stamps are CLOCK_MONOTONIC's, as the protocol promises and as a host maps them to the
wall clock. Unpaced, frames come as fast as they are computed, faster than the light they show
could have: no clock's time is theirs, and the epoch is 0 (the stamps are the virtual clock,
exactly, so runs in sensor time stay deterministic to the bit). :meth:`SimCamera.scene_time`
maps a stamp back to the virtual time the scene and the truth functions take
(``extra["sim_time_s"]`` carries it too).

Read-ahead. Because of that latency, once frame ``s`` is out the exposure and gain of frames
``s + 1 .. s + k`` are already fixed (a new ``apply()`` lands at ``s + 1 + k`` at the earliest),
so the camera starts computing those frames in worker threads while the caller works, up to the
frame where the last requested control lands (the frames a burst waits for). A read-ahead frame
is used only if the frame finally captured has exactly the same sequence, time, controls and
mode and no fault touched it, so the pixels are the same as without read-ahead (same inputs, same
per-frame noise seed). No read-ahead while a fault is armed or with ``latency_frames=0``.

Ground truth: :meth:`SimCamera.truth_calibration`, :meth:`truth_radiance`,
:meth:`render_radiance_image`, :attr:`scene`, :attr:`sensitivity`, :attr:`lens`, :attr:`sensor`.
Deterministic for a seed: frame noise comes from ``default_rng((seed, sequence))``.
"""

from __future__ import annotations

import asyncio
import copy
import os
import time
from typing import Any

import numpy as np

from lightprobe.core.calibration import Calibration
from lightprobe.drivers.base import (
    BoardTarget,
    Camera,
    CameraDisconnected,
    CameraError,
    CameraUnavailable,
    Capabilities,
    CaptureTimeout,
    ControlNotSupported,
    Controls,
    Frame,
    FrameMetadata,
    Mode,
    PixelFormat,
)

from .faults import FaultKind, FaultPlan
from .lens import SimLens, standard_lens
from .scene import Scene, rasterize_disc
from .sensor import SensorModel, raw_levels

__all__ = ["BUFFERS", "DEFAULT_MODES", "SimCamera"]

BUFFERS = 4  # realtime: frames a consumer may fall behind before the camera drops (a driver's queue)

DEFAULT_MODES: tuple[Mode, ...] = (
    Mode(640, 480, PixelFormat.RGB8, 30.0),
    Mode(640, 480, PixelFormat.RAW12, 30.0),
    Mode(640, 480, PixelFormat.RAW10, 30.0),
    Mode(1280, 960, PixelFormat.RGB8, 15.0),
    Mode(1280, 960, PixelFormat.RAW12, 15.0),
)


def _retrieve(fut: asyncio.Future[np.ndarray]) -> None:
    if not fut.cancelled():
        fut.exception()  # an unused read-ahead frame's error is not worth a warning


class SimCamera(Camera):
    """The simulated probe (see the module docstring).

    Parameters
    ----------
    scene : a :class:`Scene`, a scenario name or an equirect file path (``lightprobe.sim.scenarios``);
        None means the static ``room`` scenario.
    seed : noise and scenario seed.
    latency_frames : frames between ``apply()`` and the first frame that shows it.
    realtime : pace frames at the mode's frame rate.
    scene_scale : multiplies the scene's radiance (truth included).
    sensor : noise model; ``SensorModel()`` by default (sensitivity 1e4 e- per unit x s).
    shared_data : where named scenarios find ``envmaps/`` (default ``../shared/data``).
    read_ahead : compute frames whose controls are fixed in worker threads (module docstring).
    cache_dir : keep the lens render matrices on disk there (building one takes ~1 s; the
        service passes its state cache, so a restarted simulated probe loads them).
    readout_s : realtime: seconds from the end of a frame's exposure to its delivery.
    """

    name = "sim"
    driver = "sim"

    def __init__(self, scene: Scene | str | os.PathLike[str] | None = None, *, seed: int = 0,
                 latency_frames: int = 2, realtime: bool = False, scene_scale: float = 1.0,
                 sensor: SensorModel | None = None, modes: tuple[Mode, ...] = DEFAULT_MODES,
                 exposure_range: tuple[float, float] = (1e-5, 1.0),
                 gain_range: tuple[float, float] = (1.0, 16.0),
                 shared_data: str | os.PathLike[str] | None = None, read_ahead: bool = True,
                 readout_s: float = 0.008,
                 cache_dir: str | os.PathLike[str] | None = None) -> None:
        if not isinstance(scene, Scene):
            from .scenarios import load_scene

            scene = load_scene("room" if scene is None else scene, seed=seed, shared_data=shared_data)
        if scene_scale != 1.0:  # a shallow copy: the caller's scene keeps its own scale
            scene = copy.copy(scene)
            scene.scale *= float(scene_scale)
        if latency_frames < 0:
            raise ValueError(f"latency_frames must be >= 0, got {latency_frames}")
        self._scene = scene
        self.seed = int(seed)
        self.realtime = bool(realtime)
        self.readout_s = float(readout_s)
        self.sensor = sensor or SensorModel()
        self.faults = FaultPlan()
        self._board: tuple[Any, float] | None = None  # (lightprobe.sim.board.BoardSchedule, start time)
        self._technician = False  # the board shown is present_board's simulated technician
        self._caps = Capabilities(exposure_range=exposure_range, gain_range=gain_range,
                                  modes=tuple(modes), has_frame_metadata=True,
                                  control_latency_frames=int(latency_frames),
                                  model="lightprobe-sim", serial=f"sim-{seed}")
        self._mode = self._caps.modes[0]
        self._lenses: dict[tuple[int, int], SimLens] = {}
        self._static: dict[tuple[object, ...], np.ndarray] = {}  # the base map's sensor image per lens
        self._columns: dict[tuple[object, ...], Any] = {}  # the lens's render matrix, column-major
        self._light_images: dict[tuple[object, ...], tuple[np.ndarray, np.ndarray]] = {}
        self.cache_dir = None if cache_dir is None else os.fspath(cache_dir)
        self.read_ahead = bool(read_ahead)
        self._ahead: dict[tuple[object, ...], asyncio.Future[np.ndarray]] = {}  # read-ahead frames
        self._last_landing = -1  # sequence on which the last apply() lands
        self._open = False
        self._unplugged_until = 0.0
        self._lock = asyncio.Lock()
        self._seq = 0
        self._t = 0.0
        self._epoch = 0.0  # CLOCK_MONOTONIC of virtual time 0 when realtime (module docstring)
        self._clocked = False
        self._reset_controls()

    # -- protocol ---------------------------------------------------------------------------------
    def _reset_controls(self) -> None:
        lo, hi = self._caps.exposure_range
        self._exposure = float(min(hi, max(lo, 1.0 / 60.0)))
        self._gain = float(self._caps.gain_range[0])
        self._pending: list[tuple[int, Controls]] = []

    async def open(self) -> None:
        if time.monotonic() < self._unplugged_until:
            raise CameraUnavailable("simulated camera is unplugged", device=self.name)
        if not self._open:
            self._reset_controls()
            self._clocked = False  # realtime: the epoch is set when the first frame is out
            # load the sensor model's compiled kernels now (a driver is loaded before it
            # streams), so the first frame does not pay for them; off the loop (numba's first
            # call loads its CPU target: ~0.1 s)
            await asyncio.to_thread(self._warm_kernels)
        self._open = True

    def _warm_kernels(self) -> None:
        from lightprobe.sim._sparse import warm_kernels

        self.sensor.expose(np.zeros((2, 2, 3), np.float32), 1e-3, 1.0, self.mode.format, self.seed, 0)
        warm_kernels()  # the render matrix's loops

    async def close(self) -> None:
        self._open = False
        self._ahead.clear()

    @property
    def capabilities(self) -> Capabilities:
        return self._caps

    @property
    def mode(self) -> Mode:
        return self._mode

    async def set_mode(self, mode: Mode) -> None:
        if mode not in self._caps.modes:
            raise ControlNotSupported(f"mode {mode} is not one of the camera's modes", device=self.name)
        self._mode = mode

    async def apply(self, controls: Controls) -> None:
        self.check_controls(controls)
        self._require_open()
        self._pending.append((self._seq + self._caps.control_latency_frames, controls))
        self._last_landing = self._seq + self._caps.control_latency_frames

    async def capture(self, timeout: float = 1.0) -> Frame:  # noqa: ASYNC109 - the protocol's signature
        async with self._lock:
            self._require_open()
            fx = self.faults.next_capture()
            if fx.drop:
                self._advance(fx.drop)
            if fx.raise_kind is not None:
                await self._raise_fault(fx.raise_kind, fx.duration_s, timeout)
            if self.realtime and self._clocked:
                self._drop_missed()
            seq, t = self._seq, self._t
            self._land_controls(seq)
            exposure, gain, mode = self._exposure, self._gain, self._mode
            self._advance(1)
            ahead = self._ahead.pop((seq, t, exposure, gain, mode), None)
            if ahead is not None and not fx.lens_cap:
                data = await ahead
            else:
                data = await asyncio.to_thread(self._make_frame, self._exposure_start(t, exposure, mode), seq,
                                               exposure, gain, mode, fx.lens_cap)
            self._read_ahead()
            if fx.hot_pixels:
                white = 255 if mode.format is PixelFormat.RGB8 else int(raw_levels(mode.format)[1])
                FaultPlan.apply_hot_pixels(data, fx.hot_pixels, white)
            if self.realtime:
                if not self._clocked:  # the first frame after open() is out now (whatever the
                    # simulator spent loading its lens): the stamps are the clock's from here on
                    self._epoch, self._clocked = time.monotonic() - (self._complete_at(t, exposure) - self._epoch), True
                await self._pace(self._complete_at(t, exposure), timeout)
        levels = (0.0, 255.0) if mode.format is PixelFormat.RGB8 else raw_levels(mode.format)
        start = self._exposure_start(t, exposure, mode)
        meta = FrameMetadata(exposure_s=exposure, gain=gain, timestamp_s=self._epoch + start, sequence=seq)
        return Frame(data, meta, mode.format, black_level=levels[0], white_level=levels[1],
                     extra={"sim_time_s": start, "scene": self._scene.name})

    # -- internals --------------------------------------------------------------------------------
    def _require_open(self) -> None:
        if time.monotonic() < self._unplugged_until:
            raise CameraDisconnected("simulated camera was unplugged", device=self.name)
        if not self._open:
            raise CameraUnavailable("simulated camera is not open", device=self.name)

    def _advance(self, frames: int) -> None:
        """``frames`` sensor frames at the current exposure go by."""
        self._seq += frames
        self._t += frames * self.frame_duration(self._exposure)

    def frame_duration(self, exposure_s: float, mode: Mode | None = None) -> float:
        """Seconds one frame takes: the mode's frame time, or the exposure when that is longer
        (a sensor's frame stretches to fit its exposure, as libcamera's FrameDurationLimits do)."""
        return max(1.0 / (mode or self._mode).max_fps, float(exposure_s))

    def _read_ahead(self) -> None:
        """Start computing the frames whose controls are already fixed (module docstring)."""
        k = self._caps.control_latency_frames
        if k < 1 or not self.read_ahead or self.faults.active or not self._open:
            self._ahead.clear()
            return
        self._ahead = {key: f for key, f in self._ahead.items() if key[0] >= self._seq}  # type: ignore[operator]
        # Replay _land_controls / _advance on copies, frame by frame, exactly as capture() will
        seq, t, exposure, gain, pending = self._seq, self._t, self._exposure, self._gain, list(self._pending)
        for _ in range(k):
            if seq > self._last_landing:
                break  # nobody waits for a control to land there
            still = []
            for eff, c in pending:
                if eff <= seq:
                    exposure = exposure if c.exposure_s is None else float(c.exposure_s)
                    gain = gain if c.gain is None else float(c.gain)
                else:
                    still.append((eff, c))
            pending = still
            key = (seq, t, exposure, gain, self._mode)
            if key not in self._ahead:
                fut = asyncio.ensure_future(
                    asyncio.to_thread(self._make_frame, self._exposure_start(t, exposure, self._mode), seq,
                                      exposure, gain, self._mode, False))
                fut.add_done_callback(_retrieve)
                self._ahead[key] = fut
            seq, t = seq + 1, t + self.frame_duration(exposure)

    def _land_controls(self, seq: int) -> None:
        """Apply the pending requests whose landing frame has come (in request order)."""
        still = []
        for eff, c in self._pending:
            if eff <= seq:
                self._exposure = self._exposure if c.exposure_s is None else float(c.exposure_s)
                self._gain = self._gain if c.gain is None else float(c.gain)
            else:
                still.append((eff, c))
        self._pending = still

    async def _raise_fault(self, kind: FaultKind, duration_s: float, wait_s: float) -> None:
        self._advance(1)  # the frame is lost
        if kind is FaultKind.CAPTURE_ERROR:
            raise CameraError("simulated capture error", device=self.name)
        if kind is FaultKind.TIMEOUT:
            await asyncio.sleep(max(0.0, wait_s))
            raise CaptureTimeout(f"no frame within {wait_s} s (simulated)", device=self.name)
        self._open = False
        self._unplugged_until = time.monotonic() + duration_s
        raise CameraDisconnected("simulated camera disconnected", device=self.name)

    def _drop_missed(self) -> None:
        """Realtime: the frames a consumer more than ``BUFFERS`` frames behind missed go by
        (a driver's full queue drops them)."""
        frame = self.frame_duration(self._exposure)
        behind = time.monotonic() - self._complete_at(self._t, self._exposure)
        if behind > BUFFERS * frame:
            self._advance(int(behind / frame) - BUFFERS + 1)

    async def drain(self) -> int:
        """Realtime: skip the complete frames behind the newest complete one (not rendered:
        they cost what a driver's dropped buffer does). Unpaced, every frame is due at once:
        nothing to drain."""
        if not (self.realtime and self._clocked and self._open):
            return 0
        now, n = time.monotonic(), 0
        # while the frame after the next one is complete too, the next one is not the newest
        while self._complete_at(self._t + self.frame_duration(self._exposure), self._exposure) <= now:
            self._advance(1)
            n += 1
        return n

    def _exposure_start(self, t: float, exposure_s: float, mode: Mode) -> float:
        """Virtual time the exposure of the frame starting at ``t`` begins: its frame's end
        less the exposure (module docstring)."""
        return t + self.frame_duration(exposure_s, mode) - exposure_s

    def _complete_at(self, t: float, exposure_s: float) -> float:
        """CLOCK_MONOTONIC when the frame starting at virtual time ``t`` is exposed and read
        out (realtime): its frame's end plus the readout."""
        return self._epoch + t + self.frame_duration(exposure_s) + self.readout_s

    def scene_time(self, timestamp_s: float) -> float:
        """The virtual time (the scene's and the truth functions') of a frame stamped
        ``timestamp_s`` since the last ``open()`` (module docstring)."""
        return float(timestamp_s) - self._epoch

    async def _pace(self, at: float, wait_s: float) -> None:
        """Wait until CLOCK_MONOTONIC ``at``."""
        delay = at - time.monotonic()
        if delay > wait_s:
            await asyncio.sleep(wait_s)
            raise CaptureTimeout(f"no frame within {wait_s} s", device=self.name)
        if delay > 0:
            await asyncio.sleep(delay)

    def _make_frame(self, t: float, seq: int, exposure: float, gain: float, mode: Mode,
                    lens_cap: bool) -> np.ndarray:
        """Pixels of one frame whose exposure starts at virtual time ``t`` (runs off the event
        loop): sensor-plane irradiance, then the
        sensor's noise and quantisation in one compiled pass (``SensorModel.expose``)."""
        lens = self.lens_for(mode)
        if lens_cap:
            w, h = lens.size
            irr = np.zeros((h, w, 3), np.float32)
        elif self._board is not None:  # a technician's checkerboard in front (show_board)
            rad = self._render(lens, self._scene.radiance_equirect(t, exposure))
            rad = self._board[0].composite(rad, t - self._board[1], lens)
            irr = rad * lens.vignetting_image()[..., None]
        else:
            irr = self._irradiance(t, exposure, lens)
        return self.sensor.expose(irr, exposure, gain, mode.format, self.seed, seq)

    def _render(self, lens: SimLens, eq: np.ndarray) -> np.ndarray:
        if self.cache_dir is not None:
            from ._lenscache import load_render_matrix

            load_render_matrix(lens, eq.shape[0], self.cache_dir)
        return lens.render(eq)

    def _irradiance(self, t: float, exposure: float, lens: SimLens) -> np.ndarray:
        """Sensor-plane radiance x vignetting (H, W, 3) float32 of the scene at ``t`` over the
        exposure: the static base map rendered once per lens, plus each dynamic light's own
        sensor-plane image (its disc rasterised and pushed through the lens's columns only),
        scaled by its mean intensity over the exposure. Equal to rendering the whole map every
        frame (the render is linear), at a few percent of its cost."""
        sc = self._scene
        h = sc.height
        key = (lens.size, h)
        static = self._static.get(key)
        if static is None:
            eq = sc.base * np.float32(sc.scale) if sc.scale != 1.0 else sc.base
            static = self._render(lens, eq) * lens.vignetting_image()[..., None]
            static.flags.writeable = False
            cols = lens.render_matrix(h).transpose()  # a light's columns, as rows
            self._static[key] = static
            self._columns[key] = cols
        out = static.copy()
        if not sc.lights:
            return out
        cols = self._columns[key]
        vig = lens.vignetting_image().ravel()
        flat = out.reshape(-1, 3)
        for light in sc.lights:
            k = light.mean_intensity(t, exposure) * sc.scale
            if k <= 0:
                continue
            d = light.direction_at(t + exposure / 2)
            pk = (id(light), *np.round(d, 12).tolist())
            hit = self._light_images.get(pk)
            if hit is None:  # the light's sensor image per unit radiance: (pixels, weights)
                rows, cc, frac = rasterize_disc(h, d, light.radius_rad)
                img = cols.rows_combination(rows * 2 * h + cc, frac)
                nz = np.flatnonzero(img)
                hit = (nz, (img[nz] * vig[nz]).astype(np.float32))
                if len(self._light_images) > 64:
                    self._light_images.clear()
                self._light_images[pk] = hit
            px, wt = hit
            flat[px] += wt[:, None] * (np.asarray(light.rgb, np.float32) * np.float32(k))[None, :]
        return out

    @property
    def board_schedule(self) -> Any:
        """The :class:`lightprobe.sim.board.BoardSchedule` shown now (``show_board``), or None."""
        return None if self._board is None else self._board[0]

    def present_board(self, board: BoardTarget | None) -> bool:
        """The simulated technician (the protocol's optional capability): nobody stands in front
        of a simulated lens, so for a live calibration session a technician
        (:meth:`lightprobe.sim.board.BoardSchedule.technician`) sweeps ``board`` through the image circle;
        ``None`` takes it away. A schedule a test already shows (``show_board``) is kept."""
        if board is None:
            if self._technician:
                self.show_board(None)
                self._technician = False
            return True
        if self._board is not None:
            return True  # a test's own schedule is in front already
        from .board import BoardSchedule

        self.show_board(BoardSchedule.technician(board.cols, board.rows, board.square))
        self._technician = True
        return True

    def factory_calibration(self) -> Calibration:
        """The simulator carries its ground truth (:meth:`truth_calibration`)."""
        return self.truth_calibration()

    def show_board(self, schedule: Any) -> None:
        """Show a technician's checkerboard (a :class:`lightprobe.sim.board.BoardSchedule`) over the scene
        from the next frame on, its clock starting then; ``None`` takes it away. Frames read
        ahead before the change are dropped."""
        self._board = None if schedule is None else (schedule, self._t)
        ahead = getattr(self, "_ahead", None)
        if ahead is not None:
            ahead.clear()

    # -- ground truth -----------------------------------------------------------------------------
    def lens_for(self, mode: Mode | None = None) -> SimLens:
        """The lens on the sensor of ``mode`` (default: the current mode)."""
        m = mode or self._mode
        if m.size not in self._lenses:
            self._lenses[m.size] = standard_lens(m.width, m.height)
        return self._lenses[m.size]

    @property
    def lens(self) -> SimLens:
        return self.lens_for()

    @property
    def scene(self) -> Scene:
        return self._scene

    @property
    def sensitivity(self) -> float:
        """Electrons per (scene radiance unit x second), before vignetting and gain."""
        return self.sensor.sensitivity

    @property
    def sequence(self) -> int:
        """Sequence number of the next sensor frame."""
        return self._seq

    @property
    def time_s(self) -> float:
        """Virtual time of the next sensor frame."""
        return self._t

    def truth_calibration(self, mode: Mode | None = None) -> Calibration:
        """The ground-truth calibration for ``mode`` (default current).

        Fisheye K, D and ``fov_deg`` (the clean field of view inside the housing ring); response
        for the mode's format (``method="truth"``: the exact inverse table of the 8-bit curve, or
        linear for raw); vignetting; photometric scale ``FW / S`` so that fused value x scale ==
        scene radiance (unit "relative"); identity pose; mask = the clean image circle.
        """
        m = mode or self._mode
        lens = self.lens_for(m)
        # Written in the calibration file's schema (CONVENTIONS.md) from the simulator's own models
        return Calibration.from_json({
            "version": Calibration.VERSION,
            "source": "truth",
            "fisheye": lens.fisheye.calibration_section(),
            "response": self.sensor.truth_response_section(m.format),
            "vignetting": lens.vignetting.calibration_section(),
            "photometric": {"scale": float(self.sensor.photometric_scale), "unit": "relative"},
            "pose": {"rotation": np.eye(3).tolist(), "position": [0.0, 0.0, 0.0]},
            "mask": {"center": [float(c) for c in lens.vignetting.center], "radius_px": float(lens.clean_radius_px)},
        })

    def truth_radiance(self, t: float | None = None) -> np.ndarray:
        """Ground-truth equirect radiance at time ``t`` (default: the next frame's time)."""
        return self._scene.radiance_equirect(self._t if t is None else t)

    def render_radiance_image(self, t: float | None = None, *, housing: bool = True,
                              mode: Mode | None = None) -> np.ndarray:
        """Noise-free, unvignetted sensor-plane radiance (H, W, 3) float32 at time ``t``."""
        lens = self.lens_for(mode)
        return lens.render(self.truth_radiance(t), housing=housing)

    def pixel_solid_angle(self, mode: Mode | None = None) -> np.ndarray:
        """Solid angle (sr) of each sensor pixel's footprint (H, W) float64."""
        return self.lens_for(mode).pixel_solid_angle()
