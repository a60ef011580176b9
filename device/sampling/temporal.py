"""Temporal low-pass filters for light sets (Havran et al. 2005): total energy and trajectories.

Both are first-order exponential filters ``y_t = y_{t-1} + alpha (x_t - y_{t-1})`` (``alpha = 1``
disables filtering) with a **reset** when the input jumps: the filter then restarts from the new
value instead of sweeping from the old one, so a switched lamp or a light whose sample moved to
another part of the sky never produces a ghost light crossing the sky.

* :class:`EnergyFilter` smooths the total luminance of the map (against fluorescent flicker, which
  aliases the mains frequency into frame-to-frame brightness changes); reset when the relative
  change exceeds ``jump`` (a lamp switched on or off).
* :class:`TrajectoryFilter` smooths each light's position in the unit square of the Havran map
  (against jitter); light identity is its Halton index (``id``); reset per light when its new
  position is more than ``jump`` away (Euclidean, square units) from its filtered one.

Dtype policy: float64 state. Filters are plain objects; ``reset()`` forgets everything.

References
----------
Havran, Smyk, Krawczyk, Myszkowski, Seidel, "Interactive system for dynamic scene lighting using
captured video environment maps", EGSR 2005, sec. 4 (temporal filtering of energy and of light
positions; parameters there are described only by intent, these are ours).
"""

from __future__ import annotations

import numpy as np

__all__ = ["EnergyFilter", "TrajectoryFilter"]


class EnergyFilter:
    """Exponential filter of a non-negative scalar (total luminance) with jump reset."""

    def __init__(self, alpha: float = 0.3, jump: float = 0.5) -> None:
        if not 0.0 < alpha <= 1.0:
            raise ValueError(f"alpha must be in (0, 1], got {alpha}")
        self.alpha = float(alpha)
        self.jump = float(jump)
        self.value: float | None = None
        self.resets = 0

    def reset(self) -> None:
        self.value = None

    def update(self, x: float) -> float:
        """Feed the frame's total; return the filtered total (the input itself after a reset)."""
        x = float(x)
        prev = self.value
        if prev is None or not np.isfinite(prev) or prev <= 0.0 or x <= 0.0 \
                or abs(x - prev) > self.jump * max(prev, x):
            self.value = x
            if prev is not None:
                self.resets += 1
        else:
            self.value = prev + self.alpha * (x - prev)  # y_t = y_{t-1} + alpha (x_t - y_{t-1})
        return self.value

    def gain(self, x: float) -> float:
        """``filtered / x`` after feeding ``x`` (1 for x <= 0): the scale to apply to the lights."""
        y = self.update(x)
        return y / x if x > 0 else 1.0


class TrajectoryFilter:
    """Exponential filter of 2D positions keyed by light id, with per-light jump reset."""

    def __init__(self, alpha: float = 0.5, jump: float = 0.05) -> None:
        if not 0.0 < alpha <= 1.0:
            raise ValueError(f"alpha must be in (0, 1], got {alpha}")
        self.alpha = float(alpha)
        self.jump = float(jump)
        self._ids = np.zeros(0, np.int64)
        self._pos = np.zeros((0, 2))
        self.resets = 0

    def reset(self) -> None:
        self._ids = np.zeros(0, np.int64)
        self._pos = np.zeros((0, 2))

    def update(self, ids: np.ndarray, pos: np.ndarray) -> np.ndarray:
        """Filtered positions (N, 2) for lights ``ids`` (N,) now at ``pos`` (N, 2).

        Lights not seen before start at their position; lights absent from this frame are
        forgotten (a light that reappears starts fresh).
        """
        ids = np.asarray(ids, np.int64)
        pos = np.asarray(pos, np.float64).reshape(-1, 2)
        out = pos.copy()
        if self.alpha < 1.0 and len(self._ids):
            order = np.argsort(self._ids)
            k = np.searchsorted(self._ids[order], ids)
            k = np.minimum(k, len(order) - 1)
            known = self._ids[order][k] == ids
            prev = self._pos[order][k]
            dist = np.linalg.norm(pos - prev, axis=1)
            smooth = known & (dist <= self.jump)
            self.resets += int(np.count_nonzero(known & ~smooth))
            out[smooth] = prev[smooth] + self.alpha * (pos[smooth] - prev[smooth])
        self._ids = ids.copy()
        self._pos = out.copy()
        return out
