"""HDR fusion of exposure bursts (:mod:`lightprobe.device.hdr.fusion`) and ``lightprobe fuse`` (:mod:`lightprobe.cli.fuse`).

Importing this package does nothing but import numpy/numba code (no device access, no threads).
"""

from __future__ import annotations

from .fusion import (
    FusionResult,
    FusionSettings,
    NoiseModel,
    build_luts,
    fuse,
    fuse_frames,
    fuse_raw,
    fuse_tables,
)

__all__ = [
    "FusionResult",
    "FusionSettings",
    "NoiseModel",
    "build_luts",
    "fuse",
    "fuse_frames",
    "fuse_raw",
    "fuse_tables",
]
