"""Fisheye calibration on the real photos (acceptance against the author's independent Ceres
result) and the ``lightprobe calibrate`` command line: bad input exits 2 naming the files,
results merge into an existing calibration file."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from lightprobe.calibration.fisheye import (
    View,
    board_object_points,
    calibrate_views,
    detect_board,
    parse_board,
)
from lightprobe.cli.calibrate import main as calibrate_main
from lightprobe.core.calibration import Calibration, Photometric

ROOT = Path(__file__).resolve().parent.parent
REAL = "fisheye_calibration/lim_8x6_27.5mm"


def parse_ceres_yaml(path: Path) -> dict[str, object]:
    """The upstream result file: ``key: value`` scalars and ``key:`` followed by ``  - x`` lists."""
    out: dict[str, object] = {}
    key = None
    for line in path.read_text().splitlines():
        if not line.strip():
            continue
        if line.lstrip().startswith("- "):
            assert key is not None
            out.setdefault(key, [])
            out[key].append(float(line.strip()[2:]))  # type: ignore[union-attr]
        else:
            key, _, value = line.partition(":")
            key = key.strip()
            if value.strip():
                out[key] = value.strip()
    return out


@pytest.fixture(scope="module")
def real_views(shared_data: Path) -> list[View]:
    board = parse_board("8x6", 27.5)
    views = []
    for p in sorted((shared_data / REAL).glob("*.png")):
        corners = detect_board(cv2.imread(str(p)), board)
        assert corners is not None, p.name
        views.append(View(p.name, corners, board_object_points(board)))
    return views


def test_real_photos_match_ceres_result(real_views: list[View], shared_data: Path) -> None:
    ref = parse_ceres_yaml(shared_data / REAL / "intrinsic_ceres_result.yaml")
    assert ref["distortion_model"] == "fisheye"
    K_ref = np.array(ref["camera_matrix"]).reshape(3, 3)
    res = calibrate_views(real_views, (int(ref["image_width"]), int(ref["image_height"])))
    assert len(res.used) + len(res.rejected) == 34
    assert len(res.used) >= 30
    assert res.rms_px <= 0.4
    K = res.model.K
    for (i, j) in [(0, 0), (1, 1), (0, 2), (1, 2)]:
        assert abs(K[i, j] / K_ref[i, j] - 1) <= 0.01, (i, j, K[i, j], K_ref[i, j])
    assert set(res.per_view_rms) == set(res.used)
    assert max(res.per_view_rms.values()) < 1.0
    assert 0 < res.coverage_fraction <= 1
    assert res.missing_regions()
    assert 100 < res.model.fov_deg < 180  # a moderate fisheye, full-frame image


def test_corrupted_view_is_rejected_and_too_few_views_fail(real_views: list[View]) -> None:
    """A view with mislabelled corners (two rows swapped) is rejected by name; the result still
    matches the all-good solve; fewer views than ``min_views`` give a clean ValueError."""
    good = calibrate_views(real_views[:12], (640, 480))
    bad_corners = real_views[5].corners.reshape(6, 8, 2)[[1, 0, 2, 3, 4, 5]].reshape(-1, 2)
    views = [*real_views[:12], View("swapped.png", bad_corners, real_views[5].object_points)]
    res = calibrate_views(views, (640, 480))
    assert "swapped.png" in res.rejected
    assert "swapped.png" not in res.used
    np.testing.assert_allclose(res.model.K, good.model.K, rtol=1e-3)
    with pytest.raises(ValueError, match="calibration failed"):
        calibrate_views(real_views[:4], (640, 480), min_views=5)


def _run(*argv: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "lightprobe.cli", "calibrate", *argv], cwd=ROOT,
                          capture_output=True, text=True, timeout=120)


def test_cli_fisheye_merges_into_existing_file(tmp_path: Path, shared_data: Path) -> None:
    out = tmp_path / "calib.json"
    out.write_text(json.dumps(Calibration(photometric=Photometric(2.5, "nit")).to_json()))
    imgs = sorted(str(p) for p in (shared_data / REAL).glob("*.png"))[:12]
    r = _run("fisheye", *imgs, "--board", "8x6", "--square", "27.5", "--out", str(out))
    assert r.returncode == 0, r.stderr
    cal = Calibration.from_json(json.loads(out.read_text()))
    assert cal.photometric == Photometric(2.5, "nit")  # kept
    assert cal.fisheye is not None
    assert cal.fisheye.views_used + len(cal.fisheye.views_rejected) == 12
    assert cal.fisheye.rms_px < 0.5
    assert "rms" in r.stderr


def test_cli_bad_inputs_exit_2_naming_files(tmp_path: Path, shared_data: Path) -> None:
    blank = tmp_path / "blank.png"
    cv2.imwrite(str(blank), np.full((480, 640, 3), 128, np.uint8))
    small = tmp_path / "small.png"
    cv2.imwrite(str(small), np.full((240, 320, 3), 128, np.uint8))
    real = sorted(str(p) for p in (shared_data / REAL).glob("*.png"))[:2]
    out = str(tmp_path / "c.json")
    # Images with no board.
    assert calibrate_main(["fisheye", str(blank), str(blank), "--board", "8x6", "--square", "27.5", "--out", out]) == 2
    # Wrong board size: the real photos searched for a 9x6 board.
    r = _run("fisheye", *real, "--board", "9x6", "--square", "27.5", "--out", out)
    assert r.returncode == 2
    assert all(Path(p).name in r.stderr for p in real)
    assert "9x6" in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1
    # Mixed image sizes.
    r = _run("fisheye", real[0], str(small), "--board", "8x6", "--square", "27.5", "--out", out)
    assert r.returncode == 2
    assert "small.png" in r.stderr
    assert "differ in size" in r.stderr
    # Unreadable file, bad --board text, argparse errors.
    r = _run("fisheye", str(tmp_path / "missing.png"), "--board", "8x6", "--square", "27.5", "--out", out)
    assert r.returncode == 2
    assert "missing.png" in r.stderr
    r = _run("fisheye", real[0], "--board", "8by6", "--square", "27.5", "--out", out)
    assert r.returncode == 2
    assert "--board" in r.stderr
    r = _run("fisheye", real[0], "--board", "8x6", "--out", out)
    assert r.returncode == 2
    assert not Path(out).exists()  # nothing written on failure
    # An existing --out that is not a calibration is named, not overwritten.
    bad = tmp_path / "bad.json"
    bad.write_text("{not json")
    r = _run("pose", "--heading", "10", "--out", str(bad))
    assert r.returncode == 2
    assert "bad.json" in r.stderr
    assert bad.read_text() == "{not json"


def test_cli_store_pose_history_rollback(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    state = str(tmp_path / "state")
    assert calibrate_main(["pose", "--heading", "30", "--state", state]) == 0
    assert calibrate_main(["pose", "--heading", "45", "--tilt", "2", "--state", state]) == 0
    capsys.readouterr()
    assert calibrate_main(["history", "--state", state]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert len(lines) == 2
    assert lines[1].startswith("*")
    assert lines[0].endswith("ok")
    assert calibrate_main(["rollback", "--state", state]) == 0
    capsys.readouterr()
    assert calibrate_main(["show", "--state", state]) == 0
    shown = json.loads(capsys.readouterr().out)
    R = np.array(shown["pose"]["rotation"])
    np.testing.assert_allclose(R @ [0, 0, -1], [np.sin(np.radians(30)), 0, -np.cos(np.radians(30))], atol=1e-9)
    assert calibrate_main(["rollback", "--state", state, "--to", "9"]) == 2
