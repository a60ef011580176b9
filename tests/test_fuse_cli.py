"""``lightprobe fuse``: the real piccante stack, a calibrated response, and bad input (exit 2)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import OpenEXR
import pytest

from lightprobe.cli import main
from lightprobe.core.calibration import Calibration, Response
from lightprobe.device.hdr import FusionSettings
from lightprobe.device.hdr.stack import fit_response

STACK = "exposure_stacks/piccante_room_lamp"


def read_exr(path: Path) -> tuple[np.ndarray, dict[str, object]]:
    """Read back with the OpenEXR package itself (not our reader)."""
    with OpenEXR.File(str(path), separate_channels=True) as f:
        ch = f.parts[0].channels
        img = np.stack([ch[c].pixels for c in "RGB"], axis=-1)
        return img, dict(f.header())


@pytest.fixture(scope="module")
def stack(shared_data: Path) -> tuple[list[Path], list[float], Path]:
    d = shared_data / STACK
    times_file = d / "exposure_times_seconds.txt"
    rows = [ln.split() for ln in times_file.read_text().splitlines() if ln.strip()]
    return [d / r[0] for r in rows], [float(r[1]) for r in rows], times_file


@pytest.fixture(scope="module")
def fused_room(stack: tuple[list[Path], list[float], Path], tmp_path_factory: pytest.TempPathFactory
               ) -> tuple[np.ndarray, dict[str, object], list[np.ndarray], list[float]]:
    images, times, times_file = stack
    out = tmp_path_factory.mktemp("fuse") / "room.exr"
    assert main(["fuse", *map(str, images), "--times-file", str(times_file), "--out", str(out)]) == 0
    img, header = read_exr(out)
    frames = [cv2.imread(str(p))[..., ::-1] for p in images]
    return img, header, frames, times


def test_real_stack_reads_back_with_metadata(fused_room: tuple) -> None:
    img, header, frames, times = fused_room
    assert img.dtype == np.float32
    assert img.shape == frames[0].shape
    assert np.isfinite(img).all()
    assert (img >= 0).all()
    assert header["unit"] == "relative"
    assert [float(t) for t in str(header["exposure_labels"]).split(",")] == pytest.approx(times)
    # fused with the exposures the pictures show: the stack's own fit's, near the labels
    used = [float(t) for t in str(header["exposures"]).split(",")]
    assert used == pytest.approx(list(fit_response(frames, times).exposures_s), rel=1e-6)
    assert np.allclose(used, times, rtol=0.15)


def test_real_stack_dynamic_range_and_lamp_not_clipped(fused_room: tuple) -> None:
    img, header, frames, times = fused_room
    lum = img.mean(axis=-1)
    lo, hi = np.percentile(lum[lum > 0], [0.01, 99.99])
    assert hi / lo >= 1e4
    # The lamp: pixels near saturation in the second-shortest exposure (1/1000 s)
    order = np.argsort(times)
    lamp = frames[order[1]].max(axis=-1) >= 250
    assert lamp.sum() > 100
    n_sat = int(header["saturated_pixels"])
    core = (frames[order[0]] >= int(np.ceil(FusionSettings().sat_frac * 255))).any(axis=-1)
    # Only pixels clipped even at 1/4000 s may be flagged: a handful in the filament
    assert n_sat <= core.sum() < 0.1 * lamp.sum()
    # Unclipped: nearly all the lamp is resolved, and it is brighter than anything the stack
    # without its shortest exposure could represent (E(z_sat) / t of the second-shortest frame)
    fit = fit_response(frames, times)
    resp, used = fit.response, fit.exposures_s
    z_sat = int(np.ceil(FusionSettings().sat_frac * 255))
    bound2 = resp.inverse[z_sat] / used[order[1]]
    bound1 = resp.inverse[z_sat] / used[order[0]]
    # Pixels at the documented lower bound (flagged ones, and any at the same clip value)
    sat_mask = (img >= bound1 * (1 - 1e-4)).any(axis=-1)
    assert sat_mask.sum() >= n_sat
    resolved = lamp & ~sat_mask
    assert resolved.sum() >= 0.95 * lamp.sum()
    assert np.any(img[resolved] > 2 * bound2)
    assert lum[resolved].max() > 1000 * np.median(lum)


def test_times_on_the_command_line_and_a_calibrated_response(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A synthetic stack from a known gamma response, fused with that response as a file; the
    same picture three times is refused with the response given too (no fit to notice it)."""
    rng = np.random.default_rng(4)
    x = np.exp(rng.uniform(np.log(0.02), np.log(1.0), (40, 60, 3)))
    times = ["1/50", "0.08", "0.32"]
    tv = [1 / 50, 0.08, 0.32]
    z = np.arange(256) / 255.0
    resp = Response("table", 8, np.repeat((z**2.2)[:, None], 3, axis=1), "truth")
    paths = []
    for i, t in enumerate(tv):
        img = np.rint(255 * np.clip(x * t * 3, 0, 1) ** (1 / 2.2)).astype(np.uint8)
        paths.append(tmp_path / f"f{i}.png")
        cv2.imwrite(str(paths[-1]), img[..., ::-1])
    cal = tmp_path / "cal.json"
    cal.write_text(json.dumps(Calibration(response=resp).to_json()))
    out = tmp_path / "out.exr"
    assert main(["fuse", *map(str, paths), "--times", *times, "--response", str(cal), "--out", str(out)]) == 0
    img, header = read_exr(out)
    assert header["response"] == "truth"
    ok = (x * 3 * tv[-1] > 0.02)
    rel = np.abs(img / (3 * x) - 1)[ok]
    assert np.median(rel) < 0.005
    capsys.readouterr()
    same = [str(paths[1])] * 3
    assert main(["fuse", *same, "--times", *times, "--response", str(cal), "--out", str(tmp_path / "s.exr")]) == 2
    assert "do not get brighter with exposure time" in capsys.readouterr().err
    assert not (tmp_path / "s.exr").exists()


@pytest.fixture
def small_stack(tmp_path: Path) -> list[Path]:
    paths = []
    for i in range(2):
        p = tmp_path / f"s{i}.png"
        cv2.imwrite(str(p), np.full((8, 10, 3), 40 * (i + 1), np.uint8))
        paths.append(p)
    return paths


def _run(argv: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str]:
    code = main(["fuse", *argv])
    return code, capsys.readouterr().err


def test_bad_inputs_exit_2_naming_the_culprit(small_stack: list[Path], tmp_path: Path,
                                              capsys: pytest.CaptureFixture[str]) -> None:
    a, b = map(str, small_stack)
    out = str(tmp_path / "o.exr")
    junk = tmp_path / "junk.jpg"
    junk.write_text("not an image")
    big = tmp_path / "big.png"
    cv2.imwrite(str(big), np.zeros((9, 10, 3), np.uint8))
    cases = [
        ([a, str(junk), "--times", "0.1", "0.2", "--out", out], "junk.jpg"),
        ([a, str(tmp_path / "missing.png"), "--times", "0.1", "0.2", "--out", out], "missing.png"),
        ([a, str(big), "--times", "0.1", "0.2", "--out", out], "big.png"),
        ([a, b, "--out", out], "--times"),
        ([a, b, "--times", "0.1", "0", "--out", out], "'0'"),
        ([a, b, "--times", "0.1", "-3", "--out", out], "'-3'"),
        ([a, b, "--times", "0.1", "abc", "--out", out], "'abc'"),
        ([a, b, "--times", "0.1", "--out", out], "2 images but 1 exposure times"),
        ([a, b, "--times-file", str(junk), "--out", out], "junk.jpg"),
        ([a, b, "--times", "0.1", "0.2", "--response", str(junk), "--out", out], "junk.jpg"),
        ([a, b, "--times", "0.1", "0.2", "--out", str(tmp_path / "o.png")], "o.png"),
        ([a, a, "--times", "0.1", "0.4", "--out", out], "do not get brighter with exposure time"),
    ]
    for argv, culprit in cases:
        code, err = _run(argv, capsys)
        assert code == 2, (argv, err)
        assert culprit in err, (culprit, err)
        assert len(err.strip().splitlines()) == 1, err
    assert not (tmp_path / "o.exr").exists()


def test_console_script_exit_code(small_stack: list[Path], tmp_path: Path) -> None:
    exe = Path(sys.executable).parent / "lightprobe"
    a, b = map(str, small_stack)
    r = subprocess.run([str(exe), "fuse", a, b, "--times", "0.1", "--out", str(tmp_path / "o.exr")],
                       capture_output=True, text=True, timeout=120, check=False)
    assert r.returncode == 2
    assert "exposure times" in r.stderr
    r = subprocess.run([str(exe), "fuse", a, b, "--times", "0.1", "0.2", "--out", str(tmp_path / "o.exr")],
                       capture_output=True, text=True, timeout=120, check=False)
    assert r.returncode == 0, r.stderr
    assert (tmp_path / "o.exr").is_file()


def test_fuse_reports_what_it_did_and_a_bad_stack(stack: tuple[list[Path], list[float], Path],
                                                  shared_data: Path, tmp_path: Path,
                                                  capsys: pytest.CaptureFixture[str]) -> None:
    images, _, times_file = stack
    assert main(["fuse", *map(str, images), "--times-file", str(times_file), "--out", str(tmp_path / "a.exr")]) == 0
    out = capsys.readouterr().out
    assert "response: debevec (estimated from the stack); noise model: measured scatter per code" in out
    assert "of the usable samples rejected" in out
    assert "exposures: 7 of 7 refined from the pictures" in out  # a tripod stack: a few percent each
    assert "warning" not in out
    _, header = read_exr(tmp_path / "a.exr")
    assert float(header["deghost_rejected"]) < 0.05
    # Two times given in the wrong order: the pictures ask for a 4x correction; the labels are
    # kept and the report says why
    _, times, _ = stack
    swapped = [times[0], times[2], times[1], *times[3:]]
    assert main(["fuse", *map(str, images), "--times", *map(str, swapped), "--out", str(tmp_path / "s.exr")]) == 0
    out = capsys.readouterr().out
    assert "exposures: 0 of 7 refined from the pictures" in out
    assert "beyond belief: are the times in the images' order? the labels were kept" in out
    _, header = read_exr(tmp_path / "s.exr")
    assert header["exposures"] == header["exposure_labels"]
    # The pku grove's four longest exposures are white everywhere: the report says so
    d = shared_data / "exposure_stacks" / "pku_campus_trees"
    white = [str(d / f"Ldr0{i}.jpg") for i in range(1, 5)]
    assert main(["fuse", *white, "--times", "1/2", "1/4", "1/8", "1/15", "--out", str(tmp_path / "b.exr")]) == 0
    out = capsys.readouterr().out
    assert "warning: over 5% of the pixels are saturated even in the shortest exposure" in out


def test_a_hand_held_stack_is_reported_and_registered_with_align(shared_data: Path, tmp_path: Path,
                                                                 capsys: pytest.CaptureFixture[str]) -> None:
    """The pku phone stack (2-5 px off): ``fuse`` warns and names ``--align``; with it the frames
    are registered (the shifts in the report and the EXR header), and the warning is gone."""
    d = shared_data / "exposure_stacks" / "pku_campus_trees"
    images = sorted(str(p) for p in d.glob("Ldr*.jpg"))
    times = str(d / "exposure_times_seconds.txt")
    assert main(["fuse", *images, "--times-file", times, "--out", str(tmp_path / "a.exr")]) == 0
    out = capsys.readouterr().out
    assert "registration: not applied, frames off by up to 5 px" in out
    assert "warning: the frames are misregistered by up to 5 px (a hand-held stack?): --align registers them" in out
    _, header = read_exr(tmp_path / "a.exr")
    assert header["aligned"] == "no"
    assert main(["fuse", *images, "--times-file", times, "--align", "--out", str(tmp_path / "b.exr")]) == 0
    out = capsys.readouterr().out
    assert "registration: applied, frames off by up to 5 px" in out
    assert "misregistered" not in out
    # The phone's shortest frames are not what their labels say (one acts like 0.59 x its label):
    # fused with what the pictures show, and said so
    assert "exposures: 8 of 15 refined from the pictures" in out
    assert "warning: exposure 13 (5.80013e-05 s) acts like" in out
    _, header = read_exr(tmp_path / "b.exr")
    shifts = [tuple(int(v) for v in s.split(",")) for s in str(header["aligned"]).split()]
    assert len(shifts) == len(images)
    assert (0, 0) in shifts
    assert max(max(map(abs, s)) for s in shifts) == 5


def test_registration_recovers_known_shifts_of_a_real_stack(stack: tuple[list[Path], list[float], Path]) -> None:
    """The tripod piccante stack moved by known whole pixels (border replicated): the median
    threshold bitmaps find every move back to the pixel, relative to the reference frame, in the
    frames with mid-tones to register (the two shortest are nearly black: they take their
    neighbour's shift)."""
    from lightprobe.device.hdr.align import MIN_MIDTONE, apply_shifts, stack_shifts

    images, _, _ = stack
    frames = [cv2.imread(str(p))[..., ::-1] for p in images]
    grey = [cv2.cvtColor(np.ascontiguousarray(f), cv2.COLOR_RGB2GRAY) for f in frames]
    usable = [float(((g >= 16) & (g <= 240)).mean()) >= MIN_MIDTONE for g in grey]
    assert sum(usable) >= 4, usable
    base = stack_shifts(frames)
    moves = [(0, 0), (3, -2), (-4, 1), (2, 5), (-1, -3), (6, 0), (0, -6)][: len(frames)]
    moved = apply_shifts(frames, moves)
    found = stack_shifts(moved)
    ref = found.index((0, 0)) if (0, 0) in found else 0
    for k, (f, m, b) in enumerate(zip(found, moves, base, strict=True)):
        if not usable[k]:
            continue
        # registering undoes the move: found = base - (move - the reference's move)
        want = (b[0] - (m[0] - moves[ref][0]), b[1] - (m[1] - moves[ref][1]))
        assert f == want, (k, f, want)


def test_deghosting_with_a_measured_response_drops_a_moving_lamp_only(
        stack: tuple[list[Path], list[float], Path]) -> None:
    """A patch pasted into one exposure of the real (static) stack, bright (a lamp on during that
    exposure only) or dark (a lamp off, a passer-by): with the stack's measured scatter the
    deghosting drops exactly that patch's samples and keeps the rest."""
    from lightprobe.device.hdr.fusion import fuse
    from lightprobe.device.hdr.stack import fuse_report, read_stack

    images, times, _ = stack
    frames = read_stack(images)
    fit = fit_response(frames, times)
    response, times = fit.response, list(fit.exposures_s)
    assert response.log_sigma is not None
    settings = FusionSettings(deghost=True, ghost_rel_tol=0.05)
    clean = fuse(frames, times, response, settings=settings).radiance
    patch = (slice(20, 60), slice(20, 60))
    outside = np.ones(clean.shape[:2], bool)
    outside[patch] = False
    # 1/30 s shows the wall at ~27, 0.5 s at ~189; the dark patch is code 12, not black: a code-5
    # sample weighs so little (its typical scatter) that it barely moves even the plain merge
    for k, code in ((3, 200), (1, 12)):
        ghosted = [f.copy() for f in frames]
        ghosted[k][patch] = code
        res = fuse(ghosted, times, response, settings=settings)
        plain = fuse(ghosted, times, response, settings=FusionSettings(deghost=False)).radiance
        err = np.median(np.abs(res.radiance[patch] / clean[patch] - 1))
        err_plain = np.median(np.abs(plain[patch] / clean[patch] - 1))
        assert err < 0.02, (k, code, err)  # the patch is gone
        assert err_plain > 2 * err, (k, code, err_plain)  # without deghosting it is not
        assert res.rejected[patch].mean() >= 0.9  # its samples were the ones rejected
        assert res.rejected[outside].mean() < 0.05  # the static rest keeps its samples
        assert fuse_report(res, response, "test")["deghost_rejected_fraction"] < 0.05
