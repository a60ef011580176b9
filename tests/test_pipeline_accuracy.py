"""Live on the board (issue 14), in sensor time: light sets at the sensor's frame rate, at the
accuracy of the published lights against the simulator's truth, changes within two frames.

For each shared map and the ``flashlight``, ``switch`` and ``daylight`` scenarios the pipeline
runs as the service drives it (one ``Pipeline.step`` per sensor frame, 256 Q2-Tree lights, the
simulator's 30 fps mode, not paced: sensor time, deterministic), and
:func:`lightprobe.bench.live.measure` scores every evaluated frame after the bracket settles (40 frames):
the diffuse irradiance and glossy errors of the published lights against the true map at that
frame's time (relative RMSE over 128 upward normals, the samplers' metrics). Figures go to
``test-artifacts/pipeline_accuracy.json``; ``lightprobe bench live`` has the same per scene.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

from lightprobe.bench.live import measure
from tests.conftest import ENVMAP_NAMES

pytestmark = pytest.mark.slow

_RESULTS: dict[str, dict[str, Any]] = {}


def _record(name: str, res: dict[str, Any], artifacts_dir: Path) -> None:
    _RESULTS[name] = {k: v for k, v in res.items() if k != "per_frame"}
    (artifacts_dir / "pipeline_accuracy.json").write_text(json.dumps(_RESULTS, indent=1))


@pytest.mark.parametrize("name", ENVMAP_NAMES)
def test_every_frame_publishes_accurate_lights_on_the_shared_maps(name: str, shared_data: Path,
                                                                  artifacts_dir: Path) -> None:
    res = measure(str(shared_data / "envmaps" / name), frames=100, every=2)
    _record(name, res, artifacts_dir)
    assert res["sets_per_sensor_s"] >= 25, res
    assert res["diffuse"]["max"] <= 0.01, res["diffuse"]
    assert res["glossy"]["max"] <= 0.03, res["glossy"]


def test_daylight_sun_is_published_at_its_energy_every_frame(artifacts_dir: Path) -> None:
    """A sun far brighter than anything the camera can expose for, smaller than an output pixel
    and moving: measured only by the shortest exposure, censored in every other. 300 frames,
    every one scored: the sun's energy from one short frame scatters by +-0.5% of the map, and
    before the tracker filtered it one frame in 300 went over 1% (frame 291, 1.02%)."""
    res = measure("daylight", frames=300, every=1)
    _record("daylight", res, artifacts_dir)
    assert res["sets_per_sensor_s"] >= 25, res
    assert res["diffuse"]["max"] <= 0.01, res["diffuse"]
    assert res["glossy"]["max"] <= 0.03, res["glossy"]


def test_a_switched_lamp_is_in_the_published_lights_within_two_frames(artifacts_dir: Path) -> None:
    res = measure("switch", frames=300, every=6)
    _record("switch", res, artifacts_dir)
    lags = res["switch_lags_frames"]
    assert len(lags) >= 2, lags  # on and off at least once each after the bracket settled
    assert all(lag is not None and lag <= 2 for lag in lags), lags
    assert res["sets_per_sensor_s"] >= 25, res
    # between switches the lights are as accurate as on a static map
    assert res["diffuse"]["max"] <= 0.01, res["diffuse"]
    assert res["glossy"]["max"] <= 0.03, res["glossy"]


def test_the_published_flashlight_follows_within_one_frame(artifacts_dir: Path) -> None:
    """A 600:1 flashlight carried around the probe at 40 degrees a second: the published
    flashlight is where the true one was at most one frame earlier, every frame; its energy is
    kept (a long exposure sees it only saturated: the lamp tracker draws it where its measured
    velocity puts it, ``lightprobe.device.hdr.tracking``). Diffuse within 1% and glossy within 3% on every
    scored frame, the lamp's crossing of the map's 0 / 2 pi seam (frames 230-245) included
    (every frame of 300: 0.80% / 2.81% max; without the tracker 1.19% / 11.6% over 160)."""
    res = measure("flashlight", frames=260, every=2)
    _record("flashlight", res, artifacts_dir)
    lags = res["flashlight_lags_frames"]
    assert None not in lags, lags
    assert max(lags) <= 1, lags
    assert res["sets_per_sensor_s"] >= 25, res
    assert res["diffuse"]["max"] <= 0.01, res["diffuse"]
    assert res["glossy"]["max"] <= 0.03, res["glossy"]
