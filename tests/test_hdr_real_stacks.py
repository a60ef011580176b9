"""HDR on real photographs (issue 13): every stack in ``../shared/data/exposure_stacks``, read
from there, scored against OpenCV's Debevec and Robertson in the same run (``lightprobe.bench.hdr``).

The metric needs no ground truth: the even and the odd exposures of a static stack fused apart
must give the same radiance (median |d log L| after one global scale). Our fusion estimates its
own response from the whole stack, as ``lightprobe fuse`` does. Figures go to
``test-artifacts/hdr_real_stacks.json`` and BENCHMARKS.md.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from lightprobe.bench.hdr import run_stacks

pytestmark = pytest.mark.slow
TRIPOD = ("piccante_room_lamp", "makehdr_room_window")  # static, registered to <= 1 px


@pytest.fixture(scope="module")
def scores(shared_data: Path, artifacts_dir: Path) -> dict[str, Any]:
    r = run_stacks(shared_data)
    (artifacts_dir / "hdr_real_stacks.json").write_text(json.dumps(r, indent=1))
    return r


def test_every_shared_stack_is_scored(scores: dict[str, Any], shared_data: Path) -> None:
    on_disk = {d.name for d in (shared_data / "exposure_stacks").iterdir() if d.is_dir()}
    assert set(scores) == on_disk
    assert len(scores) >= 3


def test_subset_consistency_beats_opencv(scores: dict[str, Any]) -> None:
    for name, s in scores.items():
        ours, deb, rob = (s[k]["even_odd_dlog"] for k in ("lightprobe", "opencv_debevec", "opencv_robertson"))
        print(f"{name}: even/odd |dlog| ours {ours:.4f}, OpenCV Debevec {deb:.4f}, Robertson {rob:.4f}")
        assert ours <= rob, name
        assert ours <= deb, name
        assert ours <= 0.8 * deb, name  # makehdr, the closest: 0.796 x when this was written


def test_effective_exposures_make_the_subsets_agree(scores: dict[str, Any]) -> None:
    """Fused with the exposures the pictures show (``lightprobe.calibration.response.fit_stack``) rather than
    the nominal labels, the tripod stacks' subsets agree better (makehdr 0.0102 -> 0.0094,
    piccante 0.027 -> 0.022 when this was written), with corrections of a few percent."""
    for name in TRIPOD:
        ours, labels = scores[name]["lightprobe"], scores[name]["lightprobe_labels"]
        corr = np.asarray(ours["exposure_corrections"])
        print(f"{name}: even/odd {ours['even_odd_dlog']:.4f} (labels {labels['even_odd_dlog']:.4f}), "
              f"corrections {np.round(corr, 3).tolist()}")
        assert ours["even_odd_dlog"] <= 0.95 * labels["even_odd_dlog"], name
        assert np.all(np.abs(np.log(corr)) < np.log(1.15)), name
        assert np.any(corr != 1.0), name


def test_agrees_with_opencv_and_keeps_the_dynamic_range(scores: dict[str, Any]) -> None:
    for name, s in scores.items():
        ours = s["lightprobe"]
        assert ours["dynamic_range"] >= 0.5 * s["opencv_debevec"]["dynamic_range"], name
        assert ours["log_correlation_vs_opencv_debevec"] >= 0.98, name
        reg = s.get("registered")
        if reg is not None:  # the registered frames too, with OpenCV given the same frames
            assert reg["lightprobe"]["log_correlation_vs_opencv_debevec"] >= 0.98, name
            assert reg["lightprobe"]["dynamic_range"] >= 0.5 * reg["opencv_debevec"]["dynamic_range"], name


def test_registering_a_hand_held_stack_makes_its_subsets_agree(scores: dict[str, Any]) -> None:
    """A stack misregistered by 2 px or more (pku: 2-5 px) is registered by ``--align``
    (``lightprobe.device.hdr.align``): our even and odd fusions of the registered frames agree within 0.7 x
    of the unregistered ones and within 0.8 x of OpenCV Debevec's on the same registered frames,
    and ours agrees better with OpenCV's merge than before. The tripod stacks move by <= 1 px."""
    moved = {n: max(max(abs(v) for v in sh) for sh in s["shifts"]) for n, s in scores.items()}
    assert all(moved[n] <= 1 for n in TRIPOD), moved
    hand_held = [n for n in scores if moved[n] >= 2]
    assert hand_held, moved
    for name in hand_held:
        raw, reg = scores[name], scores[name]["registered"]
        ours, deb = reg["lightprobe"], reg["opencv_debevec"]
        print(f"{name} registered: even/odd ours {ours['even_odd_dlog']:.4f} (was {raw['lightprobe']['even_odd_dlog']:.4f}),"
              f" OpenCV Debevec {deb['even_odd_dlog']:.4f}; correlation {ours['log_correlation_vs_opencv_debevec']:.3f}")
        assert ours["even_odd_dlog"] <= 0.7 * raw["lightprobe"]["even_odd_dlog"], name
        assert ours["even_odd_dlog"] <= 0.8 * deb["even_odd_dlog"], name
        assert ours["even_odd_dlog"] <= reg["opencv_robertson"]["even_odd_dlog"], name
        assert ours["log_correlation_vs_opencv_debevec"] > raw["lightprobe"]["log_correlation_vs_opencv_debevec"], name


def test_deghosting_never_collapses_a_static_stack(scores: dict[str, Any]) -> None:
    for name, s in scores.items():
        ours = s["lightprobe"]
        assert ours["vs_no_deghost_dlog"] <= 0.01, name  # default and --no-deghost agree
        assert ours["deghost_rejected_fraction"] < 0.05, name
        assert abs(ours["even_odd_dlog"] - s["lightprobe_no_deghost"]["even_odd_dlog"]) <= 0.005, name
