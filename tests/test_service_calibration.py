"""The service takes its calibration from the calibration store (last good version wins)."""

from __future__ import annotations

from pathlib import Path

import pytest

from lightprobe.calibration.store import CalibrationStore, load_calibration
from lightprobe.core.calibration import Photometric
from lightprobe.core.errors import InputError
from lightprobe.sim.camera import SimCamera


def test_store_wins_over_the_simulators_truth_and_survives_a_corrupt_current(tmp_path: Path) -> None:
    cam = SimCamera("room")
    truth = cam.truth_calibration()
    assert load_calibration(tmp_path, cam).id == truth.id
    store = CalibrationStore(tmp_path)
    first = truth.with_(photometric=Photometric(2.0, "nit"))
    second = truth.with_(photometric=Photometric(3.0, "nit"))
    store.save(first)
    v2 = store.save(second)
    assert load_calibration(tmp_path, cam).id == second.id
    # Corrupt the current version: the previous good one stays in use
    path = next(p for p in (tmp_path / "calibration" / "history").iterdir() if p.name.startswith(f"{v2.number:06d}"))
    path.write_text("{ torn")
    assert load_calibration(tmp_path, cam).id == first.id


def test_hardware_camera_without_calibration_is_a_clear_error(tmp_path: Path) -> None:
    class Bare:
        name = "v4l2:/dev/video0"

    with pytest.raises(InputError, match="lightprobe calibrate"):
        load_calibration(tmp_path, Bare())
