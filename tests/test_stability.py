"""A static scene's published lighting holds still, from the first set on (issue 43), in sensor
time (deterministic): every shared map and synthetic suns of one map pixel (1e4-1e6 times the
sky, 12-85 degrees high), 420 frames each from a cold start (the metering sweep, the coarse projection table and
its balanced replacement, every replan), longer than a planner period: the bracket is replanned
every cycle and keeps the brightest level of the last 10 s (300 frames), whose expiry made the
published energy of a sun scene dip for 16 frames every ~345 frames before the planner read the
sun's peak from the sensor's pixels. Scored by :mod:`lightprobe.bench.stability` (``lightprobe
bench stability`` runs 3,600 frames per scene); figures to ``test-artifacts/stability.json``.
The last test holds the published energy through a camera reconnect and a calibration reload
(wall time, the service in-process).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

from lightprobe.bench.stability import SUNS, figures, record, sun_scene
from tests.conftest import ENVMAP_NAMES

pytestmark = pytest.mark.slow

FRAMES = 420
_RESULTS: dict[str, dict[str, Any]] = {}


def _scene(name: str, shared_data: Path, tmp_path: Path) -> str:
    if name in SUNS:
        return sun_scene(name, tmp_path)
    return str(shared_data / "envmaps" / name)


@pytest.mark.parametrize("name", [*ENVMAP_NAMES, *SUNS])
def test_a_static_scene_publishes_steady_lighting_from_the_first_set(name: str, shared_data: Path, tmp_path: Path,
                                                                     artifacts_dir: Path) -> None:
    f = figures(record(_scene(name, shared_data, tmp_path), FRAMES))
    _RESULTS[name] = f
    (artifacts_dir / "stability.json").write_text(json.dumps(_RESULTS, indent=1))
    # settling is a start-up state: only the first second's sets may be marked ...
    assert f["last_settling_frame"] is None or f["last_settling_frame"] < 30, f
    # ... and every unmarked set is within 3% of the steady state, the first one too
    assert abs(f["first_unmarked_set"] - 1) <= 0.03, f
    assert f["worst_unmarked_first_second"] <= 0.03, f
    # steady: no excursion over 1%, frame-to-frame p99 <= 0.5%, no creep over 0.5%
    assert f["largest_excursion"] <= 0.01, f
    assert f["f2f_p99"] <= 0.005, f
    assert abs(f["creep"]) <= 0.005, f
    # the first unmarked set is right, not only steady: diffuse irradiance within 1% of the truth
    assert f["first_unmarked_diffuse"] <= 0.01, f


def test_the_published_energy_holds_through_a_reconnect_and_a_calibration_reload(shared_data: Path,
                                                                                 tmp_path: Path) -> None:
    """The service in-process on a sun map (wall time): a 1 s camera disconnect, then the
    pipeline rebuilt from the stored calibration (what a committed calibration does). The sets
    after each are marked while they are not yet right (``stale`` while the camera is away,
    ``settling`` through the rebuilt pipeline's metering sweep and first planned cycle) and
    every other one is close to the level before (its noise: 0.29-0.41% at most over a window
    before the events; measured after the reconnect 0.22-0.35%, after the reload 0.19-0.31% on a
    quiet machine, 1.38% once under CI's load), the median within 0.3%."""
    from lightprobe.bench.stability import handover_record

    res = handover_record(str(shared_data / "envmaps" / "rooitou_park_1k.hdr"), tmp_path / "state", window_s=4.0)
    print(json.dumps(res))
    assert res["before_sets"] > 30, res
    for event in ("reconnect", "reload"):
        r = res[event]
        assert r["fresh_sets"] > 30, res
        assert r["stale_sets"] >= 1, res  # the gap is marked, not hidden
        # a reconnect keeps the estimate: within twice the noise; a reload rebuilds it: its first
        # unmarked sets are off by what the first cycle measured (quiet 0.19-0.31%; 1.38% once
        # in CI on a loaded machine, whose dropped frames the sweep and first cycle miss)
        assert r["max_dev"] <= (min(0.01, 2.0 * res["noise_max_dev"]) if event == "reconnect" else 0.015), res
        assert abs(r["median_shift"]) <= 0.003, res
