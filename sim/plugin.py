"""The simulator's camera plugins (entry points of the ``lightprobe.cameras`` group).

``--camera sim`` is :class:`lightprobe.sim.camera.SimCamera` on a scene (``scene``: a scenario name or an
equirect map path, default ``flashlight``; ``cache_dir``: where its lens matrices are kept);
``--camera v4l2-fake`` is the real V4L2 driver over :class:`lightprobe.sim.v4l2_fake.FakeV4L2Node`, a fake
UVC kernel. Production code never imports this module: ``lightprobe.drivers.discovery.open_camera`` finds
it through ``pyproject.toml``'s entry points when a user names the kind.
"""

from __future__ import annotations

import os
from typing import Any

from lightprobe.drivers.base import Camera

__all__ = ["fake_v4l2_camera", "sim_camera"]


def sim_camera(arg: str = "", *, scene: str | None = None,
               cache_dir: str | os.PathLike[str] | None = None, **options: Any) -> Camera:
    """``--camera sim``: the simulated probe on ``scene`` (InputError names a bad scene), paced
    at its frame rate as a sensor is (``realtime=False`` runs it as fast as it renders)."""
    from .camera import SimCamera
    from .scenarios import load_scene

    seed = int(options.pop("seed", 0))
    options.setdefault("realtime", True)
    return SimCamera(load_scene(scene or "flashlight", seed=seed), seed=seed, cache_dir=cache_dir,
                     **options)


def fake_v4l2_camera(arg: str = "", **_: Any) -> Camera:
    """``--camera v4l2-fake``: the real V4L2 driver over the fake UVC kernel, with the fake
    module's factory calibration."""
    from .v4l2_fake import FakeUVCCamera

    return FakeUVCCamera()
