"""Named scenarios: a base room map plus dynamic lights, deterministic for a seed.

``load_scene(name_or_path, *, seed=0)`` returns a :class:`lightprobe.sim.scene.Scene`:

========== =================================================================================
room       the base map alone (static).
flashlight a bright flashlight (3 deg disc) carried around the probe at 15-45 deg elevation,
           one turn per 8 s, with a hand's jitter: the Nikodym et al. 2013 test (Fig. 5,
           "the user moves a flashlight around the camera").
flicker    a ceiling fluorescent tube (a row of 5 small discs) whose intensity is modulated at
           twice the mains frequency (100.3 Hz) with 40% depth, a slow phase jitter and a
           0.5 Hz drift: sampled at 30 fps the 100 Hz ripple aliases to a visible ~10 Hz
           flicker (short exposures see it; exposures of 1/100 s multiples average it out).
switch     a lamp (4 deg disc) switched on and off abruptly, every 2-4 s (seeded).
swing      a hanging bulb (2 deg disc) 25 deg from the zenith swinging +-4 deg with a 1.6 s
           period: subtle movement.
daylight   a sun (0.27 deg radius, radiance 1.5e4) moving 0.5 deg per second across the sky.
========== =================================================================================

The base map is ``lebombo_1k.hdr`` from ``<shared_data>/envmaps``; ``shared_data`` defaults to
``../shared/data`` next to the project root (callers may pass the value of the
``LIGHTPROBE_SHARED_DATA`` environment variable; nothing here reads the environment). If that
file is missing, a procedural room (sky gradient, a bright window, a dim floor) is used.
Any path to an equirect ``.hdr`` / ``.exr`` file, or the name of a shared envmap (e.g.
``rooitou_park``), gives a static scene of that map. Unknown names raise InputError.
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable
from pathlib import Path

import numpy as np

from lightprobe.core.errors import InputError

from .optics import direction, equirect_centres
from .scene import DynamicLight, Scene

__all__ = ["SCENARIOS", "default_shared_data", "load_scene", "procedural_room"]

DEFAULT_BASE = "lebombo_1k.hdr"


def _dir(theta: float, phi: float) -> np.ndarray:
    """Probe-frame unit direction of polar angle ``theta`` and azimuth ``phi`` (radians)."""
    return direction(theta, phi)


def default_shared_data() -> Path:
    """``../shared/data`` relative to the project root (the repository checkout)."""
    return Path(__file__).resolve().parent.parent.parent / "shared" / "data"


def procedural_room(height: int = 256) -> np.ndarray:
    """A room without data files: sky-like ceiling gradient, a bright window, a dim floor.

    float32 (H, 2H, 3). Radiance: ceiling 0.3 .. 1.0, window 8, floor 0.15.
    """
    d = equirect_centres(height)
    y = d[..., 1]
    img = np.empty(d.shape, np.float32)
    up = np.clip(y, 0, 1)[..., None]
    img[:] = 0.3 + 0.7 * up * np.array([0.9, 0.95, 1.0])
    img[y < 0] = np.array([0.15, 0.13, 0.11], np.float32)
    win_dir = _dir(np.deg2rad(70.0), np.deg2rad(120.0))
    img[(d @ win_dir) > math.cos(np.deg2rad(12.0))] = np.array([8.0, 8.0, 7.5], np.float32)
    return img


def _base_scene(name: str, shared: Path, base: str | None) -> Scene:
    path = shared / "envmaps" / (base or DEFAULT_BASE)
    if path.is_file():
        return Scene.from_file(path, name=name)
    if base is not None:
        raise InputError(f"{path}: base map not found", param="base")
    return Scene(procedural_room(), name=name)


def _fixed(d: np.ndarray) -> Callable[[float], np.ndarray]:
    """A constant direction as a function of time."""
    return lambda t: d


def _smooth_noise(rng: np.random.Generator, terms: int = 4, fmax: float = 1.5
                  ) -> Callable[[float], float]:
    """A smooth, deterministic function of time in about [-1, 1]: a sum of random sinusoids."""
    f = rng.uniform(0.2, fmax, terms)
    ph = rng.uniform(0, 2 * math.pi, terms)
    amp = rng.uniform(0.5, 1.0, terms)
    amp /= amp.sum()
    return lambda t: float(np.sum(amp * np.sin(2 * math.pi * f * t + ph)))


def _flashlight(scene: Scene, rng: np.random.Generator) -> None:
    jit_t, jit_p = _smooth_noise(rng), _smooth_noise(rng)
    phase = float(rng.uniform(0, 2 * math.pi))

    def direction(t: float) -> np.ndarray:
        # One turn around the probe per 8 s, elevation 15..45 deg, hand jitter ~1 deg
        phi = phase + 2 * math.pi * t / 8.0 + np.deg2rad(1.0) * jit_p(t)
        elev = 30.0 + 15.0 * math.sin(2 * math.pi * t / 5.0) + 1.0 * jit_t(t)
        return _dir(np.deg2rad(90.0 - elev), phi)

    scene.lights.append(DynamicLight("flashlight", np.deg2rad(3.0), (600.0, 570.0, 500.0), direction))


def _flicker(scene: Scene, rng: np.random.Generator) -> None:
    f = 2 * 50.15  # twice the mains frequency (slightly off nominal)
    jitter = _smooth_noise(rng, fmax=0.8)
    phase0 = float(rng.uniform(0, 2 * math.pi))

    def intensity(t: float) -> float:
        # 100 Hz ripple (40% depth) with phase jitter and a slow 0.5 Hz drift of the mean
        ph = 2 * math.pi * f * t + phase0 + 0.6 * jitter(t)
        return (1.0 + 0.05 * math.sin(2 * math.pi * 0.5 * t)) * (1.0 + 0.4 * math.cos(ph))

    az = float(rng.uniform(0, 2 * math.pi))
    for i in range(5):  # a tube 5 small discs long across the ceiling
        d = _dir(np.deg2rad(35.0), az) + (i - 2) * 0.06 * _dir(np.pi / 2, az + np.pi / 2)
        scene.lights.append(DynamicLight(f"tube{i}", np.deg2rad(1.5), (220.0, 240.0, 230.0),
                                         _fixed(d), intensity))


def _switch(scene: Scene, rng: np.random.Generator) -> None:
    toggles = np.cumsum(rng.uniform(2.0, 4.0, 512))  # on at t < toggles[0], then alternating
    direction = _dir(np.deg2rad(55.0), float(rng.uniform(0, 2 * math.pi)))

    def intensity(t: float) -> float:
        return 1.0 if int(np.searchsorted(toggles, t, side="right")) % 2 == 0 else 0.0

    scene.lights.append(DynamicLight("lamp", np.deg2rad(4.0), (300.0, 270.0, 220.0),
                                     _fixed(direction), intensity))


def _swing(scene: Scene, rng: np.random.Generator) -> None:
    az = float(rng.uniform(0, 2 * math.pi))

    def direction(t: float) -> np.ndarray:
        return _dir(np.deg2rad(25.0 + 4.0 * math.sin(2 * math.pi * t / 1.6)), az)

    scene.lights.append(DynamicLight("bulb", np.deg2rad(2.0), (800.0, 700.0, 520.0), direction))


def _daylight(scene: Scene, rng: np.random.Generator) -> None:
    az0 = float(rng.uniform(0, 2 * math.pi))

    def direction(t: float) -> np.ndarray:
        # An arc from 20 deg elevation through 60 deg; 0.5 deg per second of virtual time
        s = np.deg2rad(0.5) * t
        return _dir(np.deg2rad(70.0) - 0.7 * math.sin(s), az0 + s)

    scene.lights.append(DynamicLight("sun", np.deg2rad(0.27), (1.5e4, 1.45e4, 1.35e4), direction))


UNIFORM = "uniform"
SCENARIOS: dict[str, Callable[[Scene, np.random.Generator], None] | None] = {
    "room": None,
    "flashlight": _flashlight,
    "flicker": _flicker,
    "switch": _switch,
    "swing": _swing,
    "daylight": _daylight,
}


def load_scene(name_or_path: str | os.PathLike[str], *, seed: int = 0,
               shared_data: str | os.PathLike[str] | None = None, base: str | None = None,
               scale: float = 1.0) -> Scene:
    """A scene by scenario name, shared envmap name, or equirect file path.

    Parameters
    ----------
    name_or_path : a key of :data:`SCENARIOS`, ``"uniform"`` (an integrating sphere, radiance 1
        everywhere: the flat field of the vignetting calibration), a file in ``<shared_data>/envmaps`` (with or
        without the ``.hdr``/``.exr`` suffix or ``_1k``), or a path to an equirect map.
    seed : seeds the scenario's random path, phases and switching times.
    shared_data : the shared data folder (default :func:`default_shared_data`).
    base : file name of the base map in ``envmaps/`` for named scenarios.
    scale : global radiance scale.
    """
    shared = Path(shared_data) if shared_data is not None else default_shared_data()
    key = str(name_or_path)
    if key == UNIFORM:  # an integrating sphere: radiance 1 everywhere (flat-field calibration)
        return Scene(np.ones((32, 64, 3), np.float32), name=UNIFORM, scale=float(scale))
    if key in SCENARIOS:
        scene = _base_scene(key, shared, base)
        build = SCENARIOS[key]
        if build is not None:
            build(scene, np.random.default_rng(seed))
        scene.scale = float(scale)
        return scene
    p = Path(key)
    candidates = [p] + [shared / "envmaps" / f"{key}{s}" for s in ("", ".hdr", "_1k.hdr", ".exr")]
    for c in candidates:
        if c.is_file():
            return Scene.from_file(c, scale=scale)
    if p.suffix.lower() in (".hdr", ".exr", ".pic"):
        raise InputError(f"{p}: no such scene file", param="scene")
    valid = ", ".join([*SCENARIOS, UNIFORM])
    raise InputError(f"unknown scene {key!r}: use one of {valid}, a shared envmap name or an "
                     ".hdr/.exr path", param="scene")
