"""End-to-end accuracy (issue 4): the pipeline's published lights against the true map.

Each shared map is the simulator's scene; after the metering sweep and one planned burst, the
published 256 Q2-Tree lights give the diffuse irradiance at 128 upward-facing normals
(Fibonacci, n_y > 0), compared with the exact pixel sum of the true map's upper hemisphere.
Figures are written to ``test-artifacts/pipeline_accuracy.json``.
"""

from __future__ import annotations

import asyncio
import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from device.pipeline import Pipeline, PipelineConfig
from device.sampling.metrics import ErrorReference, fibonacci_normals
from sim.camera import SimCamera
from tests.conftest import ENVMAP_NAMES

pytestmark = pytest.mark.slow

_RESULTS: dict[str, dict[str, Any]] = {}


async def _measure(name: str, shared_data: Path) -> dict[str, Any]:
    cam = SimCamera(str(shared_data / "envmaps" / name), seed=7)
    pipe = Pipeline(cam, cam.truth_calibration(), PipelineConfig(sampler="q2tree", light_count=256))
    await pipe.start()
    try:
        await pipe.step()  # metering sweep
        r = await pipe.step()
    finally:
        await pipe.stop()
    truth = cam.truth_radiance().astype(np.float32)
    truth[truth.shape[0] // 2:] = 0.0  # the upper hemisphere
    normals = fibonacci_normals(256)
    normals = normals[normals[:, 1] > 0]
    ref = ErrorReference(truth, normals)
    e_true = ref.truth("diffuse")
    e_lights = ref.approx("diffuse", r.lights)
    scale = float(e_true @ e_lights / (e_lights @ e_lights))  # least-squares global scale
    rel = np.abs(scale * e_lights - e_true) / e_true
    return {"map": name, "scale": scale, "max_rel_err_after_scale": float(rel.max()),
            "median_rel_err_after_scale": float(np.median(rel)),
            "max_rel_err_unscaled": float((np.abs(e_lights - e_true) / e_true).max()),
            "exposures": r.exposures, "saturated_fraction": r.saturated_fraction}


@pytest.mark.parametrize("name", ENVMAP_NAMES)
def test_published_lights_match_the_true_map(name: str, shared_data: Path, artifacts_dir: Path) -> None:
    res = _RESULTS[name] = asyncio.run(_measure(name, shared_data))
    (artifacts_dir / "pipeline_accuracy.json").write_text(json.dumps(_RESULTS, indent=1))
    assert res["max_rel_err_after_scale"] <= 0.03, res
    assert abs(res["scale"] - 1) <= 0.05, res
