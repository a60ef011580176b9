"""Spherical-Gaussian lighting (Michiels, Put, Bekaert 2015): the wire type and its closed forms.

A lobe is ``G(v) = amplitude exp(sharpness (axis . v - 1))`` (radiance, per RGB channel; paper
eq. 3 with mu = amplitude, lambda = sharpness, p = axis), in the probe frame. The set of lobes
*is* the lighting: ``L(v) = sum_k G_k(v)``. ``kind`` is ``"peak"`` (fitted to a bright region)
or ``"residual"`` (a level of the multiscale residual transform).

JSON (``GET /api/v1/sg``, version 1)::

    {"version": 1, "kind": "sg", "probe", "frame", "timestamp", "unit", "stale",
     "lobes": [{"axis": [x, y, z], "sharpness": lambda, "amplitude": [r, g, b], "kind": "peak"}],
     "levels": [{"nside": N, "lobes": n, "sharpness": lambda, "residual": r}], "energy": [r, g, b]}

Closed forms used by fits and hosts: the integral of a lobe over the sphere
``2 pi mu (1 - exp(-2 lambda)) / lambda``; the product of two lobes is a lobe; the triple-product
integral of paper eq. 4, ``4 pi mu1 mu2 mu3 exp(-(l1 + l2 + l3)) sinh(|r|) / |r|`` with
``r = l1 p1 + l2 p2 + l3 p3`` (written ``2 pi ... (exp(|r| - sum l) - exp(-|r| - sum l)) / |r|``
so that large sharpness does not overflow).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .errors import InputError

__all__ = ["SG_VERSION", "SGLighting", "lobe_integral", "sharpness_from_resultant", "triple_integral"]

SG_VERSION = 1
_SMALL_RESULTANT = 1e-3  # below it, sharpness_from_resultant's start is the answer


def lobe_integral(sharpness: np.ndarray) -> np.ndarray:
    """``integral exp(lambda (p . v - 1)) dv = 2 pi (1 - exp(-2 lambda)) / lambda`` (-> 4 pi as
    lambda -> 0)."""
    lam = np.asarray(sharpness, np.float64)
    small = lam < 1e-6
    safe = np.where(small, 1.0, lam)
    return np.where(small, 4 * np.pi, 2 * np.pi * (-np.expm1(-2 * safe)) / safe)


def sharpness_from_resultant(r: np.ndarray) -> np.ndarray:
    """The sharpness ``lambda`` whose lobe has mean resultant length ``r`` (``coth l - 1/l = r``,
    the von Mises-Fisher relation; Banerjee et al. 2005's start, then Newton steps). Below
    ``r = 1e-3`` the start itself (``3 r`` to within ``r^2`` relative) is the answer: there the
    Newton step's derivative ``1/l^2 - (coth^2 l - 1)`` (about 1/3) cancels to nothing."""
    if np.ndim(r) == 0:  # one lobe (a peak's): the same steps on a float, 20 x faster
        x = min(max(float(r), 1e-9), 1 - 1e-12)
        lam = x * (3 - x * x) / (1 - x * x)
        if x >= _SMALL_RESULTANT:
            for _ in range(20):
                t = 1 / math.tanh(lam)
                lam = max(lam - (t - 1 / lam - x) / (1 / (lam * lam) - (t * t - 1)), 1e-9)
        return np.float64(lam)  # type: ignore[return-value]
    r = np.clip(np.asarray(r, np.float64), 1e-9, 1 - 1e-12)
    start = r * (3 - r * r) / (1 - r * r)
    small = r < _SMALL_RESULTANT
    la = np.where(small, 1.0, start)
    for _ in range(20):
        c = 1 / np.tanh(la)
        f = c - 1 / la - np.where(small, c - 1 / la, r)
        df = 1 / (la * la) - (c * c - 1)
        la = np.maximum(la - f / df, 1e-9)
    return np.where(small, start, la)


def triple_integral(p1: np.ndarray, l1: np.ndarray, m1: np.ndarray, p2: np.ndarray, l2: np.ndarray,
                    m2: np.ndarray, p3: np.ndarray, l3: np.ndarray, m3: np.ndarray) -> np.ndarray:
    """Paper eq. 4 (broadcasting): ``integral G1 G2 G3 dv`` for axes ``p`` (..., 3), sharpness
    ``l`` (...) and amplitudes ``m`` (..., channels)."""
    r = (np.asarray(l1)[..., None] * p1 + np.asarray(l2)[..., None] * p2 + np.asarray(l3)[..., None] * p3)
    rn = np.linalg.norm(r, axis=-1)
    s = np.asarray(l1) + np.asarray(l2) + np.asarray(l3)
    safe = np.where(rn > 1e-9, rn, 1.0)
    k = np.where(rn > 1e-9, 2 * np.pi * (np.exp(rn - s) - np.exp(-rn - s)) / safe, 4 * np.pi * np.exp(-s))
    return k[..., None] * np.asarray(m1) * np.asarray(m2) * np.asarray(m3)


@dataclass
class SGLighting:
    """Lobes as arrays: ``axes`` (N, 3) unit, ``sharpness`` (N,), ``amplitude`` (N, 3), ``kinds``
    (N,) of ``"peak"`` / ``"residual"``; ``levels`` describes the residual transform's levels."""

    axes: np.ndarray
    sharpness: np.ndarray
    amplitude: np.ndarray
    kinds: list[str]
    levels: list[dict[str, Any]] = field(default_factory=list)
    probe: str = ""
    frame: int = 0
    timestamp: float = field(default_factory=time.time)
    unit: str = "relative"
    captured: float | None = None  # wall-clock middle of the newest frame's exposure (LightSet)

    def __post_init__(self) -> None:
        self.axes = np.asarray(self.axes, np.float64).reshape(-1, 3)
        self.sharpness = np.asarray(self.sharpness, np.float64).reshape(-1)
        self.amplitude = np.asarray(self.amplitude, np.float64).reshape(-1, 3)
        n = len(self.axes)
        if len(self.sharpness) != n or len(self.amplitude) != n or len(self.kinds) != n:
            raise ValueError("axes, sharpness, amplitude and kinds must have the same length")

    def __len__(self) -> int:
        return len(self.axes)

    def energy(self) -> np.ndarray:
        """Per-lobe integral of radiance over the sphere (N, 3), unit x sr."""
        return self.amplitude * lobe_integral(self.sharpness)[:, None]

    def radiance(self, v: np.ndarray) -> np.ndarray:
        """``sum_k G_k(v)`` at unit directions (..., 3) -> (..., 3)."""
        v = np.asarray(v, np.float64)
        flat = v.reshape(-1, 3)
        out = np.zeros((len(flat), 3))
        for s in range(0, len(flat), 4096):
            c = flat[s:s + 4096] @ self.axes.T
            out[s:s + 4096] = np.exp(self.sharpness[None, :] * (c - 1.0)) @ self.amplitude
        return out.reshape(*v.shape[:-1], 3)

    def to_json(self) -> dict[str, Any]:
        return {"version": SG_VERSION, "kind": "sg", "probe": self.probe, "frame": int(self.frame),
                "timestamp": float(self.timestamp),
                **({} if self.captured is None else {"captured": float(self.captured)}),
                "unit": self.unit,
                "lobes": [{"axis": [round(float(x), 7) for x in a], "sharpness": float(s),
                           "amplitude": [float(x) for x in m], "kind": k}
                          for a, s, m, k in zip(self.axes, self.sharpness, self.amplitude, self.kinds, strict=True)],
                "levels": self.levels, "energy": [float(x) for x in self.energy().sum(axis=0)]}

    @classmethod
    def from_json(cls, d: Any) -> SGLighting:
        if not isinstance(d, dict) or d.get("version") != SG_VERSION or not isinstance(d.get("lobes"), list):
            raise InputError("not an SG body (version 1 with a list of lobes)", param="sg")
        try:
            lobes = d["lobes"]
            sg = cls(np.array([lb["axis"] for lb in lobes], np.float64).reshape(-1, 3),
                     np.array([lb["sharpness"] for lb in lobes], np.float64),
                     np.array([lb["amplitude"] for lb in lobes], np.float64).reshape(-1, 3),
                     [str(lb.get("kind", "residual")) for lb in lobes], list(d.get("levels", [])),
                     str(d.get("probe", "")), int(d.get("frame", 0)), float(d.get("timestamp", 0.0)),
                     str(d.get("unit", "relative")),
                     None if d.get("captured") is None else float(d["captured"]))
        except (KeyError, TypeError, ValueError) as e:
            raise InputError(f"not an SG body: {e}", param="sg") from None
        if not (np.isfinite(sg.axes).all() and np.isfinite(sg.amplitude).all() and (sg.sharpness >= 0).all()):
            raise InputError("not an SG body: non-finite axis or amplitude, or negative sharpness", param="sg")
        return sg


def level_sharpness(nside: int) -> float:
    """Residual level ``nside``: the lobe falls to half at the HEALPix pixel spacing
    ``theta = sqrt(4 pi / (12 nside^2))``: ``lambda = ln 2 / (1 - cos theta)``."""
    theta = math.sqrt(4 * math.pi / (12 * nside * nside))
    return math.log(2.0) / (1.0 - math.cos(theta))
