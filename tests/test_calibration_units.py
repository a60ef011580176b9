"""Response curve, raw linearity, vignetting, lens mask and mounting pose against the
simulator's ground truth (lightprobe.sim.camera.SimCamera) and synthetic captures with known truth."""

from __future__ import annotations

import numpy as np
import pytest

from lightprobe.calibration.mask import fill_masked, find_mask, mask_image
from lightprobe.calibration.pose import pose_from_angles, pose_from_board, rotation_angle_deg
from lightprobe.calibration.response import (
    capture_bracket,
    compare_inverse,
    linearity_check,
    response_from_stack,
)
from lightprobe.calibration.vignetting import (
    max_relative_error,
    vignetting_from_flat_field,
    vignetting_from_patches,
)
from lightprobe.core.calibration import (
    Calibration,
    FisheyeModel,
    LensMask,
    Vignetting,
    repair_inverse,
)
from lightprobe.core.sphere import CAMERA_TO_PROBE
from lightprobe.drivers.base import Mode, PixelFormat
from lightprobe.sim.camera import SimCamera
from lightprobe.sim.scene import Scene

EXPOSURES = [1 / 1000 * 2**i for i in range(10)]  # 1 ms .. 0.512 s, 1 stop apart: the room at S = 1e4


# ---- response -------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def rgb_bracket() -> tuple[list[np.ndarray], Calibration]:
    import asyncio

    async def grab() -> tuple[list[np.ndarray], Calibration]:
        cam = SimCamera("room", seed=1)
        async with cam:
            frames = await capture_bracket(cam, EXPOSURES)
            assert [f.meta.exposure_s for f in frames] == EXPOSURES  # metadata-verified
            return [f.data for f in frames], cam.truth_calibration()

    return asyncio.run(grab())


@pytest.mark.parametrize(("method", "tol_mid", "tol_wide"), [("debevec", 0.03, 0.06), ("robertson", 0.04, 0.06)])
def test_response_matches_sim_truth(rgb_bracket: tuple[list[np.ndarray], Calibration], method: str,
                                    tol_mid: float, tol_wide: float) -> None:
    frames, truth = rgb_bracket
    resp = response_from_stack(frames, EXPOSURES, method=method)
    assert resp.method == method
    assert resp.inverse.shape == (256, 3)
    assert np.all(np.isfinite(resp.inverse))
    assert np.all(np.diff(resp.inverse, axis=0) >= 0)
    assert compare_inverse(resp, truth.response, 32, 230) <= tol_mid
    assert compare_inverse(resp, truth.response, 16, 240) <= tol_wide
    # A linear table is far from the truth: the comparison can fail.
    lin = type(resp)("table", 8, repair_inverse(np.repeat(np.arange(1, 257.0)[:, None], 3, axis=1)), "x")
    assert compare_inverse(lin, truth.response, 32, 230) > 0.2


def test_repair_inverse_guards_nan_and_non_monotone() -> None:
    t = np.linspace(0.01, 2.0, 256)[:, None].repeat(3, axis=1)
    t[:3, 0] = np.nan  # what OpenCV 5's Robertson can return for the darkest codes
    t[100, 1] = 0.0
    t[200, 2] = 0.1
    c = repair_inverse(t)
    assert np.all(np.isfinite(c))
    assert np.all(c > 0)
    assert np.all(np.diff(c, axis=0) >= 0)
    np.testing.assert_allclose(c[3:, 0], t[3:, 0])  # finite entries are kept
    assert np.all(c[:3, 0] == t[3, 0])  # the nearest finite value beyond the end
    with pytest.raises(ValueError, match="no finite"):
        repair_inverse(np.full((256, 3), np.nan))


def test_raw_linearity_check_on_sim_and_rejects_processed(rgb_bracket: tuple[list[np.ndarray], Calibration]) -> None:
    import asyncio

    async def grab() -> tuple[list[np.ndarray], float, float]:
        cam = SimCamera("room", seed=4)
        async with cam:
            await cam.set_mode(Mode(640, 480, PixelFormat.RAW12, 30.0))
            frames = await capture_bracket(cam, EXPOSURES)
            return [f.data for f in frames], frames[0].black_level, frames[0].white_level

    raw, black, white = asyncio.run(grab())
    rep = linearity_check(raw, EXPOSURES, black, white)
    assert rep.ok(1.0), rep
    nonlin = linearity_check(rgb_bracket[0], EXPOSURES, 0.0, 255.0)
    assert not nonlin.ok(5.0)


# ---- vignetting -----------------------------------------------------------------------------------
def test_vignetting_from_synthetic_flat_field_within_1_percent() -> None:
    rng = np.random.default_rng(7)
    truth = Vignetting((322.4, 236.1), 230.0, (-0.31, -0.08, 0.02))
    h, w = 480, 640
    vv, uu = np.mgrid[0:h, 0:w]
    img = 0.6 * truth.factor(uu.astype(float), vv.astype(float))
    img = img * (1 + 0.02 * rng.standard_normal(img.shape))  # 2 % pixel noise
    img[np.hypot(uu - 322.4, vv - 236.1) > 230] = 0.0  # black frame outside the circle
    img[10, 10] = np.nan
    est = vignetting_from_flat_field(img.astype(np.float32), truth.center, truth.radius_px)
    assert max_relative_error(est, truth) < 0.01
    # Same patch seen at 12 positions around the circle.
    pos = np.stack([322.4 + np.linspace(0, 225, 12) * np.cos(np.arange(12)),
                    236.1 + np.linspace(0, 225, 12) * np.sin(np.arange(12))], axis=1)
    vals = 3.0 * truth.factor(pos[:, 0], pos[:, 1]) * (1 + 0.002 * rng.standard_normal(12))
    est2 = vignetting_from_patches(pos, vals, truth.center, truth.radius_px)
    assert max_relative_error(est2, truth) < 0.01
    # All-black flat field: a clear error, no coefficients invented.
    with pytest.raises(ValueError, match="non-positive"):
        vignetting_from_flat_field(np.zeros((48, 64)), (32, 24), 20.0)


@pytest.fixture(scope="module")
def sim_flat() -> tuple[np.ndarray, Calibration, float]:
    import asyncio

    async def grab() -> tuple[np.ndarray, Calibration, float]:
        cam = SimCamera(Scene(np.ones((32, 64, 3), np.float32), name="flat"), seed=2)
        async with cam:
            await cam.set_mode(Mode(640, 480, PixelFormat.RAW12, 30.0))
            f = (await capture_bracket(cam, [0.2], frames_per_exposure=2))[0]
            lin = (f.data.astype(np.float64) - f.black_level) / (f.white_level - f.black_level)
            return lin, cam.truth_calibration(), cam.lens.circle_radius_px

    return asyncio.run(grab())


def test_vignetting_from_sim_flat_field_within_1_percent(sim_flat: tuple[np.ndarray, Calibration, float]) -> None:
    lin, truth, _ = sim_flat
    tv = truth.vignetting
    est = vignetting_from_flat_field(lin, tv.center, tv.radius_px, max_r=0.97)  # ring excluded
    assert max_relative_error(est, tv) < 0.01


# ---- lens mask ------------------------------------------------------------------------------------
def test_mask_finds_housing_ring_on_sim(sim_flat: tuple[np.ndarray, Calibration, float]) -> None:
    lin, truth, circle_r = sim_flat
    K = truth.fisheye.K
    m = find_mask(lin, (K[0, 2], K[1, 2]))
    # The ring occupies the outer 1 deg of polar angle: its inner edge is ~ circle_r * 92.5/93.5.
    ring_inner = circle_r * (92.5 / 93.5)
    assert ring_inner - 8 <= m.radius_px <= ring_inner
    inside = mask_image(m, lin.shape[:2])
    assert inside[int(K[1, 2]), int(K[0, 2])]
    assert not inside[0, 0]
    filled = fill_masked(lin.astype(np.float32), m, band_px=6)
    vv, uu = np.mgrid[0 : lin.shape[0], 0 : lin.shape[1]]
    band = (np.hypot(uu - K[0, 2], vv - K[1, 2]) > m.radius_px + 1) & (np.hypot(uu - K[0, 2], vv - K[1, 2]) < m.radius_px + 5)
    # The dark ring is filled with values like the rim inside it, not left near zero.
    rim = (np.hypot(uu - K[0, 2], vv - K[1, 2]) > m.radius_px - 4) & (np.hypot(uu - K[0, 2], vv - K[1, 2]) <= m.radius_px)
    assert np.median(lin[..., 1][band]) < 0.5 * np.median(lin[..., 1][rim])
    assert np.median(filled[..., 1][band]) == pytest.approx(np.median(lin[..., 1][rim]), rel=0.1)
    with pytest.raises(ValueError, match="black"):
        find_mask(np.zeros((48, 64, 3)), (32, 24))


def test_mask_section_round_trips_in_calibration() -> None:
    cal = Calibration(mask=LensMask((320.0, 240.0), 230.5))
    back = Calibration.from_json(cal.to_json())
    assert back.mask == cal.mask
    assert back.id == cal.id
    assert "mask" not in Calibration().to_json()  # absent when not calibrated


# ---- pose -----------------------------------------------------------------------------------------
def test_pose_from_angles_conventions() -> None:
    p = pose_from_angles(90.0)
    np.testing.assert_allclose(p.rotation @ [0, 0, -1], [1, 0, 0], atol=1e-12)  # front mark -> azimuth 90
    p = pose_from_angles(0.0, 10.0, 90.0)
    np.testing.assert_allclose(p.rotation @ [0, 1, 0], [np.sin(np.radians(10)), np.cos(np.radians(10)), 0], atol=1e-12)
    assert np.linalg.det(p.rotation) == pytest.approx(1.0)
    with pytest.raises(ValueError, match="finite"):
        pose_from_angles(float("nan"))


def test_pose_from_board_on_floor_recovers_rotation() -> None:
    """A probe hung from the ceiling looking down (180 deg about x), turned 30 deg, tilted 3 deg."""
    model = FisheyeModel((640, 480), np.array([[150.0, 0, 321.0], [0, 150.2, 241.0], [0, 0, 1]]),
                         np.array([0.02, -0.005, 0.001, 0.0]), fov_deg=190.0)
    flip = np.diag([1.0, -1.0, -1.0])
    R_true = pose_from_angles(30.0, 3.0, 45.0).rotation @ flip
    cols, rows, sq = 9, 6, 0.2
    j, i = np.mgrid[0:rows, 0:cols]
    obj = np.stack([i.ravel(), j.ravel(), np.zeros(i.size)], axis=-1) * sq
    R_room_board = np.stack([[0, 0, -1.0], [-1.0, 0, 0], [0, 1.0, 0]], axis=1)  # x_b, y_b, z_b columns
    origin = np.array([-0.6, -2.0, 0.3])  # board corner on the floor, 2 m below the probe
    pts_room = origin + obj @ R_room_board.T
    pts_cam = (pts_room @ R_true) @ CAMERA_TO_PROBE  # room -> probe (R^T), probe -> camera (C^T)
    rng = np.random.default_rng(0)
    pix = model.project(pts_cam) + rng.normal(0, 0.1, (obj.shape[0], 2))
    est = pose_from_board(pix, obj, model)
    assert rotation_angle_deg(est.rotation, R_true) < 0.3
    wrong = pose_from_angles(33.0, 3.0, 45.0).rotation @ flip
    assert rotation_angle_deg(est.rotation, wrong) > 2.0


def test_cli_pose_from_rendered_floor_board(tmp_path) -> None:  # type: ignore[no-untyped-def]
    """``calibrate pose --board-image``: a board rendered on the floor below a downward-looking
    probe (lightprobe.sim.board through the calibrated lens) gives the true mounting rotation."""
    import json

    import cv2

    from lightprobe.cli.calibrate import main as calibrate_main
    from lightprobe.sim.board import BoardPose, BoardRenderer
    from lightprobe.sim.optics import Kb4Lens

    model = FisheyeModel((640, 640), np.array([[190.0, 0, 321.3], [0, 190.4, 318.2], [0, 0, 1]]),
                         np.array([0.03, -0.01, 0.004, -0.0008]), fov_deg=190.0)
    R_true = pose_from_angles(-40.0, 2.0, 120.0).rotation @ np.diag([1.0, -1.0, -1.0])
    R_room_board = np.stack([[0, 0, -1.0], [-1.0, 0, 0], [0, 1.0, 0]], axis=1)
    origin = np.array([-0.7, -1.5, 0.5])
    R_cb = CAMERA_TO_PROBE.T @ R_true.T @ R_room_board
    t_cb = CAMERA_TO_PROBE.T @ R_true.T @ origin
    true = Kb4Lens(model.image_size, model.K, model.D, model.fov_deg)
    img = BoardRenderer(true, supersample=2).render(BoardPose(R_cb, t_cb), 9, 6, 0.15,
                                                      rng=np.random.default_rng(1))
    cv2.imwrite(str(tmp_path / "floor.png"), img)
    out = tmp_path / "calib.json"
    out.write_text(json.dumps(Calibration(fisheye=model).to_json()))
    assert calibrate_main(["pose", "--board-image", str(tmp_path / "floor.png"), "--board", "9x6",
                           "--square", "150", "--out", str(out)]) == 0
    cal = Calibration.from_json(json.loads(out.read_text()))
    assert rotation_angle_deg(cal.pose.rotation, R_true) < 0.5
    assert cal.fisheye is not None  # kept
    blank = tmp_path / "blank.png"
    cv2.imwrite(str(blank), np.zeros((640, 640), np.uint8))
    assert calibrate_main(["pose", "--board-image", str(blank), "--board", "9x6", "--out", str(out)]) == 2
