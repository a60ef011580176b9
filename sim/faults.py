"""Fault injection for the simulated camera: real code, switchable per test.

``camera.faults.inject(kind, ...)`` arms a fault; the camera consults the plan on every
``capture()``. Kinds (:class:`FaultKind`):

- ``capture_error``: ``capture()`` raises :class:`lightprobe.drivers.base.CameraError` (the frame is lost,
  its sequence number skipped), ``count`` times.
- ``timeout``: ``capture()`` waits its ``timeout`` and raises :class:`CaptureTimeout`, ``count``
  times (the frame is lost).
- ``disconnect``: ``capture()`` raises :class:`CameraDisconnected`; the camera is closed and
  "unplugged" for ``duration_s`` seconds of wall-clock time (``time.monotonic``): ``open()``
  raises :class:`CameraUnavailable` until the outage is over. After replugging, controls are
  back at their defaults (as UVC cameras do).
- ``drop``: the next capture skips ``count`` sensor frames (a sequence and timestamp gap).
- ``hot_pixel``: pixels ``pixels=((x, y), ...)`` stuck at full scale (all channels).
- ``lens_cap``: no light reaches the sensor (frames are black level plus read noise).

``after`` delays a fault by that many ``capture()`` calls. ``count=None`` keeps a fault (hot
pixel, lens cap, capture error, timeout) active until :meth:`FaultPlan.clear`.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass, field

import numpy as np

__all__ = ["Fault", "FaultKind", "FaultPlan"]


class FaultKind(enum.StrEnum):
    CAPTURE_ERROR = "capture_error"
    TIMEOUT = "timeout"
    DISCONNECT = "disconnect"
    DROP = "drop"
    HOT_PIXEL = "hot_pixel"
    LENS_CAP = "lens_cap"


_RAISING = (FaultKind.CAPTURE_ERROR, FaultKind.TIMEOUT, FaultKind.DISCONNECT)


@dataclass
class Fault:
    """One armed fault; ``remaining`` is None for 'until cleared'."""

    kind: FaultKind
    remaining: int | None = 1
    after: int = 0
    duration_s: float = 0.0
    pixels: tuple[tuple[int, int], ...] = ()


@dataclass
class CaptureFaults:
    """What the plan decided for one ``capture()`` call."""

    raise_kind: FaultKind | None = None
    duration_s: float = 0.0
    drop: int = 0
    lens_cap: bool = False
    hot_pixels: list[tuple[int, int]] = field(default_factory=list)


@dataclass
class FaultPlan:
    """The faults armed on one simulated camera (see the module docstring)."""

    faults: list[Fault] = field(default_factory=list)
    log: list[tuple[int, str]] = field(default_factory=list)  # (capture call index, kind) fired
    _calls: int = 0

    def inject(self, kind: FaultKind | str, *, count: int | None = 1, after: int = 0,
               duration_s: float = 1.0, pixels: tuple[tuple[int, int], ...] = ((0, 0),)) -> Fault:
        """Arm a fault. Raises ValueError naming the kind if it is unknown."""
        try:
            k = FaultKind(kind)
        except ValueError:
            valid = ", ".join(f.value for f in FaultKind)
            raise ValueError(f"unknown fault kind {kind!r} (valid: {valid})") from None
        if count is not None and count < 1:
            raise ValueError(f"fault count must be >= 1 or None, got {count}")
        if k in (FaultKind.DISCONNECT,):
            count = 1
        f = Fault(k, count, int(after), float(duration_s), tuple((int(x), int(y)) for x, y in pixels))
        self.faults.append(f)
        return f

    def clear(self, kind: FaultKind | str | None = None) -> None:
        """Disarm all faults, or all of one kind."""
        self.faults = [f for f in self.faults if kind is not None and f.kind != FaultKind(kind)]

    @property
    def active(self) -> bool:
        return bool(self.faults)

    def next_capture(self) -> CaptureFaults:
        """Decide the faults of the next ``capture()`` call and consume their counts.

        At most one raising fault fires per call (the first armed); drop, hot-pixel and lens-cap
        faults combine with each other.
        """
        idx = self._calls
        self._calls += 1
        out = CaptureFaults()
        keep: list[Fault] = []
        for f in self.faults:
            if f.after > 0:
                f.after -= 1
                keep.append(f)
                continue
            fired = True
            if f.kind in _RAISING:
                if out.raise_kind is None:
                    out.raise_kind, out.duration_s = f.kind, f.duration_s
                else:
                    fired = False
            elif f.kind is FaultKind.DROP:
                out.drop += f.remaining or 1
                f.remaining = 1
            elif f.kind is FaultKind.LENS_CAP:
                out.lens_cap = True
            elif f.kind is FaultKind.HOT_PIXEL:
                out.hot_pixels.extend(f.pixels)
            if fired:
                self.log.append((idx, f.kind.value))
                if f.remaining is not None:
                    f.remaining -= 1
            if f.remaining is None or f.remaining > 0:
                keep.append(f)
        self.faults = keep
        return out

    @staticmethod
    def apply_hot_pixels(data: np.ndarray, pixels: list[tuple[int, int]], white: int) -> None:
        """Set pixels (x, y) to full scale in place (out-of-range pixels are ignored)."""
        h, w = data.shape[:2]
        for x, y in pixels:
            if 0 <= x < w and 0 <= y < h:
                data[y, x, :] = white
