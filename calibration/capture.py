"""Captures for the calibration routines when the probe itself is the source (``--camera SPEC``).

The camera is any :class:`lightprobe.drivers.base.Camera` (``lightprobe calibrate`` gets it from the one
factory, :func:`lightprobe.device.bootstrap.open_cli_camera`; for the simulator the scene ``uniform``
is a flat field, an integrating sphere). Each routine opens the camera, captures through the
driver protocol (metadata-verified exposures, :func:`lightprobe.calibration.response.capture_bracket`) and
closes it:

- :func:`sweep_bracket`: a metering sweep, one stop apart, from the first exposure where
  anything shows to the first where most of the frame is saturated (the response solve needs
  the whole code range);
- :func:`capture_flat_field`: a linear flat-field image, averaged over frames, in a raw mode of
  the same size when the camera has one (else linearised with a response);

The photometric routine's map (one HDR burst through the whole pipeline) is captured by the
command layer (:func:`lightprobe.device.bootstrap.capture_map`): the pipeline stands above calibration.

Dtype policy: frames as the driver gives them (uint8 / uint16); linear images float64.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from lightprobe.core.calibration import Response
from lightprobe.core.errors import InputError
from lightprobe.drivers.base import Camera, CameraError, Frame, PixelFormat

from .response import capture_bracket

__all__ = ["capture_flat_field", "sweep_bracket"]


async def _open(camera: Camera, spec: str) -> None:
    try:
        await camera.open()
    except CameraError as e:
        raise InputError(f"--camera {spec}: cannot open ({e})", param="--camera") from e


def _code_level(frame: Frame, q: float) -> float:
    """The ``q`` quantile of a frame as a fraction of its range (0 = black, 1 = saturated)."""
    lo, hi = (0.0, 255.0) if frame.format is PixelFormat.RGB8 else (frame.black_level, frame.white_level)
    return (float(np.quantile(frame.data, q)) - lo) / max(hi - lo, 1.0)


async def sweep_bracket(camera: Camera, spec: str, exposures: Sequence[float] | None = None, *,
                        max_frames: int = 16) -> tuple[list[Frame], list[float]]:
    """A static-scene bracket: ``exposures`` if given, else the metering sweep (module docs)."""
    await _open(camera, spec)
    try:
        if exposures:
            frames = await capture_bracket(camera, list(exposures))
            return frames, [float(t) for t in exposures]
        lo, hi = camera.capabilities.exposure_range
        t = max(lo, 1e-5)
        frames, times = [], []
        while t <= hi and len(frames) < max_frames:
            f = (await capture_bracket(camera, [t]))[0]
            if frames or _code_level(f, 0.999) > 0.06:  # something shows: start keeping frames
                frames.append(f)
                times.append(t)
                if _code_level(f, 0.5) >= 0.98:  # most of the frame saturated: done
                    break
            t *= 2.0
        if len(frames) < 2:
            raise InputError(f"--camera {spec}: the scene is too dark or too bright for a bracket "
                             f"in {lo:g}..{hi:g} s", param="--camera")
        return frames, times
    finally:
        await camera.close()


async def capture_flat_field(camera: Camera, spec: str, *, frames: int = 4,
                             response: Response | None = None) -> np.ndarray:
    """Linear flat field (H, W, 3) float64 (1 = saturation): raw mode when available, else the
    processed output linearised through ``response``; metered so its 99th percentile sits near
    70% of the range."""
    await _open(camera, spec)
    try:
        mode = camera.mode
        raw = [m for m in camera.capabilities.modes if m.format is not PixelFormat.RGB8
               and (m.width, m.height) == (mode.width, mode.height)]
        if mode.format is PixelFormat.RGB8 and raw:
            await camera.set_mode(raw[0])
        elif mode.format is PixelFormat.RGB8 and response is None:
            raise InputError(f"--camera {spec}: no raw mode; calibrate the response first "
                             "(lightprobe calibrate response --camera ...)", param="--camera")
        lo, hi = camera.capabilities.exposure_range
        t = float(np.clip(1.0 / 60.0, lo, hi))
        for _ in range(8):  # meter
            level = _code_level((await capture_bracket(camera, [t]))[0], 0.99)
            if 0.5 <= level <= 0.85:
                break
            t = float(np.clip(t * (0.25 if level >= 0.98 else 0.7 / max(level, 0.01)), lo, hi))
        f = (await capture_bracket(camera, [t], frames_per_exposure=frames))[0]
    finally:
        await camera.close()
    if f.format is PixelFormat.RGB8:
        assert response is not None
        inv = response.inverse
        return np.stack([inv[f.data[..., c].astype(np.int64), c] for c in range(3)], axis=-1)
    return (f.data.astype(np.float64) - f.black_level) / (f.white_level - f.black_level)
