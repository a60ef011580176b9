"""The wiring of a probe, in one place: the camera, calibration and pipeline factories that
``lightprobe serve``, ``lightprobe run-pipeline`` and the calibration captures use.

- cameras: :func:`lightprobe.drivers.discovery.open_camera` (the one camera factory; the simulator is a
  plugin a user names, never a fallback), wrapped by :func:`camera_factory` for the service (made
  off the event loop, retried while absent) and by :func:`open_cli_camera` for commands (a
  missing camera is exit 2);
- calibrations: :func:`lightprobe.calibration.store.load_calibration` (store, then ``calibration.json``,
  then the camera's own);
- pipelines: :class:`PipelineFactory` builds :class:`lightprobe.device.pipeline.Pipeline` from the service
  config and reconfigures it in place; :func:`capture_map` runs one burst through it for the
  photometric calibration.

Nothing here runs at import.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from lightprobe.core.calibration import Calibration
from lightprobe.core.errors import InputError
from lightprobe.drivers.base import Camera, CameraError

__all__ = ["PipelineFactory", "camera_factory", "capture_map", "open_cli_camera", "pipeline_factory"]


def camera_factory(spec: str, scene: str | None = None, cache_dir: Path | None = None) -> Callable[[], Camera]:
    """``make()`` -> an unopened camera for ``--camera spec`` (plugins get ``scene`` and
    ``cache_dir``: the simulator keeps its lens tables there). A malformed spec raises
    InputError; absent hardware :class:`lightprobe.drivers.base.CameraUnavailable` (the service retries)."""
    from lightprobe.drivers.discovery import parse_spec

    parse_spec(spec)  # a malformed --camera fails now, at the command line

    def make() -> Camera:
        from lightprobe.drivers.discovery import open_camera

        return open_camera(spec, scene=scene, cache_dir=cache_dir)

    return make


def open_cli_camera(spec: str, scene: str | None = None, **options: Any) -> Camera:
    """An unopened camera for a command's ``--camera``: every failure is an InputError naming
    ``--camera`` (exit 2), a missing camera included. ``options`` go to the camera (a replay's
    ``pace``, ``loop``)."""
    try:
        if options:
            from lightprobe.drivers.discovery import open_camera, parse_spec

            parse_spec(spec)
            return open_camera(spec, scene=scene, **options)
        return camera_factory(spec, scene)()
    except InputError as e:
        raise InputError(f"--camera {spec}: {e}", param=e.param or "--camera") from e
    except (CameraError, ValueError, OSError) as e:
        raise InputError(f"--camera {spec}: {e}", param="--camera") from e


class PipelineFactory:
    """Builds ``lightprobe.device.pipeline.Pipeline`` from the service config; reconfigures it in place."""

    def __init__(self, state_dir: Path, probe_id: str) -> None:
        self.state_dir, self.probe_id = state_dir, probe_id

    def pipeline_config(self, cfg: Any, camera: Camera | None = None) -> Any:
        """The pipeline's settings from the service config. A camera whose frames are (or will
        be) a recording starts on its full tables (``staged_start`` off): the frame the balanced
        table comes in on would depend on the machine's speed, and a replay must give the
        recorded run's light sets bit for bit."""
        from lightprobe.device.pipeline import PipelineConfig
        from lightprobe.drivers.recording import RecordingCamera
        from lightprobe.drivers.replay import ReplayCamera

        return PipelineConfig(fps=cfg.get("pipeline", "fps"), sampler=cfg.get("pipeline", "sampler"),
                              light_count=cfg.get("pipeline", "light_count"),
                              max_exposures=cfg.get("pipeline", "max_exposures"),
                              equirect_height=cfg.get("pipeline", "equirect_height"),
                              nside=cfg.get("pipeline", "nside"), probe_id=self.probe_id,
                              cache_dir=str(self.state_dir / "cache"),
                              staged_start=not isinstance(camera, (RecordingCamera, ReplayCamera)))

    def __call__(self, camera: Camera, cfg: Any) -> Any:
        from lightprobe.calibration.store import load_calibration
        from lightprobe.device.pipeline import Pipeline
        from lightprobe.drivers.recording import RecordingCamera
        from lightprobe.drivers.replay import ReplayCamera

        # a replay runs on the calibration its recording was made with, whatever the state dir has
        recorded = camera.factory_calibration() if isinstance(camera, ReplayCamera) else None
        calibration = recorded if recorded is not None else load_calibration(self.state_dir, camera)
        if isinstance(camera, RecordingCamera):  # on what the recording holds: its JSON (rounded)
            calibration = Calibration.from_json(calibration.to_json())
            camera.calibration_json = calibration.to_json()
        return Pipeline(camera, calibration, self.pipeline_config(cfg, camera))

    def reconfigure(self, pipeline: Any, cfg: Any) -> None:
        pipeline.reconfigure(self.pipeline_config(cfg, pipeline.camera))


def pipeline_factory(state_dir: Path, probe_id: str) -> PipelineFactory:
    return PipelineFactory(state_dir, probe_id)


async def capture_map(camera: Camera, spec: str, calibration: Calibration, *, bursts: int = 2,
                      equirect_height: int = 128) -> np.ndarray:
    """Equirect map (H, 2H, 3) float32 of the last of ``bursts`` HDR bursts, fused and projected
    with ``calibration`` minus its photometric scale (the probe's raw relative unit): what the
    photometric calibration holds against a lux meter."""
    from lightprobe.device.pipeline import Pipeline, PipelineConfig

    if calibration.fisheye is None or calibration.response is None:
        raise InputError("a map needs a fisheye and a response calibration (in --out or --state)",
                         param="--camera")
    pipe = Pipeline(camera, calibration.with_(photometric=None),
                    PipelineConfig(equirect_height=equirect_height, light_count=16))
    try:
        await pipe.start()
    except CameraError as e:
        raise InputError(f"--camera {spec}: cannot open ({e})", param="--camera") from e
    try:
        result: Any = None
        for _ in range(max(bursts, 1)):
            result = await pipe.step()
        return np.asarray(result.equirect, np.float32)
    finally:
        await pipe.stop()

