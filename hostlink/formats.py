"""Host-side types of the probe's host formats (``GET /api/v1/sh``, ``cubemap.ktx2``, scene files),
and the same conversions for EXR maps offline.

:class:`SHLighting` is the ``/sh`` body, typed (coefficients as (9, 3) float64 arrays in the
body's convention); :func:`sh_from_map` computes it from an equirect map on the host, exactly as
the probe does (``device.formats``), for offline maps or for a map fetched with
``ProbeClient.hdr_map()``. :class:`CubeMap` is a decoded ``cubemap.ktx2``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from device.core.errors import InputError

__all__ = ["CubeMap", "EnvironmentFiles", "PrimaryLight", "SHLighting", "sh_from_map"]


@dataclass(frozen=True)
class PrimaryLight:
    """Towards the light (unit, the convention's axes); ``rgb`` irradiance at normal incidence."""

    direction: np.ndarray
    rgb: np.ndarray
    solid_angle: float


@dataclass
class SHLighting:
    """``GET /api/v1/sh``: all light and ambient SH (9, 3) plus the primary light."""

    convention: str
    coefficients: np.ndarray
    ambient: np.ndarray
    primary: PrimaryLight | None
    probe: str = ""
    frame: int = 0
    timestamp: float = 0.0
    unit: str = "relative"
    stale: bool = False
    raw: dict[str, Any] = field(default_factory=dict, repr=False)

    @classmethod
    def from_json(cls, d: Any) -> SHLighting:
        if not isinstance(d, dict) or d.get("version") != 1:
            raise InputError("not an SH body: not a version-1 JSON object", param="sh")
        try:
            c = np.asarray(d["coefficients"], np.float64)
            a = np.asarray(d["ambient_coefficients"], np.float64)
            p = d.get("primary_light")
            prim = None
            if p is not None:
                prim = PrimaryLight(np.asarray(p["direction"], np.float64).reshape(3),
                                    np.asarray(p["rgb"], np.float64).reshape(3), float(p["solid_angle"]))
            if c.shape != (9, 3) or a.shape != (9, 3) or not (np.isfinite(c).all() and np.isfinite(a).all()):
                raise InputError(f"not an SH body: coefficients must be 9 x 3 finite numbers, got {c.shape} "
                                 f"and {a.shape}", param="sh")
            return cls(str(d["convention"]), c, a, prim, str(d.get("probe", "")), int(d.get("frame", 0)),
                       float(d.get("timestamp", 0.0)), str(d.get("unit", "relative")), bool(d.get("stale", False)), d)
        except (KeyError, TypeError, ValueError) as e:
            raise InputError(f"not an SH body: {e}", param="sh") from None


@dataclass
class CubeMap:
    """A decoded ``cubemap.ktx2``: ``mips[m]`` (6, n, n, 3) float32 (faces +X..-Z, probe frame),
    ``roughness[m]`` (GGX, perceptual), and the file's key/value data."""

    mips: list[np.ndarray]
    roughness: list[float]
    meta: dict[str, Any]


@dataclass
class EnvironmentFiles:
    """A scene file (``environment.gltf`` / ``environment.usda``) and the files it references,
    ``{relative path: bytes}``; :meth:`save` writes them into a folder, keeping the layout."""

    name: str
    document: bytes
    files: dict[str, bytes]

    def save(self, folder: Any) -> Any:
        from pathlib import Path

        from device.core.fsutil import atomic_write

        root = Path(folder)
        for rel, data in self.files.items():
            (root / rel).parent.mkdir(parents=True, exist_ok=True)
            atomic_write(root / rel, data)
        root.mkdir(parents=True, exist_ok=True)
        atomic_write(root / self.name, self.document)
        return root / self.name


def sh_from_map(equirect: np.ndarray, convention: str = "canonical", **meta: Any) -> SHLighting:
    """The probe's SH + primary light of an equirect map, computed here (offline)."""
    from device.core.environment import EnvironmentEstimator

    return SHLighting.from_json(EnvironmentEstimator().estimate(equirect, **meta).to_json(convention))
