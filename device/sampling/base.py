"""Common types of the samplers: the protocol and the map every sampler integrates.

The light set type itself is :class:`lightprobe.core.lightset.LightSet` (the base layer).

Energy convention: a light's ``rgb`` is the integral of radiance x solid angle over the region it
stands for (unit x sr); over a light set ``sum(rgb)`` equals the integral of the map over the
sphere (to 1e-6 relative, accumulated in float64). Lights are stored as arrays (structure of
arrays) so samplers and hosts stay vectorised.
"""

from __future__ import annotations

from typing import Protocol

import numpy as np

from lightprobe.core.lightset import LightSet

__all__ = ["Sampler", "sanitize_radiance"]


class Sampler(Protocol):
    """A light sampler. Stateful samplers (temporal filters, incremental trees) keep their state
    between calls of ``sample`` on successive frames of one stream; ``reset()`` forgets it.

    ``equirect`` is a float32 (H, 2H, 3) radiance map in the probe frame (CONVENTIONS.md).
    """

    name: str

    def sample(self, equirect: np.ndarray, count: int) -> LightSet: ...

    def reset(self) -> None: ...


def sanitize_radiance(equirect: np.ndarray) -> tuple[np.ndarray, dict[str, int]]:
    """The map every sampler actually integrates: float32 (H, W, 3), NaN/inf and negatives -> 0.

    A sensor can hand over NaN (a failed merge) and lossy EXR (DWAB) carries tiny negative values;
    radiance is non-negative, so both are set to 0 and counted. Energy conservation is stated
    against this cleaned map. Returns ``(clean, {"nonfinite": n, "negative": m})`` (counts of
    values, not pixels). The input is never modified.
    """
    a = np.asarray(equirect)
    if a.ndim != 3 or a.shape[2] != 3:
        raise ValueError(f"expected an (H, W, 3) radiance map, got shape {a.shape}")
    a = np.array(a, dtype=np.float32, copy=True, order="C")
    finite = np.isfinite(a)
    n_bad = int(a.size - np.count_nonzero(finite))
    if n_bad:
        a[~finite] = 0.0
    neg = a < 0
    n_neg = int(np.count_nonzero(neg))
    if n_neg:
        a[neg] = 0.0
    return a, {"nonfinite": n_bad, "negative": n_neg}
