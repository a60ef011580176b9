"""The lamp tracker (``lightprobe.device.hdr.tracking``): a lamp measured on two frames is drawn where its
velocity puts it on a censored frame, with its energy; a static or switched-off lamp is left to
the merge; what the merge's hold placed near a drawn lamp is taken back."""

from __future__ import annotations

import numpy as np

from lightprobe.core.sphere import luminance
from lightprobe.device.hdr.tracking import LampTracker

ROWS, WIDTH = 32, 64
BG = 1.0


def _lamp_map(col: float | None, peak: float = 100.0) -> np.ndarray:
    """A Gaussian lamp (sigma 0.8 px) at row 12, column ``col`` on a flat background."""
    f = np.full((ROWS, WIDTH, 3), BG, np.float32)
    if col is not None:
        r, c = np.mgrid[0:ROWS, 0:WIDTH]
        f += (peak * np.exp(-((r - 12.0) ** 2 + (c - col) ** 2) / (2 * 0.8**2)))[..., None].astype(np.float32)
    return f


def _energy_above_bg(f: np.ndarray) -> float:
    return float(luminance(f.astype(np.float64) - BG).sum())


def _centroid_col(f: np.ndarray) -> float:
    w = np.maximum(luminance(f.astype(np.float64) - BG), 0.0)
    return float((w.sum(axis=0) * np.arange(WIDTH)).sum() / w.sum())


def _censored(old_col: float, new_col: float, bound: float = 5.0) -> tuple[np.ndarray, np.ndarray]:
    """What a long exposure leaves in the merged map: the truth where it measures, and where it
    is saturated (where the lamp is and where its halo still was) the old lamp the merge holds,
    or only the lower bound where the old lamp was below it."""
    f = _lamp_map(new_col)
    old = _lamp_map(old_col)
    sat = np.zeros((ROWS, WIDTH), bool)
    for col in (old_col, new_col):
        sat[10:15, int(col) - 2:int(col) + 3] = True
    f[sat] = np.maximum(old[sat], bound)
    return f, sat


def _measured(t: LampTracker, cols: list[float | None]) -> None:
    """A long frame that saturates the lamp (the schedule's), then frames that measure it."""
    first = cols[0] if cols[0] is not None else 20.0
    f, sat = _censored(first, first)
    t.update(-1, f.reshape(-1, 3), sat.reshape(-1))
    for k, col in enumerate(cols):
        t.update(k, _lamp_map(col).reshape(-1, 3), np.zeros(ROWS * WIDTH, bool))


def _run(cols: list[float | None], censored_to: float | None, tracker: LampTracker | None = None,
         placed: tuple[np.ndarray, np.ndarray] | None = None) -> tuple[np.ndarray, np.ndarray, int]:
    t = tracker or LampTracker(WIDTH)
    _measured(t, cols)
    last = cols[-1]
    assert last is not None
    f, sat = _censored(last, censored_to if censored_to is not None else last)
    before = f.copy()
    flat = f.reshape(-1, 3)
    drawn = t.update(len(cols), flat, sat.reshape(-1), placed, 4)
    return before, f, drawn


def test_a_moving_lamp_is_drawn_where_its_velocity_puts_it_with_its_energy() -> None:
    energy = _energy_above_bg(_lamp_map(30.0))
    before, after, drawn = _run([26.0, 28.0], censored_to=30.0)
    assert drawn == 1
    # the merge alone would publish the lamp where it was, and the lower bound where it went
    assert abs(_centroid_col(before) - 28.0) < 0.6
    assert abs(_centroid_col(after) - 30.0) < 0.25
    assert abs(_energy_above_bg(after) / energy - 1) < 0.01
    # the old place is background again
    assert np.allclose(after[12, 25:27], BG, atol=1e-2)


def test_a_lamp_no_exposure_saturates_is_left_to_the_merge() -> None:
    """A bright region no frame has saturated lately is measured every frame: not tracked."""
    t = LampTracker(WIDTH)
    for k, col in enumerate([26.0, 28.0]):
        t.update(k, _lamp_map(col).reshape(-1, 3), np.zeros(ROWS * WIDTH, bool))
    assert t.tracks == []


def test_a_static_or_switched_off_lamp_is_left_to_the_merge() -> None:
    before, after, drawn = _run([28.0, 28.0], censored_to=None)
    assert drawn == 0
    assert np.array_equal(before, after)
    t = LampTracker(WIDTH)
    _measured(t, [26.0, 28.0])
    off = _lamp_map(None)  # switched off: nothing saturated, nothing drawn
    assert t.update(2, off.reshape(-1, 3), np.zeros(ROWS * WIDTH, bool)) == 0
    assert np.array_equal(off, _lamp_map(None))


def test_what_the_hold_placed_near_a_drawn_lamp_is_taken_back() -> None:
    energy = _energy_above_bg(_lamp_map(30.0))
    near, far = 12 * WIDTH + 33, 25 * WIDTH + 5  # 3 px from the lamp; far from it
    extra = np.array([[7.0, 7.0, 7.0], [2.0, 2.0, 2.0]], np.float32)
    placed = (np.array([near, far], np.int64), extra)
    t = LampTracker(WIDTH)
    _measured(t, [26.0, 28.0])
    f, sat = _censored(28.0, 30.0)
    flat = f.reshape(-1, 3)
    flat[[near, far]] += extra  # as _place_held added them
    assert t.update(2, flat, sat.reshape(-1), placed, 4) == 1
    assert np.allclose(f[25, 5], BG + 2.0)  # not near the lamp: kept
    got = _energy_above_bg(f) - float(luminance(np.float64(2.0) * np.ones(3)))
    assert abs(got / energy - 1) < 0.01  # the near placement is not counted twice


def _roll(f: np.ndarray, by: int) -> np.ndarray:
    return np.roll(f, by, axis=1)


def test_a_lamp_crossing_the_seam_is_one_lamp() -> None:
    """The same moving lamp with the map's columns rolled so that it crosses the 0 / 2 pi seam:
    drawn at the same place (rolled) with the same energy as far from the seam."""
    energy = _energy_above_bg(_lamp_map(30.0))
    by = WIDTH - 29  # the lamp at column 29 sits on the seam
    t = LampTracker(WIDTH)
    f, sat = _censored(26.0, 26.0)
    t.update(-1, np.ascontiguousarray(_roll(f, by)).reshape(-1, 3), _roll(sat, by).reshape(-1))
    for k, col in enumerate([26.0, 28.0]):
        t.update(k, np.ascontiguousarray(_roll(_lamp_map(col), by)).reshape(-1, 3), np.zeros(ROWS * WIDTH, bool))
    assert len(t.tracks) == 1
    f, sat = _censored(28.0, 30.0)
    rolled = np.ascontiguousarray(_roll(f, by))
    assert t.update(2, rolled.reshape(-1, 3), np.ascontiguousarray(_roll(sat, by)).reshape(-1)) == 1
    back = _roll(rolled, -by)  # the seam now runs through the lamp's old and new places
    assert abs(_centroid_col(back) - 30.0) < 0.25
    assert abs(_energy_above_bg(back) / energy - 1) < 0.01


def test_a_static_lamps_energy_is_filtered_over_its_measurements_and_a_switch_resets_it() -> None:
    """A lamp only the short exposures measure, every other frame, with 3% noise per pixel: its
    published energy varies less than one measurement's and is unbiased, on the frames that
    measure it and on the ones that hold it; a step to 1.5 x is published at once."""
    rng = np.random.default_rng(3)
    sigma = 0.03
    t = LampTracker(WIDTH)
    sat = np.zeros((ROWS, WIDTH), bool)
    sat[10:15, 18:23] = True
    raw, measured, held = [], [], []
    for k in range(60):
        peak = 100.0 if k < 40 else 150.0
        excess = _lamp_map(20.0, peak).astype(np.float64) - BG
        noisy = (BG + excess * (1 + sigma * rng.standard_normal(excess.shape))).astype(np.float32)
        prec = (1.0 / (sigma * excess + 1e-3) ** 2).reshape(-1, 3)
        flat = noisy.reshape(-1, 3).copy()
        t.update(2 * k, flat, np.zeros(ROWS * WIDTH, bool), precision=prec)
        raw.append(_energy_above_bg(noisy))
        measured.append(_energy_above_bg(flat.reshape(ROWS, WIDTH, 3)))
        # the long frame after it: saturated there, the merge holds the measurement
        hold = noisy.reshape(-1, 3).copy()
        t.update(2 * k + 1, hold, sat.reshape(-1), precision=prec)
        held.append(_energy_above_bg(hold.reshape(ROWS, WIDTH, 3)))
    true = _energy_above_bg(_lamp_map(20.0, 100.0))
    raw_a, meas_a, held_a = (np.array(x[5:40]) / true for x in (raw, measured, held))
    assert np.std(meas_a) < 0.7 * np.std(raw_a)
    assert np.std(held_a) < 0.7 * np.std(raw_a)
    assert abs(np.mean(meas_a) - 1) < 0.01
    assert np.allclose(held_a, meas_a, rtol=1e-4)  # a held frame publishes the filtered energy too
    # the step: the first frame that measures it publishes it as measured
    assert abs(measured[40] / raw[40] - 1) < 1e-4
    assert abs(measured[40] / (1.5 * true) - 1) < 0.05


def test_the_energy_gate_counts_output_pixels_that_share_fisheye_pixels() -> None:
    """Output pixels in pairs that read the same fisheye pixels (one noise draw per pair): a lamp's
    energy scatters sqrt(2) x more than its pixels' variances summed say. Told so (``sharing``
    2), the filter keeps averaging (a 3-sigma gate resets about as rarely as on a Gaussian);
    not told, a static lamp's filter resets several times as often."""
    rng = np.random.default_rng(11)
    sigma = 0.03
    excess = _lamp_map(20.0).astype(np.float64) - BG
    prec = (1.0 / (sigma * excess + 1e-3) ** 2).reshape(-1, 3)
    noise = [rng.standard_normal((ROWS, WIDTH // 2, 1)).repeat(2, axis=1) for _ in range(300)]

    sat = np.zeros((ROWS, WIDTH), bool)
    sat[10:15, 18:23] = True

    def resets(sharing: np.ndarray | None) -> int:
        t = LampTracker(WIDTH, k_sigma=3.0)
        n = 0
        for k, z in enumerate(noise):
            noisy = (BG + excess * (1 + sigma * z)).astype(np.float32).reshape(-1, 3)
            flat = noisy.copy()
            t.update(2 * k, flat, np.zeros(ROWS * WIDTH, bool), precision=prec, sharing=sharing)
            # a reset publishes the measurement as it is (scale 1); a filtered one is rescaled
            n += k > 1 and bool(np.array_equal(flat, noisy))
            t.update(2 * k + 1, noisy.copy(), sat.reshape(-1), precision=prec, sharing=sharing)  # a long frame
        return n

    told, untold = resets(np.full(ROWS * WIDTH, 2.0)), resets(None)
    assert told <= 3, told
    assert untold >= 3 * max(told, 2), (told, untold)
