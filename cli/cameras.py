"""``lightprobe cameras``: list attached cameras and their capabilities, or check one.

    lightprobe cameras [--json]              list V4L2, UVC (USB), libcamera cameras and the simulator
    lightprobe cameras --check SPEC [--json] open SPEC, print its capabilities, grab one frame

Exit codes (CONVENTIONS.md): 0 success; 2 for a bad ``--camera``-style spec or a camera that is
missing, busy or went away (one line naming it); 1 for other failures.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import sys
from typing import Any

from lightprobe.core.command import run_command
from lightprobe.core.errors import InputError
from lightprobe.drivers.base import CameraDisconnected, CameraError, CameraUnavailable

__all__ = ["main"]


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="lightprobe cameras", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)  # fmt: skip
    p.add_argument("--json", action="store_true", help="print JSON instead of text")
    p.add_argument("--check", metavar="SPEC", help="open this camera (sim|v4l2:/dev/videoN|libcamera|uvc[:VID:PID]|auto), "
                   "print its capabilities and grab one frame")  # fmt: skip
    p.add_argument("--timeout", type=float, default=3.0, help="seconds to wait for the frame (default 3)")
    return p


def _list(as_json: bool) -> int:
    from lightprobe.drivers.discovery import camera_plugins, list_cameras

    cams = list_cameras()
    plugins = set(camera_plugins())
    hardware = [c for c in cams if c.kind not in plugins]
    if as_json:
        print(json.dumps({"hardware_found": bool(hardware), "cameras": [c.to_json() for c in cams]}, indent=2))
        return 0
    if not hardware:
        print("no camera hardware found (no V4L2 capture nodes, no UVC devices on USB, no libcamera cameras)")
    for c in cams:
        print(f"{c.spec:<48} {c.status:<12} {c.name}")
        for k, v in c.capabilities.items():
            print(f"    {k}: {v}")
    return 0


async def _check(spec: str, wait_s: float) -> dict[str, Any]:
    from lightprobe.drivers.discovery import open_camera

    cam = open_camera(spec)
    await cam.open()
    try:
        caps = cam.capabilities
        frame = await cam.capture(wait_s)
        return {
            "spec": spec, "name": cam.name, "model": caps.model,
            "exposure_range_s": list(caps.exposure_range), "gain_range": list(caps.gain_range),
            "modes": [f"{m.width}x{m.height} {m.format.value} {m.max_fps:g}fps" for m in caps.modes],
            "frame_metadata": caps.has_frame_metadata, "control_latency_frames": caps.control_latency_frames,
            "frame": {"shape": list(frame.data.shape), "dtype": str(frame.data.dtype),
                      "exposure_s": frame.meta.exposure_s, "sequence": frame.meta.sequence},
        }  # fmt: skip
    finally:
        await cam.close()


def _run(argv: list[str]) -> int:
    ns = _parser().parse_args(argv)
    if ns.check is None:
        return _list(ns.json)
    try:
        report = asyncio.run(_check(ns.check, ns.timeout))
    except (CameraUnavailable, CameraDisconnected) as e:  # missing, busy (a subclass), vanished
        raise InputError(f"--camera {ns.check}: {e}", param="--camera") from e
    except CameraError as e:
        print(f"lightprobe: error: {ns.check}: {e}", file=sys.stderr)
        return 1
    if ns.json:
        print(json.dumps(report, indent=2))
    else:
        for k, v in report.items():
            print(f"{k}: {v}")
    return 0


def main(argv: list[str]) -> int:
    return run_command(_run, argv)
