"""``lightprobe run-pipeline``: run the capture pipeline without the service.

Prints per-frame stats (exposures, stage timings, lights, skipped) and writes the latest HDR
equirect map (EXR) after every frame. Useful on a bench and on a unit without the network.
"""

from __future__ import annotations

import argparse
import asyncio
import sys
from pathlib import Path

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
    return p


async def _run(a: argparse.Namespace) -> int:
    from lightprobe.core.imageio import write_exr
    from lightprobe.device.pipeline import Pipeline, PipelineConfig

    camera, calibration = _open(a)
    pipe = Pipeline(camera, calibration, PipelineConfig(sampler=a.sampler, light_count=a.count))
    await pipe.start()
    try:
        i = 0
        while a.frames <= 0 or i < a.frames:
            r = await pipe.step()
            i += 1
            t = r.timings
            print(f"frame {r.frame:4d}  exposures {len(r.exposures)} ["
                  + ", ".join(f"{e:.3g}" for e in r.exposures) + "] s  "
                  + "  ".join(f"{k} {1e3 * v:.1f}ms" for k, v in t.items())
                  + f"  lights {len(r.lights)}  energy {r.lights.total.sum():.4g} {r.unit}.sr"
                  + ("  (skipped: unchanged)" if r.skipped else ""), flush=True)
            write_exr(a.out, r.equirect, {"unit": r.unit, "frame": str(r.frame),
                                          "calibration": r.calibration_id})
    finally:
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

    camera = open_cli_camera(a.camera, a.scene)
    if a.calibration is not None:
        try:
            return camera, Calibration.from_json(json.loads(a.calibration.read_text()))
        except (OSError, ValueError) as e:
            raise InputError(f"{a.calibration}: {e}", param="--calibration") from e
    cal = camera.factory_calibration()
    if cal is None:
        raise InputError("a hardware camera needs --calibration FILE", param="--calibration")
    return camera, cal


def main(argv: list[str] | None = None) -> int:
    a = _parser().parse_args(argv)
    return run_command(lambda: asyncio.run(_run(a)))


if __name__ == "__main__":
    sys.exit(main())
