"""``lightprobe record``: a recording of a camera as the probe runs it, or of a real bracket.

From a camera (the service stopped; while it runs, ``POST /api/v1/recordings`` does the same)::

    lightprobe record --camera SPEC [--scene S] [--calibration CAL.json] --seconds N --out FILE

runs the live pipeline on the camera for ``N`` seconds, exactly as ``run-pipeline`` (one line
per frame with ``energy E``), and writes every frame the camera delivered with its metadata, the
calibration and the camera's capabilities (:mod:`lightprobe.drivers.recording`). ``lightprobe
run-pipeline --camera replay:FILE`` then prints the same lines, and ``--jsonl`` the same light
sets, bit for bit.

From photographs (a real exposure stack, so the live pipeline runs on real pixels)::

    lightprobe record --stack IMG... --times T... --calibration CAL.json --out FILE [--size WxH]

stores each photograph once, as a ``bracket`` recording: a replay answers each frame with the
photograph nearest the exposure the pipeline asked for. ``--times`` are the exposures the frames'
metadata will say (for a phone's stack, the effective exposures ``lightprobe fuse`` reports in
its EXR's ``exposures``, not the labels). The photographs are stored at their own size, or
downscaled to ``--size`` (area interpolation); the calibration's ``image_size`` must be that size.
Its response is the stack's camera's (8-bit frames are not linear); a calibration of a camera
that is not a fisheye is allowed (the projection covers what the lens sees). The mode's frame
rate is the one the longest exposure allows (at most 30 fps).

Bad input (a missing image, a count mismatch, a calibration of another size, an existing
``--out``) exits 2 naming it; the recording is written to ``FILE.part`` and renamed when whole.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import sys
import time
from pathlib import Path
from typing import Any

from lightprobe.core.errors import InputError

__all__ = ["main"]


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="lightprobe record", description=__doc__.splitlines()[0])
    p.add_argument("--camera", help="camera spec (sim, v4l2:/dev/videoN, libcamera, uvc, ...)")
    p.add_argument("--scene", default="flashlight", help="simulated scene (sim only)")
    p.add_argument("--seconds", type=float, default=10.0, help="how long to record a camera (default 10)")
    p.add_argument("--stack", nargs="+", metavar="IMG", help="photographs of a bracket (instead of --camera)")
    p.add_argument("--times", nargs="+", metavar="T", help="exposure of each photograph, seconds (1/250 works)")
    p.add_argument("--size", help="store the photographs at WxH (default: their own size)")
    p.add_argument("--calibration", type=Path, help="calibration JSON (a camera's default: its own; required with --stack)")
    p.add_argument("--sampler", default="q2tree", help="the live pipeline's sampler (camera recordings)")
    p.add_argument("--count", type=int, default=256, help="lights per frame (camera recordings)")
    p.add_argument("--jsonl", type=Path, help="camera recordings: also write every light set, as run-pipeline --jsonl")
    p.add_argument("--out", type=Path, required=True, help="the recording file to write (.lprec)")
    return p


def _load_calibration(path: Path) -> Any:
    from lightprobe.core.calibration import Calibration

    try:
        return Calibration.from_json(json.loads(path.read_text()))
    except (OSError, ValueError) as e:
        raise InputError(f"{path}: {e}", param="--calibration") from e


def _size(text: str) -> tuple[int, int]:
    parts = text.lower().split("x")
    if len(parts) != 2 or not all(p.isdigit() and int(p) > 0 for p in parts):
        raise InputError(f"--size {text!r}: expected WxH, e.g. 640x427", param="--size")
    return int(parts[0]), int(parts[1])


def _check_out(out: Path) -> Path:
    if out.exists():
        raise InputError(f"{out}: exists (a recording is never overwritten)", param="--out")
    if not out.parent.is_dir():
        raise InputError(f"{out}: folder {out.parent} does not exist", param="--out")
    part = out.with_name(out.name + ".part")
    part.unlink(missing_ok=True)
    return part


async def _record_camera(a: argparse.Namespace) -> int:
    from lightprobe.cli.run_pipeline import frame_line
    from lightprobe.device.bootstrap import open_cli_camera
    from lightprobe.device.pipeline import Pipeline, PipelineConfig
    from lightprobe.drivers.recording import RecordingCamera, RecordingWriter

    if a.seconds <= 0:
        raise InputError(f"--seconds must be > 0, got {a.seconds}", param="--seconds")
    part = _check_out(a.out)
    camera = open_cli_camera(a.camera, a.scene)
    calibration = _load_calibration(a.calibration) if a.calibration is not None else camera.factory_calibration()
    if calibration is None:
        raise InputError("a hardware camera needs --calibration FILE", param="--calibration")
    calibration = type(calibration).from_json(calibration.to_json())  # what the recording holds (rounded)
    rec = RecordingCamera(camera)
    pipe = Pipeline(rec, calibration, PipelineConfig(sampler=a.sampler, light_count=a.count))
    await pipe.start()
    writer = RecordingWriter(part, rec.header(calibration=calibration.to_json(), source=a.camera),
                             max_seconds=a.seconds + 60.0)
    rec.start(writer)
    jsonl = a.jsonl.open("w") if a.jsonl is not None else None
    try:
        t_end = None  # counted from the first frame (the start builds tables first)
        while (t_end is None or time.monotonic() < t_end) and not writer.full:  # every frame run is recorded
            r = await pipe.step()
            t_end = t_end or time.monotonic() + a.seconds
            print(frame_line(r), flush=True)
            if jsonl is not None:
                jsonl.write(r.lights.comparable_json() + "\n")
    finally:
        if jsonl is not None:
            jsonl.close()
        rec.stop()
        writer.close()
        await pipe.stop()
    if writer.error is not None:
        raise InputError(f"recording failed: {writer.error}", param="--out")
    os.replace(part, a.out)
    st = writer.status()
    print(f"{a.out}: {st['frames']} frames, {st['seconds']:.2f} s, {st['bytes'] / 1e6:.1f} MB"
          + (f", {st['lost_frames']} frames lost (the disk was too slow)" if st["lost_frames"] else ""))
    return 0


def _record_stack(a: argparse.Namespace) -> int:
    import cv2
    import numpy as np

    from lightprobe.device.hdr.stack import parse_time, read_stack
    from lightprobe.drivers.base import Capabilities, Frame, FrameMetadata, Mode, PixelFormat
    from lightprobe.drivers.recording import RecordingWriter, capabilities_to_json

    images = [Path(p) for p in a.stack]
    if not a.times:
        raise InputError("--stack needs --times T... (one exposure per photograph)", param="--times")
    times = [parse_time(t) for t in a.times]
    if len(times) != len(images):
        raise InputError(f"{len(images)} photographs but {len(times)} exposure times", param="--times")
    if a.calibration is None:
        raise InputError("--stack needs --calibration CAL.json (the lens and the response)", param="--calibration")
    calibration = _load_calibration(a.calibration)
    if calibration.fisheye is None or calibration.response is None:
        raise InputError(f"{a.calibration}: a recording of photographs needs a lens ('fisheye') and a "
                         "response", param="--calibration")
    frames = read_stack(images)
    h, w = frames[0].shape[:2]
    if a.size:
        w, h = _size(a.size)
        frames = [np.ascontiguousarray(cv2.resize(f, (w, h), interpolation=cv2.INTER_AREA)) for f in frames]
    if tuple(calibration.fisheye.image_size) != (w, h):
        raise InputError(f"{a.calibration}: image_size {list(calibration.fisheye.image_size)} is not the "
                         f"photographs' {w}x{h}", param="--calibration")
    part = _check_out(a.out)
    fps = min(30.0, 1.0 / max(times))
    mode = Mode(w, h, PixelFormat.RGB8, fps)
    caps = Capabilities(exposure_range=(min(times), max(times)), gain_range=(1.0, 1.0), modes=(mode,),
                        has_frame_metadata=True, control_latency_frames=1, model="photographs")
    header = {"kind": "bracket", "source": " ".join(str(p) for p in images),
              "camera": capabilities_to_json(caps),
              "mode": {"width": w, "height": h, "format": "rgb8", "max_fps": fps},
              "calibration": calibration.to_json()}
    writer = RecordingWriter(part, header, queue_frames=len(frames) + 1)
    try:
        for i in np.argsort(times, kind="stable"):
            meta = FrameMetadata(exposure_s=times[i], gain=1.0, timestamp_s=0.0, sequence=int(i))
            writer.append(Frame(frames[i], meta, PixelFormat.RGB8, extra={"photo": str(images[i])}),
                          delivered_s=0.0)
    finally:
        writer.close()
    if writer.error is not None or writer.frames != len(frames):
        raise InputError(f"recording failed: {writer.error or 'frames lost'}", param="--out")
    os.replace(part, a.out)
    print(f"{a.out}: {len(frames)} photographs at {w}x{h}, {min(times):.3g}-{max(times):.3g} s, "
          f"{writer.bytes / 1e6:.1f} MB")
    return 0


def main(argv: list[str] | None = None) -> int:
    from lightprobe.core.command import run_command

    a = _parser().parse_args(argv)
    if (a.camera is None) == (a.stack is None):
        print("lightprobe record: error: give --camera SPEC or --stack IMG... (one of them)", file=sys.stderr)
        return 2
    if a.stack is not None:
        return run_command(lambda: _record_stack(a))
    return run_command(lambda: asyncio.run(_record_camera(a)))


if __name__ == "__main__":
    sys.exit(main())
