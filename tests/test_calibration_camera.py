"""``lightprobe calibrate response|vignetting|photometric --camera SPEC``: the probe captures its
own calibration data through the driver protocol (the simulator here), checked against the
simulator's ground truth with the tolerances of the file-based tests; bad --camera exits 2."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from lightprobe.calibration.photometric import upper_irradiance
from lightprobe.calibration.response import compare_inverse
from lightprobe.calibration.vignetting import max_relative_error
from lightprobe.cli.calibrate import main
from lightprobe.core.calibration import Calibration
from lightprobe.sim.camera import SimCamera
from lightprobe.sim.luxmeter import SimT10A


def load(path: Path) -> Calibration:
    return Calibration.from_json(json.loads(path.read_text()))


@pytest.mark.slow
@pytest.mark.parametrize(("method", "tol_mid", "tol_wide"), [("debevec", 0.03, 0.06), ("robertson", 0.04, 0.06)])
def test_response_from_the_probes_own_bracket(tmp_path: Path, method: str, tol_mid: float, tol_wide: float,
                                              capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "cal.json"
    assert main(["response", "--camera", "sim", "--scene", "lebombo", "--method", method, "--out", str(out)]) == 0
    assert "captured" in capsys.readouterr().err
    resp = load(out).response
    assert resp is not None
    assert resp.method == method
    truth = SimCamera("lebombo").truth_calibration().response
    assert truth is not None
    mid, wide = compare_inverse(resp, truth, 32, 230), compare_inverse(resp, truth, 16, 240)
    print(f"response {method} from the probe's bracket: codes 32..230 {100 * mid:.2f}%, 16..240 {100 * wide:.2f}%")
    assert mid <= tol_mid, f"codes 32..230: {100 * mid:.2f}%"
    assert wide <= tol_wide, f"codes 16..240: {100 * wide:.2f}%"


def test_raw_mode_gets_a_linearity_check(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                         capsys: pytest.CaptureFixture[str]) -> None:
    """A camera in a raw mode: the bracket is checked for linearity and a linear response stored."""
    import lightprobe.device.bootstrap as bootstrap
    from lightprobe.drivers.base import Mode, PixelFormat

    def raw_camera(spec: str, scene: str | None = None) -> SimCamera:
        cam = SimCamera("room", seed=3)
        cam._mode = Mode(640, 480, PixelFormat.RAW12, 30.0)  # as if set by the installer's config
        return cam

    monkeypatch.setattr(bootstrap, "open_cli_camera", raw_camera)
    out = tmp_path / "cal.json"
    assert main(["response", "--camera", "sim", "--exposures", "0.004", "0.008", "0.016", "0.032",
                 "--out", str(out)]) == 0
    assert "raw linearity" in capsys.readouterr().err
    resp = load(out).response
    assert resp is not None
    assert resp.model == "linear"
    assert resp.bits == 12


def test_vignetting_from_a_captured_flat_field(tmp_path: Path) -> None:
    truth = SimCamera("room").truth_calibration()
    out = tmp_path / "cal.json"
    out.write_text(json.dumps(truth.with_(vignetting=None).to_json()))  # fisheye + mask known
    assert main(["vignetting", "--camera", "sim", "--scene", "uniform", "--out", str(out)]) == 0
    est = load(out).vignetting
    assert est is not None
    assert truth.vignetting is not None
    err = max_relative_error(est, truth.vignetting)
    print(f"vignetting from a captured flat field: max error {100 * err:.4f}%")
    assert err < 0.01, f"max relative error {100 * err:.3f}%"


@pytest.mark.slow
def test_photometric_scale_from_a_captured_burst_and_the_meter(tmp_path: Path) -> None:
    """Meter reads 100 x the true illuminance (1 scene unit = 100 nit): the scale must be
    100 x the simulator's fused-to-radiance factor."""
    cam = SimCamera("room")
    truth = cam.truth_calibration()
    assert truth.photometric is not None
    lux = 100.0 * upper_irradiance(cam.truth_radiance())
    out = tmp_path / "cal.json"
    with SimT10A(lux, noise_rel=0.0, period_s=0.01) as meter:
        assert main(["photometric", "--camera", "sim", "--scene", "room", "--port", meter.port, "--readings", "3",
                     "--interval", "0.02", "--timeout", "0.5", "--out", str(out)]) == 0
    phot = load(out).photometric
    assert phot is not None
    assert phot.unit == "nit"
    err = phot.scale / (100.0 * truth.photometric.scale) - 1
    print(f"photometric scale from a captured burst: error {100 * err:+.3f}%")
    assert abs(err) <= 0.01, f"scale error {100 * err:+.3f}%"


@pytest.mark.parametrize("argv", [
    ["response", "--camera", "bogus:thing"],
    ["response", "--camera", "v4l2:/dev/video-lightprobe-none"],
    ["response", "--camera", "sim", "--scene", "no-such-scene"],
    ["response", "a.png", "--camera", "sim"],
    ["response", "--scene", "room", "--times", "1"],
    ["vignetting", "--camera", "nope"],
    ["vignetting"],
    ["photometric", "--camera", "bogus:x", "--lux", "100"],
    ["photometric", "--lux", "100"],
])
def test_bad_camera_or_source_exits_2_naming_it(argv: list[str], tmp_path: Path,
                                               capsys: pytest.CaptureFixture[str]) -> None:
    assert main([*argv, "--out", str(tmp_path / "x.json")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("lightprobe: error:")
    assert any(k in err for k in ("--camera", "--scene", "scene", "IMG", "FLAT", "--map")), err
    assert not (tmp_path / "x.json").exists()
