"""``lightprobe fuse IMG... --times T... [--response FILE] [--align] --out OUT.exr``

Fuses an exposure stack of 8-bit images into a linear HDR image (OpenEXR, float32, metadata
``unit=relative``, ``exposures``, ``exposure_labels``, ``response``, ``saturated_pixels``).
Without ``--response`` the camera response is estimated from the stack itself (Debevec & Malik
1997, :func:`calibration.response.fit_stack`, with the scatter per code the merge weights by),
and so is each frame's effective exposure: shutter labels are nominal (1/15 s for 2^-4 s) and a
phone changes its gain unlabelled, so the frames are fused with the exposures the pictures show
(``exposures``; the given ones are ``exposure_labels``). It reports what it did: the response's
source, the exposure corrections, the frames' misregistration (``--align`` registers a hand-held
stack first, :mod:`device.hdr.align`), the share of samples the deghosting rejected, the
saturated and too-dark fractions, the dynamic range, and warnings for a bad stack. Bad input
(unreadable image, mismatched sizes, missing or non-positive times, count mismatch, frames that
do not get brighter with their times) exits 2 with a one-line message naming the file or value
(CONVENTIONS.md).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from device.core.calibration import Calibration, Response
from device.core.errors import InputError

if TYPE_CHECKING:
    from calibration.response import StackFit
    from device.hdr.fusion import FusionSettings

__all__ = ["fit_response", "fuse_report", "fusion_settings", "main", "read_stack", "read_times_file"]

EXPOSURE_WARN = 0.15  # an exposure that the pictures put this far from its label is reported


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
    p.add_argument("--align", action="store_true",
                   help="register a hand-held stack first (median threshold bitmaps, whole pixels); "
                        "without it a misregistered stack is only reported")
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


def fit_response(frames: list[np.ndarray], times: list[float], smoothness: float | None = None, *,
                 refine_exposures: bool = True) -> StackFit:
    """Debevec-Malik response of the stack itself and the effective exposures it was solved with
    (:func:`calibration.response.fit_stack`): fuse the stack with ``fit.exposures_s``."""
    from calibration.response import SMOOTHNESS, fit_stack

    return fit_stack(frames, times, smoothness=SMOOTHNESS if smoothness is None else smoothness,
                     refine_exposures=refine_exposures)


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
    from device.hdr.align import apply_shifts, stack_shifts
    from device.hdr.fusion import fuse

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
    shifts = stack_shifts(frames)
    if ns.align:
        frames = apply_shifts(frames, shifts)
    source = f"{ns.response}" if response is not None else "estimated from the stack"
    fit = None
    if response is not None:  # (the stack's own fit checks this itself)
        from calibration.response import check_brightens

        check_brightens(frames, times)
    else:
        fit = fit_response(frames, times, ns.smoothness)
        response = fit.response
    exposures = list(fit.exposures_s) if fit is not None else times
    settings = fusion_settings(response, deghost=not ns.no_deghost)
    res = fuse(frames, exposures, response, settings=settings)
    report = fuse_report(res, response, source, shifts=shifts, aligned=ns.align, fit=fit)
    meta = {
        "unit": "relative",
        "exposures": ",".join(f"{t:.9g}" for t in exposures),
        "exposure_labels": ",".join(f"{t:.9g}" for t in times),
        "response": response.method or response.model,
        "saturated_pixels": str(int(res.saturated.sum())),
        "invalid_pixels": str(int(res.invalid.sum())),
        "deghost_rejected": f"{report['deghost_rejected_fraction']:.6g}",
        "aligned": " ".join(f"{dx},{dy}" for dx, dy in shifts) if ns.align else "no",
        "software": "lightprobe fuse",
    }
    write_exr(ns.out, res.radiance, meta)
    print(f"{ns.out}: {res.radiance.shape[1]}x{res.radiance.shape[0]}, {len(images)} exposures")
    print(f"  response: {report['response']} ({source}); noise model: {report['noise_model']}")
    if fit is not None:
        print(f"  exposures: {report['exposures_refined']} of {len(times)} refined from the pictures, "
              f"largest correction x{report['max_exposure_correction']:.3f} of the label")
    print(f"  registration: {'applied' if ns.align else 'not applied'}, frames off by up to "
          f"{report['max_shift_px']} px")
    print(f"  deghosting: {'off' if ns.no_deghost else 'on'}, {100 * report['deghost_rejected_fraction']:.2f}% "
          "of the usable samples rejected")
    print(f"  saturated in every exposure: {100 * report['saturated_fraction']:.2f}% of pixels; "
          f"no usable sample (too dark or invalid): {100 * report['dark_fraction']:.2f}%")
    print(f"  dynamic range (p99.9 / p0.1 of luminance): {report['dynamic_range']:.3g}")
    for warn in report["warnings"]:
        print(f"  warning: {warn}")
    return 0


def fusion_settings(response: Response, *, deghost: bool = True) -> FusionSettings:
    """The merge settings for a response: a truth response or one that carries its measured
    scatter (``log_sigma``) lets the deghosting test against the real noise (a small relative
    tolerance); a table without it is only good to a few percent, so the tolerance widens."""
    from device.hdr.fusion import FusionSettings

    exact = response.method == "truth" or response.log_sigma is not None
    return FusionSettings(deghost=deghost, ghost_rel_tol=0.05 if exact else 0.25)


def fuse_report(res: Any, response: Response, source: str, shifts: list[tuple[int, int]] | None = None,
                aligned: bool = False, fit: StackFit | None = None) -> dict[str, Any]:
    """What a fusion did, so a user sees a bad stack for what it is. ``shifts``: each frame's
    registration (:func:`device.hdr.align.stack_shifts`), applied if ``aligned``; ``fit``: the
    stack's own response fit, whose exposure corrections are reported (each frame's effective
    exposure over its label) and warned about beyond :data:`EXPOSURE_WARN`."""
    lum = res.radiance @ np.array([0.2126, 0.7152, 0.0722], np.float32)
    good = lum[np.isfinite(lum) & (lum > 0) & ~res.saturated & ~res.invalid]
    dr = float(np.percentile(good, 99.9) / np.percentile(good, 0.1)) if good.size > 10 else 0.0
    out: dict[str, Any] = {
        "response": response.method or response.model, "response_source": source,
        "noise_model": "measured scatter per code" if response.log_sigma is not None
        else ("sensor model" if response.method in ("truth", "linear") else "sensor model (no measured scatter)"),
        "deghost_rejected_fraction": res.rejected_fraction,
        "saturated_fraction": float(res.saturated.mean()), "dark_fraction": float(res.invalid.mean()),
        "dynamic_range": dr, "warnings": [],
        "shifts": [list(s) for s in shifts or []], "aligned": aligned,
        "max_shift_px": max((max(abs(dx), abs(dy)) for dx, dy in shifts or []), default=0),
    }
    if fit is not None:
        corr = np.asarray(fit.corrections, np.float64)
        out["exposure_corrections"] = [round(float(c), 6) for c in corr]
        out["exposures_refined"] = int(np.count_nonzero(fit.refined))
        worst = int(np.argmax(np.abs(np.log(corr))))
        out["max_exposure_correction"] = float(corr[worst])
        if abs(np.log(corr[worst])) > np.log1p(EXPOSURE_WARN):
            out["warnings"].append(f"exposure {worst + 1} ({fit.labels_s[worst]:.6g} s) acts like "
                                   f"{fit.exposures_s[worst]:.6g} s (x{corr[worst]:.3f}): a nominal label, or the "
                                   "camera changed its gain; fused with the effective exposure")
        if fit.rejected_correction > 1.0:
            out["warnings"].append(f"the pictures asked for an exposure x{fit.rejected_correction:.2f} off its label, "
                                   "beyond belief: are the times in the images' order? the labels were kept")
    most = out["max_shift_px"]
    if not aligned and most >= 2:  # (a pixel is the bitmaps' resolution: tripod stacks show 0-1)
        out["warnings"].append(f"the frames are misregistered by up to {most} px (a hand-held stack?): "
                               "--align registers them")
    if out["saturated_fraction"] > 0.05:
        out["warnings"].append("over 5% of the pixels are saturated even in the shortest exposure: add shorter ones")
    if out["dark_fraction"] > 0.05:
        out["warnings"].append("over 5% of the pixels have no usable sample: add longer exposures")
    if out["deghost_rejected_fraction"] > 0.2:
        out["warnings"].append("the deghosting rejected over 20% of the samples: is the stack static and "
                               "registered? (--no-deghost keeps them)")
    return out


def main(argv: list[str]) -> int:
    from device.core.command import run_command

    ns = _parser().parse_args(argv)
    return run_command(_run, ns)
