"""``lightprobe run-pipeline``: run the capture pipeline without the service.

Prints per-frame stats (exposures, stage timings, lights, skipped) and writes the latest HDR
equirect map (EXR) after every frame. Useful on a bench and on a unit without the network, and on
a recording (``--camera replay:FILE``, as fast as it runs unless ``--pace``): ``--jsonl`` writes
every light set (without its publication time), so two runs compare byte for byte.
"""

from __future__ import annotations

import argparse
import asyncio
import sys
from pathlib import Path
from typing import Any

from lightprobe.core.command import run_command

__all__ = ["main"]


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="lightprobe run-pipeline", description=__doc__.splitlines()[0])
    p.add_argument("--camera", default="sim", help="camera spec: sim (default), v4l2:/dev/videoN, libcamera, uvc, auto (hardware only)")
    p.add_argument("--scene", default="flashlight", help="simulated scene: scenario name or equirect file (sim only)")
    p.add_argument("--frames", type=int, default=10, help="frames to run (0 = until interrupted)")
    p.add_argument("--sampler", default="q2tree", help="pharr, hemigon, q2tree or median-cut")
    p.add_argument("--count", type=int, default=256, help="lights per frame")
    p.add_argument("--calibration", type=Path, help="calibration JSON (default: the simulator's truth)")
    p.add_argument("--out", type=Path, default=Path("latest.exr"), help="where to write the latest HDR map")
    p.add_argument("--jsonl", type=Path, help="also write every light set, one JSON line per frame")
    p.add_argument("--pace", action="store_true", help="replay: at the recorded rate (default: as fast as it runs)")
    p.add_argument("--loop", action="store_true", help="replay: start again at the end")
    return p


def frame_line(r: Any) -> str:
    """The one line per frame ``run-pipeline`` and ``record`` print."""
    t = r.timings
    return (f"frame {r.frame:4d}  exposures {len(r.exposures)} ["
            + ", ".join(f"{e:.3g}" for e in r.exposures) + "] s  "
            + "  ".join(f"{k} {1e3 * v:.1f}ms" for k, v in t.items())
            + f"  lights {len(r.lights)}  energy {r.lights.total.sum():.4g} {r.unit}.sr"
            + ("  (skipped: unchanged)" if r.skipped else ""))


def camera_options(a: argparse.Namespace) -> dict[str, Any]:
    """A replay's options from the command line (other cameras take none of them)."""
    if not str(a.camera).startswith("replay:"):
        return {}
    return {"pace": bool(getattr(a, "pace", False)), "loop": bool(getattr(a, "loop", False))}


async def _run(a: argparse.Namespace) -> int:
    from lightprobe.core.imageio import write_exr
    from lightprobe.device.pipeline import Pipeline, PipelineConfig
    from lightprobe.drivers.replay import RecordingEnded

    camera, calibration = _open(a)
    pipe = Pipeline(camera, calibration, PipelineConfig(sampler=a.sampler, light_count=a.count))
    await pipe.start()
    try:
        i = 0
        jsonl = a.jsonl.open("w") if a.jsonl is not None else None
        while a.frames <= 0 or i < a.frames:
            try:
                r = await pipe.step()
            except RecordingEnded as e:
                print(f"{e}", flush=True)
                break
            i += 1
            print(frame_line(r), flush=True)
            if jsonl is not None:
                jsonl.write(r.lights.comparable_json() + "\n")
            write_exr(a.out, r.equirect, {"unit": r.unit, "frame": str(r.frame),
                                          "calibration": r.calibration_id})
    finally:
        if jsonl is not None:
            jsonl.close()
        await pipe.stop()
    print(f"latest HDR map: {a.out}")
    return 0


def _open(a: argparse.Namespace):  # type: ignore[no-untyped-def]
    """The camera (:func:`lightprobe.device.bootstrap.open_cli_camera`) and its calibration: --calibration,
    else the camera's own (the simulator's truth); InputError (exit 2) otherwise."""
    import json

    from lightprobe.core.calibration import Calibration
    from lightprobe.core.errors import InputError
    from lightprobe.device.bootstrap import open_cli_camera

    camera = open_cli_camera(a.camera, a.scene, **camera_options(a))
    if a.calibration is not None:
        try:
            return camera, Calibration.from_json(json.loads(a.calibration.read_text()))
        except (OSError, ValueError) as e:
            raise InputError(f"{a.calibration}: {e}", param="--calibration") from e
    try:
        cal = camera.factory_calibration()  # a replay's: the calibration it was recorded with
    except (OSError, ValueError) as e:
        raise InputError(f"--camera {a.camera}: {e}", param="--camera") from e
    if cal is None:
        raise InputError("a hardware camera needs --calibration FILE", param="--calibration")
    return camera, cal


def main(argv: list[str] | None = None) -> int:
    a = _parser().parse_args(argv)
    return run_command(lambda: asyncio.run(_run(a)))


if __name__ == "__main__":
    sys.exit(main())
