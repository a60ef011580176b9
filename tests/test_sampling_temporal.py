"""Temporal behaviour on the simulated scenarios (lightprobe.sim.scenarios), measured as in the benchmark."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from lightprobe.bench.samplers import temporal_metrics, temporal_run
from lightprobe.device.sampling.registry import make_sampler


@pytest.fixture(scope="module")
def flashlight(shared_data: Path) -> dict[str, dict[str, float]]:
    from lightprobe.bench.samplers import _Scenario

    sc = _Scenario("flashlight", 60, shared_data)
    return {m: temporal_metrics(temporal_run(sc, make_sampler(m), 256)) for m in ("pharr", "hemigon")}


def test_flashlight_hemigon_flicker_is_at_most_a_third_of_pharr(
        flashlight: dict[str, dict[str, float]]) -> None:
    """Issue 3 acceptance (measured: Pharr ~0.0036, Hemigon ~0.0010 at N = 256, 60 frames)."""
    print({m: round(v["flicker"], 6) for m, v in flashlight.items()})
    assert flashlight["hemigon"]["flicker"] <= flashlight["pharr"]["flicker"] / 3


def test_flashlight_errors_stay_bounded(flashlight: dict[str, dict[str, float]]) -> None:
    for m, v in flashlight.items():
        assert np.isfinite(v["flicker"]), m
        assert 0 < v["error_mean"] < 0.05, (m, v)
        assert v["toggles"] == 0  # no abrupt change in this scenario


def _spot_map(phi_deg: float) -> np.ndarray:
    from lightprobe.core.sphere import directions_from_angles, equirect_directions

    d = equirect_directions(64)
    img = np.full((64, 128, 3), 0.01, np.float32)
    spot = directions_from_angles(np.radians(60.0), np.radians(phi_deg))
    img[(d @ spot) > np.cos(np.radians(5.0))] = 100.0
    return img


def test_trajectory_filter_reset_prevents_ghost_lights() -> None:
    """A lamp jumps 120 deg between frames: with the reset, lights are at the new lamp at once;
    without it, filtered lights sweep across the sky (ghosts) between old and new place."""
    from lightprobe.core.sphere import directions_from_angles

    new = directions_from_angles(np.radians(60.0), np.radians(150.0))
    power_near_new = {}
    for label, jump in (("reset", 0.05), ("no reset", 1e9)):
        s = make_sampler("hemigon", trajectory_alpha=0.3, trajectory_jump=jump)
        s.sample(_spot_map(30.0), 64)
        ls = s.sample(_spot_map(150.0), 64)
        near = ls.directions @ new > np.cos(np.radians(8.0))
        power_near_new[label] = ls.rgb[near].sum() / ls.rgb.sum()
    print(power_near_new)
    # 95% of the energy is in the new lamp; stratum centroids at its rim and the lower
    # hemisphere's lights sit farther than 8 deg (measured 0.79 with reset)
    assert power_near_new["reset"] > 0.7
    assert power_near_new["no reset"] < 0.1
