"""The simulator's camera plugins (entry points of the ``lightprobe.cameras`` group).

``--camera sim`` is :class:`lightprobe.sim.camera.SimCamera` on a scene (``scene``: a scenario name or an
equirect map path, default ``flashlight``). Its lens matrices are the simulator's, not the unit's:
they are kept in the user's cache (``$LIGHTPROBE_SIM_CACHE``, default
``$XDG_CACHE_HOME/lightprobe/sim`` or ``~/.cache/lightprobe/sim``), built once per lens and map
size like compiled kernels, and shared by every state directory; the service's ``cache_dir``
(the state directory's) is used only when that cache cannot be written. So a fresh state
directory starts the probe as a unit would, without the simulator's own build (~2 s at VGA);
``--camera v4l2-fake`` is the real V4L2 driver over :class:`lightprobe.sim.v4l2_fake.FakeV4L2Node`, a fake
UVC kernel. Production code never imports this module: ``lightprobe.drivers.discovery.open_camera`` finds
it through ``pyproject.toml``'s entry points when a user names the kind.
"""

from __future__ import annotations

import os
from typing import Any

from lightprobe.drivers.base import Camera

__all__ = ["fake_v4l2_camera", "sim_cache_dir", "sim_camera"]


def sim_camera(arg: str = "", *, scene: str | None = None,
               cache_dir: str | os.PathLike[str] | None = None, **options: Any) -> Camera:
    """``--camera sim``: the simulated probe on ``scene`` (InputError names a bad scene), paced
    at its frame rate as a sensor is (``realtime=False`` runs it as fast as it renders)."""
    from .camera import SimCamera
    from .scenarios import load_scene

    seed = int(options.pop("seed", 0))
    options.setdefault("realtime", True)
    return SimCamera(load_scene(scene or "flashlight", seed=seed), seed=seed, cache_dir=sim_cache_dir(cache_dir),
                     **options)


def sim_cache_dir(fallback: str | os.PathLike[str] | None = None) -> str | os.PathLike[str] | None:
    """The simulator's lens-matrix cache (module docstring), or ``fallback`` if it cannot be made."""
    root = os.environ.get("LIGHTPROBE_SIM_CACHE") or os.path.join(
        os.environ.get("XDG_CACHE_HOME") or os.path.expanduser("~/.cache"), "lightprobe", "sim")
    try:
        os.makedirs(root, exist_ok=True)
    except OSError:
        return fallback
    return root if os.access(root, os.W_OK) else fallback


def fake_v4l2_camera(arg: str = "", **_: Any) -> Camera:
    """``--camera v4l2-fake``: the real V4L2 driver over the fake UVC kernel, with the fake
    module's factory calibration."""
    from .v4l2_fake import FakeUVCCamera

    return FakeUVCCamera()
