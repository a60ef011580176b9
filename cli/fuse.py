"""``lightprobe fuse IMG... --times T... [--response FILE] [--align] --out OUT.exr``

Fuses an exposure stack of 8-bit images into a linear HDR image (OpenEXR, float32, metadata
``unit=relative``, ``exposures``, ``exposure_labels``, ``response``, ``saturated_pixels``).
Without ``--response`` the camera response is estimated from the stack itself (Debevec & Malik
1997, :func:`lightprobe.calibration.response.fit_stack`, with the scatter per code the merge weights by),
and so is each frame's effective exposure: shutter labels are nominal (1/15 s for 2^-4 s) and a
phone changes its gain unlabelled, so the frames are fused with the exposures the pictures show
(``exposures``; the given ones are ``exposure_labels``). It reports what it did: the response's
source, the exposure corrections, the frames' misregistration (``--align`` registers a hand-held
stack first, :mod:`lightprobe.device.hdr.align`), the share of samples the deghosting rejected, the
saturated and too-dark fractions, the dynamic range, and warnings for a bad stack. Bad input
(unreadable image, mismatched sizes, missing or non-positive times, count mismatch, frames that
do not get brighter with their times) exits 2 with a one-line message naming the file or value
(CONVENTIONS.md).
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING

from lightprobe.core.errors import InputError

if TYPE_CHECKING:
    pass

__all__ = ["main"]



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
                        "(default: lightprobe.calibration.response.SMOOTHNESS)")
    return p












def _run(ns: argparse.Namespace) -> int:
    from lightprobe.core.imageio import write_exr
    from lightprobe.device.hdr.align import apply_shifts, stack_shifts
    from lightprobe.device.hdr.fusion import fuse
    from lightprobe.device.hdr.stack import (
        fit_response,
        fuse_report,
        fusion_settings,
        load_response,
        parse_time,
        read_stack,
        read_times_file,
    )

    images = [Path(p) for p in ns.images]
    if ns.times is not None and ns.times_file is not None:
        raise InputError("give --times or --times-file, not both", param="--times")
    if ns.times_file is not None:
        times = read_times_file(ns.times_file, images)
    elif ns.times is not None:
        times = [parse_time(t) for t in ns.times]
    else:
        raise InputError("missing exposure times: give --times T... or --times-file FILE", param="--times")
    if len(times) != len(images):
        raise InputError(f"{len(images)} images but {len(times)} exposure times", param="--times")
    if ns.out.suffix.lower() != ".exr":
        raise InputError(f"{ns.out}: output must be an .exr file", param="--out")
    if not ns.out.parent.is_dir():
        raise InputError(f"{ns.out}: folder {ns.out.parent} does not exist", param="--out")
    response = load_response(ns.response) if ns.response is not None else None
    frames = read_stack(images)
    shifts = stack_shifts(frames)
    if ns.align:
        frames = apply_shifts(frames, shifts)
    source = f"{ns.response}" if response is not None else "estimated from the stack"
    fit = None
    if response is not None:  # (the stack's own fit checks this itself)
        from lightprobe.calibration.response import check_brightens

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






def main(argv: list[str]) -> int:
    from lightprobe.core.command import run_command

    ns = _parser().parse_args(argv)
    return run_command(_run, ns)
