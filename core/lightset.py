"""The light set: N directional lights in the probe frame (CONVENTIONS.md light-set JSON).

Energy convention: a light's ``rgb`` is the integral of radiance x solid angle over the region it
stands for (unit x sr); over a light set ``sum(rgb)`` equals the integral of the map over the
sphere (to 1e-6 relative, accumulated in float64). Lights are stored as arrays (structure of
arrays) so samplers and hosts stay vectorised. This is the wire type the probe publishes and
hosts read: it lives in the base layer both sides share.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .errors import InputError

__all__ = ["LIGHTSET_VERSION", "LightSet"]

LIGHTSET_VERSION = 1


@dataclass
class LightSet:
    """N directional lights in the probe frame.

    ``directions`` (N, 3) unit float64; ``rgb`` (N, 3) float64 (unit x sr); ``solid_angle`` (N,)
    sr of the region each light stands for; ``ids`` (N,) int64 stable across frames where the
    method gives temporal correspondence, else -1. ``extra`` holds method-specific additions
    published as optional fields (e.g. ``"peaks"``, ``"ambient"``). ``stale``: the camera is
    away, these are the last good lights; ``settling``: the probe is starting and its estimate
    is still taking in its first exposures, so the lighting may be off by more than its noise
    (only the first frames after start: the metering sweep and one cycle of the bracket planned
    from it, under a second at 30 fps). Two times, both wall-clock seconds (Unix time):
    ``captured``, when the light these lights show reached the sensor (the middle of the exposure
    of the newest frame the set was made from; None for a set not made from a camera, e.g. from
    a saved map) and ``timestamp``, when the set was made (published); ``timestamp - captured``
    is the probe's own latency, a host's clock minus ``captured`` the lighting's age.
    """

    directions: np.ndarray
    rgb: np.ndarray
    solid_angle: np.ndarray
    ids: np.ndarray | None = None
    method: str = ""
    unit: str = "relative"
    probe: str = ""
    frame: int = 0
    timestamp: float = field(default_factory=time.time)
    captured: float | None = None
    stale: bool = False
    settling: bool = False
    pose: dict[str, Any] = field(
        default_factory=lambda: {"rotation": np.eye(3).tolist(), "position": [0.0, 0.0, 0.0]}
    )
    extra: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.directions = np.asarray(self.directions, np.float64).reshape(-1, 3)
        self.rgb = np.asarray(self.rgb, np.float64).reshape(-1, 3)
        self.solid_angle = np.asarray(self.solid_angle, np.float64).reshape(-1)
        n = len(self.directions)
        if self.rgb.shape[0] != n or self.solid_angle.shape[0] != n:
            raise ValueError("directions, rgb and solid_angle must have the same length")
        if self.ids is None:
            self.ids = np.full(n, -1, np.int64)
        else:
            self.ids = np.asarray(self.ids, np.int64).reshape(-1)

    def __len__(self) -> int:
        return len(self.directions)

    @property
    def total(self) -> np.ndarray:
        """Sum of rgb, float64 (equals the map's integral)."""
        return self.rgb.sum(axis=0)

    def to_json(self) -> dict[str, Any]:
        lights = []
        for i in range(len(self)):
            item: dict[str, Any] = {
                "direction": [round(float(x), 7) for x in self.directions[i]],
                "rgb": [float(x) for x in self.rgb[i]],
                "solid_angle": float(self.solid_angle[i]),
            }
            assert self.ids is not None
            if self.ids[i] >= 0:
                item["id"] = int(self.ids[i])
            lights.append(item)
        out: dict[str, Any] = {
            "version": LIGHTSET_VERSION,
            "probe": self.probe,
            "frame": int(self.frame),
            "timestamp": float(self.timestamp),
            **({} if self.captured is None else {"captured": float(self.captured)}),
            "method": self.method,
            "unit": self.unit,
            "stale": bool(self.stale),
            "settling": bool(self.settling),
            "pose": self.pose,
            "lights": lights,
        }
        out.update(self.extra)
        return out

    def comparable_json(self) -> str:
        """The set as one JSON line without its publication time (``timestamp``): what the same
        frames give again, bit for bit (floats written exactly), so two runs compare byte for byte
        (``run-pipeline --jsonl``, a recording's replay)."""
        import json

        d = self.to_json()
        d.pop("timestamp", None)
        return json.dumps(d, separators=(",", ":"))

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> LightSet:
        if not isinstance(d, dict) or d.get("version") != LIGHTSET_VERSION:
            raise InputError(f"light set version {d.get('version') if isinstance(d, dict) else None!r} "
                             f"is not {LIGHTSET_VERSION}", param="version")
        lights = d.get("lights")
        if not isinstance(lights, list):
            raise InputError("light set has no 'lights' list", param="lights")
        try:
            dirs = np.array([li["direction"] for li in lights], np.float64).reshape(-1, 3)
            rgb = np.array([li["rgb"] for li in lights], np.float64).reshape(-1, 3)
            sa = np.array([li.get("solid_angle", 0.0) for li in lights], np.float64)
            ids = np.array([li.get("id", -1) for li in lights], np.int64)
        except (KeyError, TypeError, ValueError) as e:
            raise InputError(f"malformed light in light set: {e}", param="lights") from e
        known = {"version", "probe", "frame", "timestamp", "captured", "method", "unit", "stale", "settling", "pose",
                 "lights"}
        captured = d.get("captured")
        return cls(dirs, rgb, sa, ids, method=str(d.get("method", "")), unit=str(d.get("unit", "relative")),
                   probe=str(d.get("probe", "")), frame=int(d.get("frame", 0)),
                   timestamp=float(d.get("timestamp", 0.0)),
                   captured=None if captured is None else float(captured), stale=bool(d.get("stale", False)),
                   settling=bool(d.get("settling", False)),
                   pose=d.get("pose") or {"rotation": np.eye(3).tolist(), "position": [0.0, 0.0, 0.0]},
                   extra={k: v for k, v in d.items() if k not in known})
