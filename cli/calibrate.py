"""``lightprobe calibrate ...``: calibration routines for technicians (the routines themselves are
in :mod:`calibration`; captures through the probe use :mod:`lightprobe.device.bootstrap`).

Subcommands: ``fisheye`` (checkerboard photos), ``response`` (bracketed photos), ``photometric``
(lux meter + probe map), ``vignetting`` (flat field), ``mask`` (lens frame), ``pose`` (installer
angles or a board on the floor), ``show``, ``history`` and ``rollback`` (the state directory's
calibration store). Results merge into ``--out`` (its other sections are kept) and, with
``--state DIR``, are saved as a new version in the store. Exit codes per CONVENTIONS.md: bad
input exits 2 with one line naming the files at fault.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

import numpy as np

from lightprobe.core.errors import InputError

__all__ = ["main"]


def _err(msg: str, param: str | None = None) -> InputError:
    return InputError(msg, param=param)


def _load_existing(out: Path | None) -> Any:
    from lightprobe.core.calibration import Calibration

    if out is None or not out.exists():
        return Calibration()
    try:
        return Calibration.from_json(json.loads(out.read_text()))
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise _err(f"{out}: existing calibration is not valid JSON ({e})", str(out)) from e
    except InputError as e:
        raise _err(f"{out}: {e}", str(out)) from e


def _write(args: argparse.Namespace, **sections: Any) -> None:
    """Merge ``sections`` into --out (keeping its others) and/or save to --state."""
    from lightprobe.calibration.store import CalibrationStore, atomic_write

    out = Path(args.out) if getattr(args, "out", None) else None
    state = getattr(args, "state", None)
    base = _load_existing(out)
    if out is None and state:
        res = CalibrationStore(state).load()
        base = res.calibration or base
    cal = base.with_(created="", **sections)
    data = (json.dumps(cal.to_json(), indent=1) + "\n").encode()
    if out is not None:
        out.parent.mkdir(parents=True, exist_ok=True)
        atomic_write(out, data)
        print(f"wrote {out} (id {cal.id})", file=sys.stderr)
    if state:
        v = CalibrationStore(state).save(cal)
        print(f"saved version {v.number} ({v.id}) in {state}", file=sys.stderr)


def _read_images(paths: list[str]) -> list[tuple[str, np.ndarray]]:
    import cv2

    out: list[tuple[str, np.ndarray]] = []
    sizes: dict[tuple[int, int], list[str]] = {}
    for p in paths:
        img = cv2.imread(p, cv2.IMREAD_UNCHANGED)
        if img is None:
            raise _err(f"{p}: not a readable image", p)
        out.append((p, img))
        sizes.setdefault((img.shape[1], img.shape[0]), []).append(p)
    if len(sizes) > 1:
        desc = "; ".join(f"{w}x{h}: {', '.join(ps)}" for (w, h), ps in sizes.items())
        raise _err(f"images differ in size ({desc})", "IMG")
    return out


def _progress() -> Any:
    from rich.console import Console
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn

    return Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(),
                    console=Console(stderr=True), transient=True)


def cmd_fisheye(args: argparse.Namespace) -> int:
    from lightprobe.calibration.fisheye import (
        View,
        board_object_points,
        calibrate_views,
        detect_board,
        parse_board,
    )

    try:
        board = parse_board(args.board, args.square)
    except ValueError as e:
        raise _err(f"--board/--square: {e}", "--board") from e
    images = _read_images(args.images)
    views, missing = [], []
    with _progress() as prog:
        task = prog.add_task("detecting board", total=len(images))
        for p, img in images:
            c = detect_board(img, board)
            (missing.append(p) if c is None else views.append(View(Path(p).name, c, board_object_points(board))))
            prog.advance(task)
    if len(views) < args.min_views:
        raise _err(f"no {args.board} board (inner corners) found in: {', '.join(missing)} "
                   f"({len(views)} usable views, need {args.min_views})", "IMG")
    for p in missing:
        print(f"warning: {p}: no {args.board} board found, skipped", file=sys.stderr)
    size = (images[0][1].shape[1], images[0][1].shape[0])
    try:
        res = calibrate_views(views, size, min_views=args.min_views,
                              progress=lambda m: print(m, file=sys.stderr))
    except ValueError as e:
        raise _err(f"{e}", "IMG") from e
    from dataclasses import replace

    from lightprobe.calibration.fisheye import field_of_view_deg

    model = replace(res.model, views_rejected=tuple(res.rejected) + tuple(Path(p).name for p in missing))
    circle = _image_circle([img for _, img in images], (float(model.K[0, 2]), float(model.K[1, 2])))
    if circle is not None:  # a circular fisheye: the field of view ends at the circle, not the corner
        model = replace(model, fov_deg=field_of_view_deg(model, circle))
    print(f"rms {res.rms_px:.3f} px, {len(res.used)} views used, {len(model.views_rejected)} rejected, "
          f"fx {model.K[0, 0]:.2f} fy {model.K[1, 1]:.2f} cx {model.K[0, 2]:.2f} cy {model.K[1, 2]:.2f}, "
          f"fov {model.fov_deg:.1f} deg, coverage {100 * res.coverage_fraction:.0f}%", file=sys.stderr)
    _write(args, fisheye=model)
    return 0


def _image_circle(images: list[np.ndarray], center: tuple[float, float]) -> float | None:
    """Radius of a circular fisheye's image circle from the per-pixel maximum of the photos
    (outside the circle every photo is dark), or None for a full-frame image."""
    from lightprobe.calibration.mask import find_mask

    stack = np.max([i if i.ndim == 2 else i.max(axis=2) for i in images], axis=0).astype(np.float64)
    h, w = stack.shape
    inscribed = min(center[0], center[1], w - 1 - center[0], h - 1 - center[1])
    try:
        m = find_mask(stack, center, margin_px=0.0)
    except ValueError:
        return None
    return m.radius_px if m.radius_px < inscribed - 2 else None


def _run(coro: Any) -> Any:
    import asyncio

    return asyncio.run(coro)


def _camera_base(args: argparse.Namespace, camera: Any) -> Any:
    """The calibration a camera capture builds on: --out, else --state's store, else the
    camera's own ground truth (the simulator)."""
    from lightprobe.calibration.store import CalibrationStore

    base = _load_existing(Path(args.out) if getattr(args, "out", None) else None)
    if not base.body() and getattr(args, "state", None):
        base = CalibrationStore(args.state).load().calibration or base
    own = camera.factory_calibration()
    if not base.body() and own is not None:
        base = own
    return base


def _check_source(args: argparse.Namespace, files: list[str] | str | None, what: str) -> None:
    if bool(files) == bool(args.camera):
        raise _err(f"give {what} or --camera SPEC (not both)", "--camera")
    if args.scene and not args.camera:
        raise _err("--scene needs --camera sim", "--scene")


def cmd_response(args: argparse.Namespace) -> int:
    from lightprobe.calibration.response import response_from_stack

    _check_source(args, args.images, "IMG...")
    if args.camera:
        return _response_from_camera(args)
    if args.times is None or len(args.times) != len(args.images):
        n = 0 if args.times is None else len(args.times)
        raise _err(f"--times has {n} values for {len(args.images)} images", "--times")
    imgs = [img for _, img in _read_images(args.images)]
    if any(i.dtype != np.uint8 or i.ndim != 3 for i in imgs):
        raise _err("response needs 8-bit RGB images: " + ", ".join(p for p, i in zip(args.images, imgs, strict=True)
                                                                     if i.dtype != np.uint8 or i.ndim != 3), "IMG")
    rgb = [np.ascontiguousarray(i[..., ::-1]) for i in imgs]
    try:
        resp = response_from_stack(rgb, args.times, method=args.method)
    except ValueError as e:
        raise _err(f"{', '.join(args.images)}: {e}", "IMG") from e
    _write(args, response=resp)
    return 0


def _response_from_camera(args: argparse.Namespace) -> int:
    """Bracket a static scene through the driver; processed output -> response solve, raw
    output -> linearity check (a linear response is written only when it passes)."""
    from lightprobe.calibration.capture import sweep_bracket
    from lightprobe.calibration.response import linearity_check, response_from_stack
    from lightprobe.core.calibration import Response
    from lightprobe.device.bootstrap import open_cli_camera
    from lightprobe.drivers.base import PixelFormat

    camera = open_cli_camera(args.camera, args.scene)
    frames, times = _run(sweep_bracket(camera, args.camera, args.exposures))
    print(f"captured {len(frames)} exposures {times[0]:.3g} .. {times[-1]:.3g} s", file=sys.stderr)
    f0 = frames[0]
    if f0.format is not PixelFormat.RGB8:
        rep = linearity_check([f.data for f in frames], times, f0.black_level, f0.white_level)
        print(f"raw linearity: max deviation {rep.max_deviation_percent:.2f}% over {len(rep.deviations_percent)} "
              "exposure pairs", file=sys.stderr)
        if not rep.ok(args.linearity_tolerance):
            print(f"lightprobe: error: raw output is not linear within {args.linearity_tolerance}%",
                  file=sys.stderr)
            return 1
        _write(args, response=Response.linear(f0.format.bit_depth, f0.black_level, f0.white_level))
        return 0
    try:
        resp = response_from_stack([f.data for f in frames], times, method=args.method)
    except ValueError as e:
        raise _err(f"--camera {args.camera}: {e}", "--camera") from e
    _write(args, response=resp)
    return 0


def cmd_photometric(args: argparse.Namespace) -> int:
    from lightprobe.calibration.photometric import lux_statistics, photometric_scale
    from lightprobe.core.imageio import read_hdr_image
    from lightprobe.drivers.t10a import T10A, T10AError

    _check_source(args, args.map, "--map")
    source = args.map or f"--camera {args.camera}"
    if args.camera:
        from lightprobe.device.bootstrap import capture_map, open_cli_camera

        camera = open_cli_camera(args.camera, args.scene)
        eq = _run(capture_map(camera, args.camera, _camera_base(args, camera)))
    else:
        eq = read_hdr_image(args.map)
    if args.lux is not None:
        values = list(args.lux)
    else:
        try:
            with T10A(args.port, timeout=args.timeout) as meter:
                values = meter.read_many(args.readings, interval=args.interval)
        except T10AError as e:
            print(f"lightprobe: error: lux meter: {e}", file=sys.stderr)
            return 1
    stats = lux_statistics(values)
    try:
        phot = photometric_scale(stats.mean, eq)
    except ValueError as e:
        raise _err(f"{source}: {e}", args.map or "--camera") from e
    print(json.dumps({"scale": phot.scale, "unit": phot.unit, "lux": stats.to_json()}), file=sys.stderr)
    _write(args, photometric=phot)
    return 0


def cmd_vignetting(args: argparse.Namespace) -> int:
    from lightprobe.calibration.vignetting import vignetting_from_flat_field
    from lightprobe.core.imageio import read_hdr_image

    _check_source(args, args.flat, "FLAT")
    if args.camera:
        from lightprobe.calibration.capture import capture_flat_field
        from lightprobe.device.bootstrap import open_cli_camera

        camera = open_cli_camera(args.camera, args.scene)
        existing = _camera_base(args, camera)
        print("flat field: cover the lens with the opal diffuser (or put the probe in the "
              "integrating sphere) and keep the light steady", file=sys.stderr)
        img = _run(capture_flat_field(camera, args.camera, frames=args.frames, response=existing.response))
        source = f"--camera {args.camera}"
    else:
        img = read_hdr_image(args.flat)
        existing = _load_existing(Path(args.out) if args.out else None)
        source = args.flat
    h, w = img.shape[:2]
    if args.center:
        center = (args.center[0], args.center[1])
    elif existing.fisheye is not None:
        center = (float(existing.fisheye.K[0, 2]), float(existing.fisheye.K[1, 2]))
    else:
        center = ((w - 1) / 2, (h - 1) / 2)
    radius = args.radius or (existing.mask.radius_px if existing.mask else min(w, h) / 2)
    try:
        max_r = args.max_r if args.max_r is not None else (0.97 if args.camera else 1.0)
        vig = vignetting_from_flat_field(img, center, radius, max_r=max_r,
                                         saturation=0.98 if args.camera else None)
    except ValueError as e:
        raise _err(f"{source}: {e}", args.flat or "--camera") from e
    _write(args, vignetting=vig)
    return 0


def cmd_mask(args: argparse.Namespace) -> int:
    from lightprobe.calibration.mask import find_mask
    from lightprobe.core.imageio import read_hdr_image

    img = read_hdr_image(args.image)
    h, w = img.shape[:2]
    center = tuple(args.center) if args.center else ((w - 1) / 2, (h - 1) / 2)
    try:
        m = find_mask(img, center, threshold=args.threshold, margin_px=args.margin)
    except ValueError as e:
        raise _err(f"{args.image}: {e}", args.image) from e
    _write(args, mask=m)
    return 0


def cmd_pose(args: argparse.Namespace) -> int:
    from lightprobe.calibration.pose import pose_from_angles, pose_from_board

    if args.board_image:
        return _pose_from_board_image(args, pose_from_board)
    if args.heading is None:
        raise _err("give --heading (installer angles) or --board-image", "--heading")
    try:
        pose = pose_from_angles(args.heading, args.tilt, args.tilt_azimuth, tuple(args.position))
    except ValueError as e:
        raise _err(str(e), "--heading") from e
    _write(args, pose=pose)
    return 0


def _pose_from_board_image(args: argparse.Namespace, pose_from_board: Any) -> int:
    """Pose from a board lying on the floor, seen through the calibrated fisheye."""
    from dataclasses import replace

    from lightprobe.calibration.fisheye import (
        board_object_points,
        detect_board,
        orient_corners,
        parse_board,
    )
    from lightprobe.calibration.store import CalibrationStore

    existing = _load_existing(Path(args.out) if args.out else None)
    if existing.fisheye is None and args.state:
        existing = CalibrationStore(args.state).load().calibration or existing
    if existing.fisheye is None:
        raise _err("--board-image needs a fisheye calibration in --out or --state", "--board-image")
    if not args.board:
        raise _err("--board-image needs --board COLSxROWS", "--board")
    try:
        board = parse_board(args.board, args.square)
    except ValueError as e:
        raise _err(f"--board/--square: {e}", "--board") from e
    (path, img), = _read_images([args.board_image])
    corners = detect_board(img, board, accurate=True)
    if corners is None:
        raise _err(f"{path}: no {args.board} board found", path)
    if (board.cols + board.rows) % 2 == 0:
        print("warning: a board with both counts even or both odd is symmetric: the heading may be "
              "off by 180 degrees (use e.g. 9x6)", file=sys.stderr)
    corners = orient_corners(img, corners, board)
    try:
        pose = pose_from_board(corners, board_object_points(board), existing.fisheye)
    except ValueError as e:
        raise _err(f"{path}: {e}", path) from e
    _write(args, pose=replace(pose, position=np.asarray(args.position, np.float64)))
    return 0


def cmd_show(args: argparse.Namespace) -> int:
    from lightprobe.calibration.store import CalibrationStore

    if args.state:
        res = CalibrationStore(args.state).load()
        for e in res.errors:
            print(f"warning: {e}", file=sys.stderr)
        if res.calibration is None:
            raise _err(f"{args.state}: no valid calibration", "--state")
        cal = res.calibration
    elif args.file:
        cal = _load_existing(Path(args.file))
        if not Path(args.file).exists():
            raise _err(f"{args.file}: no such file", args.file)
    else:
        raise _err("give CALIB.json or --state DIR", "file")
    print(json.dumps(cal.to_json(), indent=1))
    return 0


def cmd_history(args: argparse.Namespace) -> int:
    from lightprobe.calibration.store import CalibrationStore, CorruptCalibration

    store = CalibrationStore(args.state)
    try:
        cur = store.current_version().number
    except CorruptCalibration:
        cur = None
    for v in store.versions():
        try:
            store.read_version(v)
            state = "ok"
        except CorruptCalibration as e:
            state = f"corrupt: {e}"
        print(f"{'*' if v.number == cur else ' '} {v.number:6d} {v.id} {state}")
    return 0


def cmd_rollback(args: argparse.Namespace) -> int:
    from lightprobe.calibration.store import CalibrationStore

    v = CalibrationStore(args.state).rollback(args.to)
    print(f"current calibration is now version {v.number} ({v.id})", file=sys.stderr)
    return 0


def camera_opts(sp: argparse.ArgumentParser, what: str) -> None:
    sp.add_argument("--camera", metavar="SPEC", help=f"sim | v4l2:/dev/videoN | libcamera | uvc: {what}")
    sp.add_argument("--scene", help="simulator scene NAME or map PATH (with --camera sim)")


def out_opts(sp: argparse.ArgumentParser) -> None:
    sp.add_argument("--out", help="calibration JSON to write (merged if it exists)")
    sp.add_argument("--state", help="state directory: also save as a new version in its store")


def _add_measure_parsers(sub: Any) -> None:
    """photometric, vignetting, mask and pose subcommands."""
    ph = sub.add_parser("photometric", help="photometric scale from a lux meter beside the probe")
    ph.add_argument("--map", help="the probe's equirect map (.exr/.hdr) at the meter time")
    camera_opts(ph, "capture the map now (one HDR burst, fused and projected)")
    src = ph.add_mutually_exclusive_group(required=True)
    src.add_argument("--port", help="serial port of a Konica Minolta T-10A")
    src.add_argument("--lux", type=float, nargs="+", help="readings typed in by hand (lux)")
    ph.add_argument("--readings", type=int, default=5)
    ph.add_argument("--interval", type=float, default=0.5)
    ph.add_argument("--timeout", type=float, default=1.0)
    out_opts(ph)
    ph.set_defaults(fn=cmd_photometric)

    v = sub.add_parser("vignetting", help="radial fall-off from a linear flat-field image")
    v.add_argument("flat", metavar="FLAT", nargs="?", help="linear flat-field image (.exr/.hdr)")
    camera_opts(v, "capture the flat field now (the sim's scene 'uniform' is an integrating sphere)")
    v.add_argument("--frames", type=int, default=4, help="frames averaged with --camera")
    v.add_argument("--center", type=float, nargs=2)
    v.add_argument("--radius", type=float, help="image-circle radius (px)")
    v.add_argument("--max-r", type=float, default=None,
                   help="fit radii up to this fraction of --radius (default 1; 0.97 with --camera: "
                        "pixels straddling the housing ring stay out)")
    out_opts(v)
    v.set_defaults(fn=cmd_vignetting)

    m = sub.add_parser("mask", help="lens frame mask from a capture")
    m.add_argument("image", metavar="IMG")
    m.add_argument("--center", type=float, nargs=2)
    m.add_argument("--threshold", type=float, default=0.25)
    m.add_argument("--margin", type=float, default=3.0)
    out_opts(m)
    m.set_defaults(fn=cmd_mask)

    po = sub.add_parser("pose", help="mounting pose from installer angles (deg) or a floor board")
    po.add_argument("--heading", type=float, help="room azimuth of the front mark (deg)")
    po.add_argument("--tilt", type=float, default=0.0)
    po.add_argument("--tilt-azimuth", type=float, default=0.0)
    po.add_argument("--position", type=float, nargs=3, default=(0.0, 0.0, 0.0), help="metres")
    po.add_argument("--board-image", help="photo of a board on the floor (x axis = azimuth 0)")
    po.add_argument("--board", help="COLSxROWS inner corners of the floor board")
    po.add_argument("--square", type=float, default=1.0, help="square size (any unit)")
    out_opts(po)
    po.set_defaults(fn=cmd_pose)



def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="lightprobe calibrate", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="cmd", required=True)

    f = sub.add_parser("fisheye", help="fisheye geometry from checkerboard photos")
    f.add_argument("images", nargs="+", metavar="IMG")
    f.add_argument("--board", required=True, help="COLSxROWS inner corners, e.g. 8x6")
    f.add_argument("--square", type=float, required=True, help="square size in mm")
    f.add_argument("--min-views", type=int, default=4)
    out_opts(f)
    f.set_defaults(fn=cmd_fisheye)

    r = sub.add_parser("response", help="response curve from a bracketed static scene")
    r.add_argument("images", nargs="*", metavar="IMG")
    r.add_argument("--times", nargs="+", type=float, help="exposure times (s) of IMG...")
    camera_opts(r, "capture the bracket now (a metering sweep one stop apart unless --exposures)")
    r.add_argument("--exposures", nargs="+", type=float, help="exposure times (s) to capture with --camera")
    r.add_argument("--linearity-tolerance", type=float, default=2.0, help="raw modes: max deviation (%%)")
    r.add_argument("--method", choices=("debevec", "robertson"), default="debevec")
    out_opts(r)
    r.set_defaults(fn=cmd_response)

    _add_measure_parsers(sub)
    s = sub.add_parser("show", help="print a calibration")
    s.add_argument("file", nargs="?")
    s.add_argument("--state")
    s.set_defaults(fn=cmd_show)
    h = sub.add_parser("history", help="list stored versions")
    h.add_argument("--state", required=True)
    h.set_defaults(fn=cmd_history)
    rb = sub.add_parser("rollback", help="make an earlier version current")
    rb.add_argument("--state", required=True)
    rb.add_argument("--to", type=int)
    rb.set_defaults(fn=cmd_rollback)
    return p


def main(argv: list[str]) -> int:
    from lightprobe.core.command import run_command

    args = _parser().parse_args(argv)
    if args.cmd not in ("show", "history", "rollback") and not (args.out or args.state):
        print("lightprobe calibrate: error: give --out CALIB.json and/or --state DIR", file=sys.stderr)
        return 2
    return run_command(args.fn, args)
