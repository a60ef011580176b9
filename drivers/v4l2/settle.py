"""When has an exposure change landed? The settling rule for cameras without per-frame metadata.

V4L2 (and UVC controls over USB) never say which exposure a frame was taken with. A change lands
a few frames after the request (sensor pipeline + queued buffers: about 2 frames plus the buffer
count; up to 5 frames over UVC). :class:`SettleTracker` decides per frame whether the latest
request is in effect, with two checks:

1. frame count: at least ``latency_frames`` sensor frames (by sequence number, so dropped frames
   count) after the request;
2. brightness step: the frame's mean level moved by at least ``accept_fraction`` of the expected
   step ``gamma * log(ratio)`` from the baseline (the last frame before the request; ``gamma`` is
   the response exponent, about 1/2.2 for processed RGB8 and 1 for raw), and less than
   ``stable_fraction`` of it since the previous frame, i.e. two consecutive frames sit at the new
   level (a rolling shutter shows a half-changed frame first). The check is skipped when it cannot tell anything: a ratio near 1, or a
   baseline that is black or clipped (``level`` outside ``valid_range``).

If the step never shows (a scene change, a camera that ignores the control) the request is taken
as settled after ``timeout_frames`` and the frame says so (``reason="timeout"``); callers log it.
Pure bookkeeping, no I/O; levels are means of a frame normalised to [0, 1].
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = ["SettleDecision", "SettleTracker", "frame_level"]


def frame_level(rgb: np.ndarray, white: float) -> float:
    """Mean level of a frame in [0, 1] over a coarse subsample (float64 accumulator)."""
    if rgb.size == 0 or white <= 0:
        return 0.0
    step = max(1, min(rgb.shape[0], rgb.shape[1]) // 64)
    sub = rgb[::step, ::step].astype(np.float64)
    level = float(np.nanmean(sub)) / white if np.isfinite(sub).any() else 0.0
    return min(max(level, 0.0), 1.0)


@dataclass(frozen=True)
class SettleDecision:
    settled: bool
    exposure_s: float  # the exposure this frame is reported with
    gain: float
    reason: str  # "steady", "step", "no-step-needed", "unobservable", "timeout", "latency"


class SettleTracker:
    """Per-camera settling state. Call :meth:`request` on apply, :meth:`observe` per frame."""

    def __init__(self, latency_frames: int, *, exposure_s: float, gain: float = 1.0,
                 gamma: float = 1.0, accept_fraction: float = 0.5, stable_fraction: float = 0.25,
                 valid_range: tuple[float, float] = (0.02, 0.9), timeout_frames: int | None = None) -> None:  # fmt: skip
        self.latency = max(0, int(latency_frames))
        self.gamma = gamma
        self.accept, self.stable, self.valid = accept_fraction, stable_fraction, valid_range
        self.timeout = timeout_frames if timeout_frames is not None else 3 * self.latency + 3
        self.exposure_s, self.gain = exposure_s, gain  # settled values
        self._target: tuple[float, float] | None = None
        self._req_seq = 0
        self._baseline: float | None = None
        self._prev: float | None = None
        self._last_seq: int | None = None

    @property
    def pending(self) -> bool:
        return self._target is not None

    def request(self, exposure_s: float, gain: float) -> None:
        """A new exposure/gain was sent to the device after the last observed frame."""
        if self._target is None and (exposure_s, gain) == (self.exposure_s, self.gain):
            return
        self._target = (exposure_s, gain)
        self._req_seq = (self._last_seq if self._last_seq is not None else -1) + 1
        self._baseline = self._prev

    def reset(self, exposure_s: float, gain: float) -> None:
        """Forget history (after a reopen): the next frames are measured from scratch."""
        self.exposure_s, self.gain, self._target = exposure_s, gain, None
        self._baseline = self._prev = self._last_seq = None

    def observe(self, sequence: int, level: float) -> SettleDecision:
        """Decide for the frame with this sequence number and mean level."""
        prev, self._prev, self._last_seq = self._prev, level, sequence
        if self._target is None:
            return SettleDecision(True, self.exposure_s, self.gain, "steady")
        frames = sequence - self._req_seq + 1  # sensor frames since the request, drops included
        ok, reason = False, "latency"
        if frames >= self.latency:
            ok, reason = self._step_ok(level, prev)
            if not ok and frames >= self.timeout:
                ok, reason = True, "timeout"
        if not ok:
            return SettleDecision(False, self.exposure_s, self.gain, reason)
        self.exposure_s, self.gain = self._target
        self._target = None
        return SettleDecision(True, self.exposure_s, self.gain, reason)

    def _step_ok(self, level: float, prev: float | None) -> tuple[bool, str]:
        assert self._target is not None
        exp, gain = self._target
        ratio = (exp * gain) / max(self.exposure_s * self.gain, 1e-12)
        expected = self.gamma * math.log(ratio) if ratio > 0 else 0.0
        if abs(expected) < self.gamma * math.log(1.05):
            return True, "no-step-needed"
        base = self._baseline
        lo, hi = self.valid
        if base is None or not lo <= base <= hi:
            return True, "unobservable"
        # Expected step: log(level / baseline) ~ log(ratio), until the frame clips or goes black.
        if (expected > 0 and level >= hi) or (expected < 0 and level <= lo):
            moved = 1.0
        else:
            moved = math.log(max(level, 1e-6) / base) / expected
        still = prev is None or abs(math.log(max(level, 1e-6) / max(prev, 1e-6))) <= self.stable * abs(expected)
        return (moved >= self.accept and still), "step"
