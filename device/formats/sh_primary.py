"""The probe's lighting as hosts consume it, per frame: SH (all light and ambient) plus the primary
light, in any host's convention (``GET /api/v1/sh``, the stream's ``sh`` subscription).

JSON (version 1)::

    {"version": 1, "probe": ..., "frame": ..., "timestamp": ..., "captured": ..., "unit": "relative",
     "convention": "threejs", "order": 2,
     "coefficients": [[r, g, b] x 9],          # all light
     "ambient_coefficients": [[r, g, b] x 9],  # without the primary light
     "primary_light": {"direction": [x, y, z], "rgb": [r, g, b], "solid_angle": sr} | null}

``direction`` points towards the light, in the convention's world axes (Unity: z flipped);
``rgb`` is the irradiance the light gives at normal incidence (unit x sr, like a light set's).
For ``webxr`` the body also carries ``sphericalHarmonicsCoefficients`` (27 floats),
``primaryLightDirection`` and ``primaryLightIntensity`` exactly as ``XRLightEstimate`` names
them. The pose travels beside the lights (CONVENTIONS.md): coefficients are in the probe frame.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from lightprobe.core.sh import SHLighting, SHProjector, direction_to_convention, to_convention
from lightprobe.core.sphere import lit_rows
from lightprobe.device.formats.primary import PrimaryLight, extract_primary

__all__ = ["SH_VERSION", "Environment", "EnvironmentEstimator", "sh_from_map"]

SH_VERSION = 1


def _rows(m: list[list[float]] | np.ndarray) -> list[list[float]]:
    return [[float(v) for v in row] for row in np.asarray(m, np.float64)]


@dataclass
class Environment:
    """One frame's SH and primary light, canonical convention, probe frame."""

    coefficients: np.ndarray  # (9, 3)
    ambient: np.ndarray  # (9, 3)
    primary: PrimaryLight | None
    frame: int = 0
    timestamp: float = field(default_factory=time.time)
    unit: str = "relative"
    probe: str = ""
    pose: dict[str, Any] | None = None
    captured: float | None = None  # wall-clock middle of the newest frame's exposure (LightSet)

    def to_json(self, convention: str = "canonical") -> dict[str, Any]:
        coeffs = to_convention(self.coefficients, convention)  # validates the name
        amb = to_convention(self.ambient, convention)
        prim = None
        if self.primary is not None:
            prim = self.primary.to_json()
            prim["direction"] = [round(float(x), 7)
                                 for x in direction_to_convention(self.primary.direction, convention)]
        body: dict[str, Any] = {
            "version": SH_VERSION, "kind": "sh", "probe": self.probe, "frame": int(self.frame),
            "timestamp": float(self.timestamp),
            **({} if self.captured is None else {"captured": float(self.captured)}),
            "unit": self.unit, "convention": convention, "order": 2,
            "coefficients": _rows(coeffs), "ambient_coefficients": _rows(amb), "primary_light": prim}
        if self.pose is not None:
            body["pose"] = self.pose
        if convention == "webxr":
            # what XRLightEstimate carries: the ambient SH goes with a primary light, all light without one
            body["sphericalHarmonicsCoefficients"] = [float(v) for v in (amb if prim else coeffs).reshape(-1)]
            body["primaryLightDirection"] = prim["direction"] if prim else [0.0, 1.0, 0.0]
            body["primaryLightIntensity"] = prim["rgb"] if prim else [0.0, 0.0, 0.0]
        return body


class EnvironmentEstimator:
    """Per-frame SH + primary light of the probe's maps, incremental (see :class:`SHProjector`).

    A map whose lower half is black (the probe's upper-hemisphere maps) is read over its upper
    rows only. ``estimate`` is blocking (run it in a worker thread on the service).
    """

    def __init__(self) -> None:
        self._proj: SHProjector | None = None
        self.last: Environment | None = None

    def estimate(self, equirect: np.ndarray, **meta: Any) -> Environment:
        a = np.asarray(equirect)
        h = a.shape[0]
        rows = lit_rows(a)
        if self._proj is None or self._proj.height != h or self._proj.rows != rows:
            self._proj = SHProjector(h, rows)
        coeffs = self._proj.update(a).copy()
        if self._proj.last_changed == 0 and self.last is not None:
            primary = self.last.primary  # nothing moved: the same light
        else:
            primary = extract_primary(a, rows=rows)
        ambient = coeffs - primary.sh if primary is not None else coeffs.copy()
        self.last = Environment(coeffs, ambient, primary, **meta)
        return self.last

    @property
    def nbytes(self) -> int:
        return self._proj.nbytes if self._proj is not None else 0


def sh_from_map(equirect: np.ndarray, convention: str = "canonical", **meta: Any) -> SHLighting:
    """The probe's SH + primary light of an equirect map, computed here (offline)."""
    return SHLighting.from_json(EnvironmentEstimator().estimate(equirect, **meta).to_json(convention))
