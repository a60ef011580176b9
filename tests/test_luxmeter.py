"""T-10A protocol client against the simulated meter on a real pty: framing, faults, retries,
and the photometric scale from meter readings."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from lightprobe.calibration.photometric import lux_statistics, photometric_scale, upper_irradiance
from lightprobe.core.sphere import equirect_directions
from lightprobe.drivers.t10a import (
    T10A,
    T10AChecksumError,
    T10ADisconnected,
    T10AGarbage,
    T10AMeterError,
    T10ATimeout,
    bcc,
    decode_block,
    encode_block,
    make_frame,
    parse_reply,
)
from lightprobe.sim.luxmeter import SimT10A


def test_frame_layout_and_bcc() -> None:
    f = make_frame(0, "54", "1   ")
    assert f[:1] == b"\x02"
    assert f[-2:] == b"\r\n"
    assert len(f) == 14
    assert f[1:10] == b"00541   \x03"
    x = 0
    for b in f[1:10]:
        x ^= b
    assert f[10:12] == f"{x:02X}".encode()
    assert bcc(b"\x03") == b"03"


@given(st.floats(min_value=0.0, max_value=9.99e8, allow_nan=False))
@settings(max_examples=300, deadline=None)
def test_data_block_round_trip(value: float) -> None:
    back = decode_block(encode_block(value))
    # 4 significant digits (values >= 0.1), or absolute resolution 1e-4 below.
    assert abs(back - value) <= max(5e-4 * value, 5e-5)


def test_parse_reply_rejects_bad_frames() -> None:
    good = make_frame(0, "10", "  00", encode_block(123.4) * 3)
    assert parse_reply(good, "10").values[0] == pytest.approx(123.4)
    with pytest.raises(T10AChecksumError):
        parse_reply(good[:-4] + b"00\r\n", "10")
    with pytest.raises(T10AGarbage):
        parse_reply(b"hello\r\n", "10")
    with pytest.raises(T10AGarbage, match="command"):
        parse_reply(good, "11")
    with pytest.raises(T10AGarbage, match="data block"):
        parse_reply(make_frame(0, "10", "  00", b"+12a45" * 3), "10")


@pytest.fixture
def meter() -> SimT10A:
    with SimT10A(523.4, noise_rel=0.0, period_s=0.02) as m:
        yield m


def test_reads_true_value_after_pc_mode(meter: SimT10A) -> None:
    with T10A(meter.port, timeout=0.3) as t:
        assert t.read_lux() == pytest.approx(523.4)
    assert meter.requests[0][3:9] == b"541   "  # PC-connect sent first


@pytest.mark.parametrize(("fault", "error"), [("checksum", T10AChecksumError), ("garbage", T10AGarbage),
                                              ("partial", T10ATimeout), ("timeout", T10ATimeout)])
def test_transient_fault_is_retried(meter: SimT10A, fault: str, error: type) -> None:
    with T10A(meter.port, timeout=0.3, retries=2) as t:
        meter.inject(fault, 1)
        n0 = len(meter.requests)
        assert t.read_lux() == pytest.approx(523.4)
        assert len(meter.requests) - n0 == 2  # one failed attempt + one retry


@pytest.mark.parametrize(("fault", "error"), [("checksum", T10AChecksumError), ("garbage", T10AGarbage),
                                              ("partial", T10ATimeout), ("timeout", T10ATimeout)])
def test_persistent_fault_gives_typed_error_bounded(meter: SimT10A, fault: str, error: type) -> None:
    with T10A(meter.port, timeout=0.3, retries=2) as t:
        meter.inject(fault, None)
        n0 = len(meter.requests)
        with pytest.raises(error, match=r"after 3 attempts") as ei:
            t.read_lux()  # bounded: attempts x timeout, never a hang (the test's timeout guards it)
        assert meter.port in str(ei.value)
        assert len(meter.requests) - n0 == 3


def test_meter_error_status_is_not_retried(meter: SimT10A) -> None:
    with T10A(meter.port, timeout=0.3) as t:
        meter.inject("over_range", 1)
        with pytest.raises(T10AMeterError, match="over range"):
            t.read_lux()


def test_unplug_gives_disconnected_and_no_hang(meter: SimT10A) -> None:
    t = T10A(meter.port, timeout=0.3)
    t.open()
    meter.inject("unplug", 1)
    with pytest.raises(T10ADisconnected):
        t.read_lux()
    with pytest.raises(T10ADisconnected, match="not open"):
        t.read_lux()
    t.close()


def test_missing_port_is_disconnected() -> None:
    with pytest.raises(T10ADisconnected, match="cannot open"):
        T10A("/dev/nonexistent-t10a", timeout=0.2).open()


def test_photometric_scale_from_simulated_meter_within_1_percent() -> None:
    """Truth: a sky of L(theta) = L0 (1 + 2 cos theta) nits above the horizon and a 'floor'
    below; E = pi L0 + 2 L0 (2 pi / 3) = L0 (pi + 4 pi / 3) lux. The probe sees radiance / k."""
    L0, k_true = 80.0, 37.5
    h = 128
    d = equirect_directions(h)
    cos_t = d[..., 1]
    radiance = np.where(cos_t > 0, L0 * (1 + 2 * cos_t), 15.0)[..., None] * np.ones(3)
    probe_map = (radiance / k_true).astype(np.float32)
    lux_true = L0 * (np.pi + 4 * np.pi / 3)
    with SimT10A(lux_true, noise_rel=0.005, period_s=0.01, seed=3) as m, T10A(m.port, timeout=0.3) as t:
        stats = lux_statistics(t.read_many(8, interval=0.012))
    phot = photometric_scale(stats.mean, probe_map)
    assert phot.unit == "nit"
    assert abs(phot.scale / k_true - 1) < 0.01
    assert 0 < stats.cv_percent < 2.0
    assert len(stats.values) == 8
    # Degenerate maps: black -> clear error; NaN pixels ignored.
    with pytest.raises(ValueError, match="no light"):
        photometric_scale(100.0, np.zeros((8, 16, 3), np.float32))
    nan_map = probe_map.copy()
    nan_map[3, 5] = np.nan
    assert upper_irradiance(nan_map) == pytest.approx(upper_irradiance(probe_map), rel=1e-3)


def test_upper_irradiance_of_uniform_sky_is_pi_l() -> None:
    for h in (7, 16, 64):
        img = np.ones((h, 2 * h, 3), np.float32) * 2.0
        expected = np.pi * 2.0  # the lower hemisphere contributes nothing
        assert upper_irradiance(img) == pytest.approx(expected, rel=1e-12)


def test_cli_photometric_with_simulated_meter(tmp_path) -> None:  # type: ignore[no-untyped-def]
    """``lightprobe calibrate photometric --port PTY`` end to end: uniform sky of 3 relative
    units, meter reading 300 pi lux -> scale 100, merged into the calibration file."""
    import json

    from lightprobe.cli.calibrate import main as calibrate_main
    from lightprobe.core.calibration import Calibration
    from lightprobe.core.imageio import write_exr

    m = tmp_path / "map.exr"
    write_exr(m, np.full((32, 64, 3), 3.0, np.float32))
    out = tmp_path / "calib.json"
    with SimT10A(300 * np.pi, noise_rel=0.0, period_s=0.01) as meter:
        rc = calibrate_main(["photometric", "--map", str(m), "--port", meter.port, "--readings", "3",
                             "--interval", "0.02", "--timeout", "0.3", "--out", str(out)])
        assert rc == 0
        meter.inject("timeout", None)  # a dead meter: exit 1 with a clear message, no hang
        rc = calibrate_main(["photometric", "--map", str(m), "--port", meter.port, "--timeout", "0.2",
                             "--out", str(tmp_path / "other.json")])
        assert rc == 1
    cal = Calibration.from_json(json.loads(out.read_text()))
    assert cal.photometric.unit == "nit"
    assert cal.photometric.scale == pytest.approx(100.0, rel=1e-3)
    assert not (tmp_path / "other.json").exists()
