"""An exposure stack as ``lightprobe fuse`` and the HDR bench read it: the images and their
times, the stack's own response fit, the merge settings for a response, and the report of what a
fusion did (saturation, dark pixels, misregistration, exposure corrections)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from lightprobe.core.calibration import Calibration, Response
from lightprobe.core.errors import InputError

if TYPE_CHECKING:
    from lightprobe.calibration.response import StackFit
    from lightprobe.device.hdr.fusion import FusionSettings

__all__ = ["EXPOSURE_WARN", "fit_response", "fuse_report", "fusion_settings", "load_response", "parse_time", "read_stack", "read_times_file"]


EXPOSURE_WARN = 0.15  # an exposure that the pictures put this far from its label is reported


def parse_time(text: str) -> float:
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
            out.append(parse_time(table[img.name]))
        return out
    if rows and all(len(r) == 1 for r in rows):
        return [parse_time(r[0]) for r in rows]
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
    (:func:`lightprobe.calibration.response.fit_stack`): fuse the stack with ``fit.exposures_s``."""
    from lightprobe.calibration.response import SMOOTHNESS, fit_stack

    return fit_stack(frames, times, smoothness=SMOOTHNESS if smoothness is None else smoothness,
                     refine_exposures=refine_exposures)


def load_response(path: Path) -> Response:
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


def fusion_settings(response: Response, *, deghost: bool = True) -> FusionSettings:
    """The merge settings for a response: a truth response or one that carries its measured
    scatter (``log_sigma``) lets the deghosting test against the real noise (a small relative
    tolerance); a table without it is only good to a few percent, so the tolerance widens."""
    from lightprobe.device.hdr.fusion import FusionSettings

    exact = response.method == "truth" or response.log_sigma is not None
    return FusionSettings(deghost=deghost, ghost_rel_tol=0.05 if exact else 0.25)


def fuse_report(res: Any, response: Response, source: str, shifts: list[tuple[int, int]] | None = None,
                aligned: bool = False, fit: StackFit | None = None) -> dict[str, Any]:
    """What a fusion did, so a user sees a bad stack for what it is. ``shifts``: each frame's
    registration (:func:`lightprobe.device.hdr.align.stack_shifts`), applied if ``aligned``; ``fit``: the
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

