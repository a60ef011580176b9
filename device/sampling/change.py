"""The change test that lets the live pipeline skip resampling a map that did not change.

A frame's map is resampled unless, since the last sampled frame, its coarse energy (luminance x
solid angle summed in blocks of the upper hemisphere) changed less than ``threshold`` (relative
L1, well above noise), and so did the pixels the rolling estimate found changed beyond noise (a
small lamp moving within a coarse block changes no block's energy, but its pixels), the last
sampled map held no energy by guess (a moving lamp a long exposure saw only saturated), and that
was less than ``max_skip_s`` ago (monotonic clock). A change beyond it is sampled in the frame
that shows it, never later (:mod:`lightprobe.device.pipeline`).
"""

from __future__ import annotations

import time

import numpy as np

from lightprobe.core.sphere import luminance

__all__ = ["ChangeTest"]


class ChangeTest:
    """What the last sampled frame was, and what changed since."""

    def __init__(self) -> None:
        self.last: tuple[np.ndarray, float] | None = None  # (coarse energy, monotonic time) when last sampled
        self.lum: np.ndarray | None = None  # luminance x solid angle per pixel when last sampled
        self.changed_since: np.ndarray | None = None  # pixels the merge found changed since then
        self.guessed = False  # the last sampled map held energy no exposure measured (a moving lamp)

    def reset(self) -> None:
        """Forget the last sampled frame: the next one is sampled whatever it shows."""
        self.last = None

    def observe(self, changed: np.ndarray, held: np.ndarray) -> None:
        """Take in a frame's pixels that the rolling merge found changed, or held by guess."""
        if self.changed_since is None or self.changed_since.shape != changed.shape:
            self.changed_since = np.zeros_like(changed)
        self.changed_since |= changed
        self.changed_since |= held

    def unchanged(self, coarse: np.ndarray, fused: np.ndarray, solid_angle: np.ndarray, *,
                  threshold: float, max_skip_s: float) -> bool:
        """Whether the frame (its ``coarse`` energy, its ``fused`` upper-hemisphere pixels) may
        republish the last light set (see the module docstring)."""
        if self.last is None or self.guessed:
            return False  # nothing sampled yet; or the last set placed a moving lamp by guess
        ref, when = self.last
        if time.monotonic() - when > max_skip_s:
            return False
        denom = float(np.abs(ref).sum())
        if denom <= 0:
            return float(np.abs(coarse).sum()) <= 0
        if float(np.abs(coarse - ref).sum()) / denom >= threshold:
            return False
        moved = np.flatnonzero(self.changed_since) if self.changed_since is not None else np.zeros(0, np.intp)
        if len(moved) and self.lum is not None:
            now = luminance(fused[moved].astype(np.float64)) * solid_angle[moved]
            if float(np.abs(now - self.lum[moved]).sum()) / denom >= threshold:
                return False
        return True

    def sampled(self, coarse: np.ndarray, lum_w: np.ndarray, held: np.ndarray) -> None:
        """The frame was sampled: it is the reference now."""
        self.last = (coarse, time.monotonic())
        if self.lum is None or self.lum.shape != lum_w.shape:
            self.lum = np.empty_like(lum_w)
        np.copyto(self.lum, lum_w)
        if self.changed_since is not None:
            self.changed_since[:] = False
        self.guessed = bool(held.any())
