"""``lightprobe fuse IMG... --times T... [--response FILE] --out OUT.exr``

Fuses an exposure stack of 8-bit images into a linear HDR image (OpenEXR, float32, metadata
``unit=relative``, ``exposures``, ``response``, ``saturated_pixels``). Without ``--response`` the
camera response is estimated from the stack itself (Debevec & Malik 1997,
:mod:`device.hdr.response`, on deterministically sampled pixels). Bad input
(unreadable image, mismatched sizes, missing or non-positive times, count mismatch) exits 2 with a
one-line message naming the file or value (CONVENTIONS.md).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from device.core.calibration import Calibration, Response
from device.core.errors import InputError

__all__ = ["estimate_response", "main", "read_stack", "read_times_file"]


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="lightprobe fuse",
        description="Fuse an exposure stack of 8-bit images into a linear HDR OpenEXR image.",
    )
    p.add_argument("images", nargs="+", metavar="IMG", help="8-bit images (any format OpenCV reads)")
    p.add_argument("--times", nargs="+", metavar="T",
                   help="exposure time of each image in seconds, in the same order (e.g. 0.01 1/250)")
    p.add_argument("--times-file", type=Path, metavar="FILE",
                   help="text file of 'IMAGE_NAME SECONDS' (or just SECONDS) lines, instead of --times")
    p.add_argument("--response", type=Path, metavar="FILE",
                   help="calibration JSON with a 'response' section (or a bare response object); "
                        "default: estimate it from the stack (Debevec-Malik)")
    p.add_argument("--out", type=Path, required=True, metavar="OUT.exr", help="output OpenEXR file")
    p.add_argument("--no-deghost", action="store_true",
                   help="keep samples that disagree with the reference exposure (static scenes)")
    p.add_argument("--smoothness", type=float, default=None,
                   help="Debevec-Malik smoothness lambda per sample when estimating the response "
                        "(default: calibration.response.SMOOTHNESS)")
    return p


def _parse_time(text: str) -> float:
    """Seconds from '0.004', '4e-3' or '1/250'; InputError naming the value otherwise."""
    try:
        if "/" in text:
            num, den = text.split("/", 1)
            value = float(num) / float(den)
        else:
            value = float(text)
    except (ValueError, ZeroDivisionError) as e:
        raise InputError(f"exposure time {text!r} is not a number of seconds", param="--times") from e
    if not (np.isfinite(value) and value > 0):
        raise InputError(f"exposure time {text!r} must be positive", param="--times")
    return value


def read_times_file(path: Path, images: list[Path]) -> list[float]:
    """Times from a text file: 'NAME SECONDS' lines matched by image file name, or one time per
    line in image order. Blank lines and '#' comments are ignored."""
    try:
        lines = path.read_text().splitlines()
    except (OSError, UnicodeDecodeError) as e:
        raise InputError(f"{path}: cannot read times file ({e})", param=str(path)) from e
    rows = [ln.split("#", 1)[0].split() for ln in lines]
    rows = [r for r in rows if r]
    if rows and all(len(r) == 2 for r in rows):
        table = {r[0]: r[1] for r in rows}
        out = []
        for img in images:
            if img.name not in table:
                raise InputError(f"{path}: no exposure time for {img.name}", param=str(path))
            out.append(_parse_time(table[img.name]))
        return out
    if rows and all(len(r) == 1 for r in rows):
        return [_parse_time(r[0]) for r in rows]
    raise InputError(f"{path}: expected 'NAME SECONDS' or 'SECONDS' lines", param=str(path))


def read_stack(images: list[Path]) -> list[np.ndarray]:
    """Read 8-bit RGB images (H, W, 3) uint8; InputError naming the file at fault."""
    import cv2

    out: list[np.ndarray] = []
    for p in images:
        if not p.is_file():
            raise InputError(f"{p}: no such file", param=str(p))
        img = cv2.imread(str(p), cv2.IMREAD_COLOR)
        if img is None:
            raise InputError(f"{p}: not a readable image", param=str(p))
        if img.dtype != np.uint8:
            raise InputError(f"{p}: expected an 8-bit image, got {img.dtype}", param=str(p))
        if out and img.shape != out[0].shape:
            raise InputError(f"{p}: size {img.shape[1]}x{img.shape[0]} differs from {images[0]} "
                             f"({out[0].shape[1]}x{out[0].shape[0]})", param=str(p))
        out.append(np.ascontiguousarray(img[..., ::-1]))
    return out


def estimate_response(frames: list[np.ndarray], times: list[float], smoothness: float | None = None) -> Response:
    """Debevec-Malik response of the stack itself (:func:`calibration.response.solve_debevec`)."""
    from calibration.response import SMOOTHNESS, solve_debevec

    return solve_debevec(frames, times, smoothness=SMOOTHNESS if smoothness is None else smoothness)


def _load_response(path: Path) -> Response:
    try:
        doc = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise InputError(f"{path}: not a readable JSON file ({e})", param=str(path)) from e
    if not isinstance(doc, dict):
        raise InputError(f"{path}: expected a JSON object", param=str(path))
    try:
        if "version" in doc:
            resp = Calibration.from_json(doc).response
        else:
            resp = Response.from_json(doc.get("response", doc))
    except InputError as e:
        raise InputError(f"{path}: {e}", param=str(path)) from e
    if resp is None:
        raise InputError(f"{path}: calibration has no 'response' section", param=str(path))
    if resp.bits != 8:
        raise InputError(f"{path}: response is for {resp.bits}-bit data, images are 8-bit", param=str(path))
    return resp


def _run(ns: argparse.Namespace) -> int:
    from device.core.imageio import write_exr
    from device.hdr.fusion import FusionSettings, fuse

    images = [Path(p) for p in ns.images]
    if ns.times is not None and ns.times_file is not None:
        raise InputError("give --times or --times-file, not both", param="--times")
    if ns.times_file is not None:
        times = read_times_file(ns.times_file, images)
    elif ns.times is not None:
        times = [_parse_time(t) for t in ns.times]
    else:
        raise InputError("missing exposure times: give --times T... or --times-file FILE", param="--times")
    if len(times) != len(images):
        raise InputError(f"{len(images)} images but {len(times)} exposure times", param="--times")
    if ns.out.suffix.lower() != ".exr":
        raise InputError(f"{ns.out}: output must be an .exr file", param="--out")
    if not ns.out.parent.is_dir():
        raise InputError(f"{ns.out}: folder {ns.out.parent} does not exist", param="--out")
    response = _load_response(ns.response) if ns.response is not None else None
    frames = read_stack(images)
    if response is None:
        response = estimate_response(frames, times, ns.smoothness)
    # An estimated response is only good to a few percent: widen the ghost tolerance accordingly
    settings = FusionSettings(deghost=not ns.no_deghost,
                              ghost_rel_tol=0.05 if response.method == "truth" else 0.25)
    res = fuse(frames, times, response, settings=settings)
    meta = {
        "unit": "relative",
        "exposures": ",".join(f"{t:.9g}" for t in times),
        "response": response.method or response.model,
        "saturated_pixels": str(int(res.saturated.sum())),
        "invalid_pixels": str(int(res.invalid.sum())),
        "software": "lightprobe fuse",
    }
    write_exr(ns.out, res.radiance, meta)
    lum = res.radiance.mean(axis=2)
    good = ~(res.saturated | res.invalid) & (lum > 0)
    dr = float(lum[good].max() / lum[good].min()) if good.any() else 0.0
    print(f"{ns.out}: {res.radiance.shape[1]}x{res.radiance.shape[0]}, {len(images)} exposures, "
          f"dynamic range {dr:.3g}, {int(res.saturated.sum())} saturated pixels")
    return 0


def main(argv: list[str]) -> int:
    from device.core.command import run_command

    ns = _parser().parse_args(argv)
    return run_command(_run, ns)
