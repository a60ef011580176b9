"""The camera protocol every backend implements: types, errors and the async interface.

Backends (``lightprobe.drivers.v4l2``, ``lightprobe.drivers.libcamera``, ``lightprobe.drivers.uvc``) and the simulator
(``lightprobe.sim.camera``) implement :class:`Camera`; the burst logic in ``lightprobe.device.burst`` only talks to this
protocol, so the whole service runs unchanged on any of them.

Units at this boundary are SI: exposure times in seconds (drivers convert from 100 us units or
microseconds), timestamps in seconds of CLOCK_MONOTONIC. Importing this module does nothing.

Timestamps. ``FrameMetadata.timestamp_s`` is when the frame's exposure *started* (its first row,
as libcamera's ``SensorTimestamp``), on CLOCK_MONOTONIC, so the light a frame shows arrived at
``timestamp_s + exposure_s / 2`` on average (:func:`exposure_middle`) and a host can map it to
the wall clock. Backends whose hardware stamps another instant convert (V4L2's end-of-frame
stamps: :mod:`lightprobe.drivers.v4l2.camera`); the simulator stamps its virtual clock offset
to CLOCK_MONOTONIC (:mod:`lightprobe.sim.camera`).

Exposure latency. Real sensors apply a new exposure a few frames after it is requested. Frames
carry the exposure the *sensor* used: when the backend reads it from per-frame metadata
(libcamera, the simulator) ``FrameMetadata.exposure_verified`` is True; when it can only infer it
(V4L2 has no per-frame exposure), the backend sets ``exposure_verified=False`` and reports the
requested value only once its settling rule (``Capabilities.control_latency_frames`` frames after
the request) says it has landed. ``lightprobe.device.burst`` accepts a frame only when its metadata shows the
requested exposure.
"""

from __future__ import annotations

import abc
import enum
import math
import time
from dataclasses import dataclass, field
from types import TracebackType
from typing import TYPE_CHECKING, Self, TypeVar

import numpy as np

_T = TypeVar("_T")

if TYPE_CHECKING:
    from lightprobe.core.calibration import Calibration

__all__ = [
    "BoardTarget",
    "Camera",
    "CameraBusy",
    "CameraDisconnected",
    "CameraError",
    "CameraUnavailable",
    "Capabilities",
    "CaptureTimeout",
    "ControlNotSupported",
    "ControlOutOfRange",
    "Controls",
    "Frame",
    "FrameMetadata",
    "Mode",
    "PixelFormat",
    "captured_at",
    "clock_offset",
    "exposure_middle",
    "snap_exposure",
    "wall_clock",
]


@dataclass(frozen=True)
class BoardTarget:
    """A checkerboard to present for calibration: inner corners and the side of a square (in the
    session's unit; the simulator renders it in metres)."""

    cols: int
    rows: int
    square: float


# ---- Errors -------------------------------------------------------------------------------------
class CameraError(Exception):
    """Base class of camera errors. ``device`` names the camera (path, id or 'sim')."""

    def __init__(self, message: str, *, device: str | None = None) -> None:
        super().__init__(message)
        self.device = device


class CameraUnavailable(CameraError):
    """The camera does not exist or cannot be opened (missing device node, no permission)."""


class CameraBusy(CameraUnavailable):
    """Another process holds the camera (EBUSY, or a USB interface claimed by a kernel driver)."""


class CameraDisconnected(CameraError):
    """The camera went away while open (unplugged, ENODEV). Reopen to continue."""


class ControlOutOfRange(CameraError, ValueError):
    """A requested control value is outside the range the camera reports."""

    def __init__(self, control: str, value: float, lo: float, hi: float, *, device: str | None = None) -> None:
        super().__init__(f"{control}={value!r} is outside [{lo!r}, {hi!r}]", device=device)
        self.control, self.value, self.lo, self.hi = control, value, lo, hi


class ControlNotSupported(CameraError):
    """The camera has no such control (V4L2 EINVAL on the id, UVC STALL)."""


class CaptureTimeout(CameraError, TimeoutError):
    """No frame arrived within the timeout."""


# ---- Types --------------------------------------------------------------------------------------
class PixelFormat(enum.StrEnum):
    """What a frame's pixels are. ``RGB8`` is processed (non-linear response); ``RAW*`` are
    linear sensor values, demosaiced to RGB by the backend, still with the black level in."""

    RGB8 = "rgb8"
    RAW10 = "raw10"
    RAW12 = "raw12"
    RAW16 = "raw16"

    @property
    def is_raw(self) -> bool:
        return self is not PixelFormat.RGB8

    @property
    def bit_depth(self) -> int:
        return {"rgb8": 8, "raw10": 10, "raw12": 12, "raw16": 16}[self.value]


@dataclass(frozen=True, slots=True)
class Mode:
    """A sensor mode: output size, pixel format and the fastest frame rate it allows."""

    width: int
    height: int
    format: PixelFormat = PixelFormat.RGB8
    max_fps: float = 30.0

    @property
    def size(self) -> tuple[int, int]:
        return (self.width, self.height)


@dataclass(frozen=True, slots=True)
class Capabilities:
    """What a camera can do. Ranges are inclusive; exposure in seconds, gain as a factor."""

    exposure_range: tuple[float, float]
    gain_range: tuple[float, float]
    modes: tuple[Mode, ...]
    # True when every frame reports the exposure the sensor actually used.
    has_frame_metadata: bool
    # Frames between a control request and the first frame that shows it (worst case).
    control_latency_frames: int
    model: str = ""
    serial: str = ""
    # The exposure grid (s): the device sets whole multiples of it (V4L2/UVC 100 us units,
    # libcamera microseconds); 0 = any value in the range. Request exposures on it
    # (:func:`snap_exposure`) or they land rounded and no frame shows the value asked for.
    exposure_step_s: float = 0.0


def snap_exposure(caps: Capabilities, exposure_s: float, *, down: bool = False) -> float:
    """``exposure_s`` on the camera's grid (nearest multiple of ``exposure_step_s``, or the
    next one down with ``down=True``), clamped to the exposure range (itself on the grid)."""
    lo, hi = caps.exposure_range
    t = min(max(float(exposure_s), lo), hi)
    step = float(caps.exposure_step_s)
    if step <= 0:
        return t
    k = math.floor(t / step + 1e-9) if down else round(t / step)
    kmin, kmax = math.ceil(lo / step - 1e-9), math.floor(hi / step + 1e-9)
    return max(kmin, min(kmax, k)) * step


@dataclass(frozen=True, slots=True)
class Controls:
    """Control values to apply; ``None`` leaves a control unchanged. Exposure is always manual."""

    exposure_s: float | None = None
    gain: float | None = None


@dataclass(frozen=True, slots=True)
class FrameMetadata:
    exposure_s: float  # exposure the sensor used (or the settled request, see module docs)
    gain: float
    timestamp_s: float  # start of the exposure, CLOCK_MONOTONIC seconds (module docstring)
    sequence: int  # increases by one per sensor frame; gaps mean dropped frames
    exposure_verified: bool = True


def exposure_middle(meta: FrameMetadata) -> float:
    """CLOCK_MONOTONIC seconds of the middle of the frame's exposure: when, on average, the light
    it shows reached the sensor."""
    return float(meta.timestamp_s) + 0.5 * float(meta.exposure_s)


_OFFSET = [0.0, -math.inf]  # the clocks' offset held, when it was last read (CLOCK_MONOTONIC)


def clock_offset() -> float:
    """``time.time() - time.monotonic()``, held steady: read again at most once a second and
    changed only when it moved by more than 1 ms (an NTP step, or a slew that added up), so the
    same stamp maps to the same wall-clock time all through a run (reading the two clocks costs
    a jitter of ~1 us between them; a replay gives the recorded ``captured`` bit for bit)."""
    now = time.monotonic()
    if now - _OFFSET[1] >= 1.0:
        offset = time.time() - time.monotonic()
        if abs(offset - _OFFSET[0]) > 1e-3:
            _OFFSET[0] = offset
        _OFFSET[1] = now
    return _OFFSET[0]


def wall_clock(monotonic_s: float) -> float:
    """A CLOCK_MONOTONIC time as wall-clock (Unix) seconds, through the two clocks' offset
    (:func:`clock_offset`)."""
    return clock_offset() + float(monotonic_s)


def captured_at(frame: Frame) -> float:
    """Wall-clock seconds of the middle of ``frame``'s exposure: through the clocks' offset now,
    or the one its ``extra["wall_minus_monotonic_s"]`` carries (a replayed frame: stamped on the
    recorded unit's clock, :mod:`lightprobe.drivers.replay`)."""
    offset = frame.extra.get("wall_minus_monotonic_s")
    middle = exposure_middle(frame.meta)
    return middle + float(offset) if isinstance(offset, (int, float)) else wall_clock(middle)  # type: ignore[arg-type]


@dataclass(frozen=True, slots=True)
class Frame:
    """One image: ``data`` is (H, W, 3) uint8 for RGB8, uint16 for RAW formats."""

    data: np.ndarray
    meta: FrameMetadata
    format: PixelFormat
    black_level: float = 0.0  # in pixel units, RAW only
    white_level: float = 255.0  # largest value the sensor can report (saturation)
    extra: dict[str, object] = field(default_factory=dict)


# ---- The protocol -------------------------------------------------------------------------------
class Camera(abc.ABC):
    """An exposure-controllable camera.

    Lifecycle: ``open()`` (or ``async with``), ``set_mode()``, then ``apply()`` and ``capture()``
    in any order, ``close()``. ``capture()`` returns the next frame the sensor delivers, in order;
    after ``apply()`` the first frames may still carry the old exposure: check ``frame.meta``.
    Blocking work (ioctls, USB transfers) must not run on the event loop.
    """

    name: str = "camera"
    # the driver this camera runs through ("sim", "v4l2", "libcamera", "uvc", "replay"): what
    # /status and mDNS say beside the device's model
    driver: str = "camera"

    @abc.abstractmethod
    async def open(self) -> None:
        """Open the device. Raises CameraUnavailable / CameraBusy."""

    @abc.abstractmethod
    async def close(self) -> None:
        """Release the device. Safe to call twice and after a disconnect."""

    @property
    @abc.abstractmethod
    def capabilities(self) -> Capabilities:
        """Valid after ``open()``."""

    @property
    @abc.abstractmethod
    def mode(self) -> Mode:
        """The current mode."""

    @abc.abstractmethod
    async def set_mode(self, mode: Mode) -> None:
        """Switch sensor mode; ``mode`` must be one of ``capabilities.modes``."""

    @abc.abstractmethod
    async def apply(self, controls: Controls) -> None:
        """Request control values. Raises ControlOutOfRange before touching the device."""

    @abc.abstractmethod
    async def capture(self, timeout: float = 1.0) -> Frame:  # noqa: ASYNC109 - part of the protocol
        """The next frame. Raises CaptureTimeout, CameraDisconnected."""

    # -- optional capabilities (defaults: the camera has none) --
    async def drain(self) -> int:
        """Drop the frames that are complete and queued behind the newest complete one, so
        the next :meth:`capture` returns the newest (a consumer that fell behind catches up
        instead of reading ever older frames); returns how many were dropped (sequence gaps
        show them too). By default the camera cannot (0): its queue is read in order."""
        return 0

    def factory_calibration(self) -> Calibration | None:
        """A calibration the camera itself carries (a module's EEPROM; the simulator's ground
        truth), used only when the state directory has none. None by default."""
        return None

    def present_board(self, board: BoardTarget | None) -> bool:
        """Put a calibration board in front of the lens (a bench rig with an arm; the simulator's
        technician) for a live calibration session, or take it away (None). Returns whether the
        camera did so; by default it cannot (a technician holds the board)."""
        return False

    # -- helpers shared by backends --
    def _opened(self, value: _T | None) -> _T:
        """``value`` (a property only an open camera has), or CameraUnavailable naming the camera."""
        if value is None:
            raise CameraUnavailable(f"{self.name} is not open", device=self.name)
        return value

    def check_controls(self, controls: Controls) -> None:
        """Raise ControlOutOfRange for values outside the capabilities."""
        caps = self.capabilities
        if controls.exposure_s is not None:
            lo, hi = caps.exposure_range
            if not (lo <= controls.exposure_s <= hi):
                raise ControlOutOfRange("exposure_s", controls.exposure_s, lo, hi, device=self.name)
        if controls.gain is not None:
            lo, hi = caps.gain_range
            if not (lo <= controls.gain <= hi):
                raise ControlOutOfRange("gain", controls.gain, lo, hi, device=self.name)

    async def __aenter__(self) -> Self:
        await self.open()
        return self

    async def __aexit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        await self.close()
