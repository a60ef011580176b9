"""Q2-Tree quality on the six shared maps at N = 256 (exact, map-based errors).

Measured on this box (medians over the six maps, N = 256, default Q2TreeSampler: integral
importance, centroid placement, nside 256): diffuse 0.00085, occluded 0.0052 (issue: <= 0.002
and <= 0.006). The registry's median cut: diffuse 0.00137, occluded 0.0057 (the issue quotes
about 0.0016 / 0.0057 for a plain median cut, which checks the metric's definition).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from lightprobe.core.imageio import read_hdr_image
from lightprobe.device.sampling.metrics import ErrorReference
from lightprobe.device.sampling.q2tree import Q2TreeSampler
from lightprobe.device.sampling.registry import available_samplers, make_sampler

COUNT = 256
KINDS = ("diffuse", "occluded")


@pytest.fixture(scope="module")
def errors(envmap_paths: dict[str, Path]) -> dict[str, dict[str, list[float]]]:
    variants = {
        "q2tree": Q2TreeSampler,
        "mean": lambda: Q2TreeSampler(importance="mean"),
        "jitter": lambda: Q2TreeSampler(placement="jitter"),
    }
    if "median-cut" in available_samplers():
        variants["median-cut"] = lambda: make_sampler("median-cut")
    out: dict[str, dict[str, list[float]]] = {v: {k: [] for k in KINDS} for v in variants}
    for path in envmap_paths.values():
        img = read_hdr_image(path)
        ref = ErrorReference(img)
        for name, make in variants.items():
            for kind, value in ref.errors(make().sample(img, COUNT), KINDS).items():
                out[name][kind].append(value)
    return out


def _median(errors: dict[str, dict[str, list[float]]], variant: str, kind: str) -> float:
    return float(np.median(errors[variant][kind]))


def test_q2tree_median_errors_at_256(errors: dict[str, dict[str, list[float]]]) -> None:
    assert len(errors["q2tree"]["diffuse"]) == 6
    assert _median(errors, "q2tree", "diffuse") <= 0.002  # measured 0.00085
    assert _median(errors, "q2tree", "occluded") <= 0.006  # measured 0.0052


def test_integral_importance_and_centroid_placement_are_the_better_defaults(
        errors: dict[str, dict[str, list[float]]]) -> None:
    for kind in KINDS:
        assert _median(errors, "q2tree", kind) < 0.5 * _median(errors, "mean", kind)
        assert _median(errors, "q2tree", kind) < _median(errors, "jitter", kind)


def test_q2tree_beats_median_cut(errors: dict[str, dict[str, list[float]]]) -> None:
    if "median-cut" not in errors:
        pytest.fail("median cut sampler not available from the registry")
    for kind in KINDS:
        assert _median(errors, "q2tree", kind) <= _median(errors, "median-cut", kind)
