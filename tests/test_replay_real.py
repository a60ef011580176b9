"""The live pipeline on real photographs (issue 45): each real exposure stack of ``../shared/data``
made a recording (``lightprobe record --stack``), replayed as a camera for 300 frames, against
the offline fusion of the same stack (``lightprobe fuse``'s method) projected with the same
calibration.

The camera that took these stacks is not a fisheye: the calibration is a pinhole of 60 degrees
across (written here from its formula, ``r = f tan(theta)``, as the KB4 series of ``tan``), so
the projection covers a sixth of the upper hemisphere and the rest is unseen: the light sets say
so (``seen``), and the comparison is over the pixels the lens sees whole. The response is the
stack's own (Debevec-Malik with the exposures the pictures show, as ``lightprobe fuse`` does
without ``--response``), and the recording's exposures are those effective exposures.

Targets: after 300 frames the published map's energy within 2% of the offline fusion's (the
median of the last 30 frames; every one of them within 3%: one frame a cycle reads piccante's
lamp 2.6% high), and its per-pixel log difference (median, after the global scale) within the
offline method's own even/odd disagreement (the even and the odd exposures fused apart). Met on
piccante's desk lamp and make-hdr's living room, and per pixel on pku's campus. pku's energy is
not (1.22-1.25 x): its hand-held phone photographs disagree with one another in level, which no
one response describes. Alone, the 1/2024 s photograph reads 1.23-1.28 x the full fusion however
many of its dark codes are dropped; the 1/17241-1/71429 s ones read 1.28-1.52 x, of which their
codes 0-8 (a phone's tone curve puts code 8 at 9% of mid-grey) are a quarter: without them,
0.98-1.06 x. The offline fusion of the very six photographs the live bracket uses gives 1.04 x,
weighing them pixel by pixel; the live merge weighs output pixels (a footprint with a clipped
sample gives a bound, not a measurement, so that a sun keeps its energy) and reads 1.24 x. That part
is ``xfail(strict=True)``: the day it passes, the test says so.
"""

from __future__ import annotations

import asyncio
import json
import math
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
FRAMES = 300


def _pinhole(w: int, h: int, hfov_deg: float = 60.0) -> Any:
    from lightprobe.core.calibration import FisheyeModel

    f = (w / 2) / math.tan(math.radians(hfov_deg) / 2)
    corner = math.degrees(math.atan(math.hypot(w / 2, h / 2) / f))
    # KB4 theta_d = theta (1 + k1 theta^2 + ...): tan's series, 1/3, 2/15, 17/315, 62/2835
    return FisheyeModel(image_size=(w, h), K=np.array([[f, 0, (w - 1) / 2], [0, f, (h - 1) / 2], [0, 0, 1.0]]),
                        D=np.array([1 / 3, 2 / 15, 17 / 315, 62 / 2835]), fov_deg=2 * corner + 2.0)


def _run(stack: str, shared_data: Path, tmp: Path) -> dict[str, Any]:
    import cv2

    from lightprobe.bench.hdr import load_stack
    from lightprobe.core.calibration import Calibration
    from lightprobe.core.sphere import equirect_solid_angle, luminance
    from lightprobe.device.hdr.fusion import fuse
    from lightprobe.device.hdr.quality import subset_consistency
    from lightprobe.device.hdr.stack import fit_response, fusion_settings
    from lightprobe.device.pipeline import Pipeline, PipelineConfig
    from lightprobe.device.projection import Projector
    from lightprobe.drivers.replay import ReplayCamera

    frames, times = load_stack(shared_data, stack, max_width=640)
    h, w = frames[0].shape[:2]
    fit = fit_response(frames, times)
    cal = Calibration(fisheye=_pinhole(w, h), response=fit.response, source="pinhole, the stack's own response")
    cal = Calibration.from_json(cal.to_json())  # what the file holds
    (tmp / "cal.json").write_text(json.dumps(cal.to_json()))
    paths = []
    for i, fr in enumerate(frames):  # lossless copies of the downscaled photographs
        paths.append(str(tmp / f"{i:02d}.png"))
        cv2.imwrite(paths[-1], np.ascontiguousarray(fr[..., ::-1]))
    rec = tmp / f"{stack}.lprec"
    r = subprocess.run([sys.executable, "-m", "lightprobe.cli", "record", "--stack", *paths,
                        "--times", *[repr(float(t)) for t in fit.exposures_s], "--calibration", str(tmp / "cal.json"),
                        "--out", str(rec)], cwd=ROOT, env={**os.environ, "PYTHONPATH": str(ROOT)},
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr

    async def live() -> tuple[list[np.ndarray], Any]:
        cam = ReplayCamera(rec, pace=False)
        await cam.open()
        pipe = Pipeline(cam, cam.factory_calibration(), PipelineConfig(sampler="q2tree", light_count=256))
        await pipe.start()
        maps, res = [], None
        try:
            for _ in range(FRAMES):
                res = await pipe.step()
                maps.append(np.asarray(res.equirect, np.float64))
        finally:
            await pipe.stop()
        return maps, res

    maps, last = asyncio.run(live())
    proj = Projector(cal, equirect_height=maps[0].shape[0], maps=("equirect",))
    settings = fusion_settings(fit.response, deghost=True)

    def offline(idx: list[int]) -> np.ndarray:
        res = fuse([frames[i] for i in idx], [fit.exposures_s[i] for i in idx], fit.response, settings=settings)
        return np.asarray(proj.project_equirect(res.radiance), np.float64)

    n = len(frames)
    full, even, odd = offline(list(range(n))), offline(list(range(0, n, 2))), offline(list(range(1, n, 2)))
    cov = np.asarray(proj.coverage_equirect, np.float64)
    seen = cov > 0.999
    omega = equirect_solid_angle(full.shape[0])
    upper = slice(0, full.shape[0] // 2)

    def energy(x: np.ndarray) -> float:
        return float((luminance(x) * omega)[seen].sum())

    def dlog(a: np.ndarray, b: np.ndarray) -> float:
        return subset_consistency(np.where(seen[..., None], a, 0.0), np.where(seen[..., None], b, 0.0))

    tail = maps[-30:]
    return {"energy": [energy(m) / energy(full) for m in tail], "dlog": [dlog(m, full) for m in tail],
            "even_odd": dlog(even, odd), "last": last,
            "seen_share": float((cov * omega)[upper].sum() / omega[upper].sum()),
            "unseen_energy": float((luminance(maps[-1]) * omega)[cov <= 0].sum()) / energy(maps[-1])}


_RESULTS: dict[str, dict[str, Any]] = {}


def _result(stack: str, shared_data: Path, tmp_path_factory: Any) -> dict[str, Any]:
    if stack not in _RESULTS:
        _RESULTS[stack] = _run(stack, shared_data, tmp_path_factory.mktemp(stack))
    return _RESULTS[stack]


_ENERGY = [
    "piccante_room_lamp",
    "makehdr_room_window",
    pytest.param("pku_campus_trees", marks=pytest.mark.xfail(
        strict=True, reason="pku's hand-held photographs disagree in level: the live map is 22-25% brighter (issue 45 note)")),
]
_PIXELS = ["piccante_room_lamp", "makehdr_room_window", "pku_campus_trees"]


@pytest.mark.timeout(900)
@pytest.mark.parametrize("stack", _ENERGY)
def test_live_pipeline_on_a_real_bracket_holds_the_offline_energy(stack: str, shared_data: Path,
                                                                  tmp_path_factory: Any) -> None:
    r = _result(stack, shared_data, tmp_path_factory)
    # the level the last 30 of 300 frames hold (their median), and no frame of them far from it:
    # one frame a cycle, after the 1/920 s photograph, reads piccante's lamp 2.6% high (its
    # halo's codes near the top of a fitted JPEG response; issue 45's note)
    assert abs(float(np.median(r["energy"])) - 1.0) <= 0.02, r["energy"]
    assert max(abs(e - 1.0) for e in r["energy"]) <= 0.03, r["energy"]
    # the lens sees a sixth of the hemisphere: the set says so, and nothing is made up outside it
    assert r["last"].lights.extra.get("seen") == pytest.approx(r["seen_share"], abs=0.02)
    assert 0.1 < r["seen_share"] < 0.25
    assert r["last"].coverage is not None
    assert r["unseen_energy"] < 0.01


@pytest.mark.timeout(900)
@pytest.mark.parametrize("stack", _PIXELS)
def test_live_pipeline_on_a_real_bracket_agrees_per_pixel(stack: str, shared_data: Path,
                                                          tmp_path_factory: Any) -> None:
    r = _result(stack, shared_data, tmp_path_factory)
    assert max(r["dlog"]) <= r["even_odd"], (r["dlog"][-1], r["even_odd"])
