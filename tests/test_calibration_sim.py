"""Fisheye calibration on simulated board views rendered through known KB4 lenses
(lightprobe.sim.board), and the live routine fed by a frame source."""

from __future__ import annotations

from itertools import pairwise

import cv2
import numpy as np
import pytest

from lightprobe.calibration.fisheye import (
    BoardSpec,
    View,
    board_object_points,
    calibrate_views,
    detect_board,
)
from lightprobe.calibration.live import LiveFisheyeCalibration
from lightprobe.core.calibration import FisheyeModel
from lightprobe.drivers.base import (
    Camera,
    Capabilities,
    Controls,
    Frame,
    FrameMetadata,
    Mode,
    PixelFormat,
)
from lightprobe.sim.board import BoardRenderer, random_pose, true_corners
from lightprobe.sim.optics import Kb4Lens

BOARD = BoardSpec(9, 6, 0.04)


def lens(fov_deg: float) -> Kb4Lens:
    """The true lens, the simulator's own KB4 model (the calibration under test fits a FisheyeModel)."""
    return Kb4Lens((640, 640), np.array([[190.0, 0, 321.3], [0, 190.4, 318.2], [0, 0, 1]]),
                        np.array([0.03, -0.01, 0.004, -0.0008]), fov_deg=fov_deg)


def render_views(true: Kb4Lens, n: int, seed: int, max_theta: float
                 ) -> tuple[list[View], float]:
    """Up to ``n`` detected views with board centres up to ``max_theta`` deg off-axis, and the
    largest true corner angle (deg) among them."""
    rend = BoardRenderer(true, supersample=2)
    rng = np.random.default_rng(seed)
    views, theta_max = [], 0.0
    for k in range(3 * n):
        if len(views) == n:
            break
        pose = random_pose(rng, BOARD.cols, BOARD.rows, BOARD.square,
                           theta_deg=rng.uniform(0, max_theta), distance=rng.uniform(0.35, 0.5))
        img = rend.render(pose, BOARD.cols, BOARD.rows, BOARD.square, noise=2.0, rng=rng)
        c = detect_board(img, BOARD, accurate=True)
        if c is None:
            continue
        tc = true_corners(true, pose, BOARD.cols, BOARD.rows, BOARD.square)
        # Detection is right up to the board's 180-degree symmetry.
        assert min(np.abs(c - tc).max(), np.abs(c[::-1] - tc).max()) < 1.0
        d = true.unproject(tc)
        theta_max = max(theta_max, float(np.degrees(np.arccos(d[:, 2].min()))))
        views.append(View(f"sim{k:03d}", c, board_object_points(BOARD)))
    return views, theta_max


def reprojection_vs_truth(est: FisheyeModel, true: Kb4Lens, theta_max_deg: float) -> tuple[float, float]:
    """(max, rms) pixel distance between estimated and true projections of directions up to
    ``theta_max_deg`` (72 azimuths x 60 polar angles)."""
    th = np.radians(np.linspace(0, theta_max_deg, 60))
    ph = np.linspace(0, 2 * np.pi, 72, endpoint=False)
    TH, PH = np.meshgrid(th, ph)
    d = np.stack([np.sin(TH) * np.cos(PH), np.sin(TH) * np.sin(PH), np.cos(TH)], axis=-1)
    err = np.linalg.norm(est.project(d) - true.project(d), axis=-1)
    return float(err.max()), float(np.sqrt(np.mean(err**2)))


@pytest.fixture(scope="module")
def sim190() -> tuple[Kb4Lens, list[View], float]:
    true = lens(190.0)
    views, theta_max = render_views(true, 24, seed=1, max_theta=90.0)
    assert len(views) >= 20
    return true, views, theta_max


@pytest.mark.slow
def test_sim_lens_recovered(sim190: tuple[Kb4Lens, list[View], float]) -> None:
    true, views, theta_max = sim190
    res = calibrate_views(views, true.image_size)
    K = res.model.K
    assert abs(K[0, 0] / true.K[0, 0] - 1) <= 0.003
    assert abs(K[1, 1] / true.K[1, 1] - 1) <= 0.003
    worst, rms = reprojection_vs_truth(res.model, true, theta_max)
    print(f"sim 190: f err {100 * (K[0, 0] / true.K[0, 0] - 1):.3f}% / {100 * (K[1, 1] / true.K[1, 1] - 1):.3f}%, "
          f"reprojection vs truth up to {theta_max:.1f} deg: max {worst:.3f} px rms {rms:.3f} px, "
          f"rms {res.rms_px:.3f} px, used {len(res.used)}, rejected {len(res.rejected)}")
    # Issue 5: the true model is reprojected within 0.2 px over the part of the image circle the
    # views cover (seeded views; deterministic on one machine, not across CPUs: on an AMD EPYC
    # max 0.196 px, rms 0.129 px; on an Intel Xeon the same code gave 0.381 / 0.230 px, two
    # views failing OpenCV's extrinsic initialisation and SB's inward corner bias at the rim;
    # with the readmission + bundle adjustment and the guarded corner polish 0.134 / 0.101 px)
    assert worst <= 0.2, (worst, rms)
    assert rms <= 0.2
    assert res.rms_px < 0.3
    # The check can fail: the true model with a 0.5 % focal error is far outside the bound.
    off = FisheyeModel(true.image_size, true.K * np.array([[1.005, 1, 1], [1, 1.005, 1], [1, 1, 1]]), true.D)
    assert reprojection_vs_truth(off, true, theta_max)[1] > 0.5


@pytest.mark.slow
def test_stronger_than_180_lens_converges_through_rejection() -> None:
    true = lens(220.0)
    views, theta_max = render_views(true, 24, seed=5, max_theta=105.0)
    assert theta_max > 95  # some boards really sit behind the image plane
    messages: list[str] = []
    res = calibrate_views(views, true.image_size, progress=messages.append)
    assert res.rejected
    assert messages
    K = res.model.K
    print(f"sim 220: f err {100 * (K[0, 0] / true.K[0, 0] - 1):.3f}%, rms {res.rms_px:.3f} px, "
          f"used {len(res.used)}, rejected {len(res.rejected)}, fov {res.model.fov_deg:.1f} deg")
    assert np.all(np.isfinite(res.model.D))
    assert abs(K[0, 0] / true.K[0, 0] - 1) <= 0.01
    assert res.rms_px < 0.5
    assert res.model.fov_deg > 180


def test_degenerate_view_sets_fail_cleanly() -> None:
    true = lens(190.0)
    obj = board_object_points(BOARD)
    rng = np.random.default_rng(0)
    # Random corner soup: OpenCV cannot make sense of it; a ValueError, never a crash.
    soup = [View(f"soup{i}", rng.uniform(0, 640, (BOARD.n_corners, 2)), obj) for i in range(6)]
    with pytest.raises(ValueError, match="calibration failed"):
        calibrate_views(soup, true.image_size)
    # A blank frame has no board.
    assert detect_board(np.zeros((640, 640), np.uint8), BOARD) is None


def test_live_routine_accepts_still_views_that_add_coverage() -> None:
    true = lens(190.0)
    rend = BoardRenderer(true, supersample=2)
    rng = np.random.default_rng(3)
    live = LiveFisheyeCalibration(BOARD, true.image_size, still_px=1.0, still_frames=3, min_views=6,
                                  target_rms=0.5, target_coverage=0.3,
                                  image_circle=(321.3, 318.2, 329.0))
    events: list[str] = []
    coverage = []
    for _ in range(14):
        if live.progress.good_enough:
            break
        pose = random_pose(rng, BOARD.cols, BOARD.rows, BOARD.square,
                           theta_deg=rng.uniform(0, 75), distance=rng.uniform(0.35, 0.45))
        # The technician moves the board in (a big step), then holds it still for 3 frames.
        moving = type(pose)(pose.R, pose.t + np.array([0.05, 0.0, 0.0]))
        events.append(live.feed(rend.render(moving, 9, 6, 0.04, rng=rng)))
        for _ in range(3):
            events.append(live.feed(rend.render(pose, 9, 6, 0.04, rng=rng)))
        coverage.append((live.progress.coverage_percent, len(live.progress.rejected)))
    p = live.progress
    assert "accepted" in events
    assert p.views == events.count("accepted")
    assert p.views >= 6
    assert p.good_enough
    assert p.rms_px is not None
    assert p.rms_px < 0.5
    # Coverage goes down only when the solve rejects a view (it counts the views the solve kept)
    for (c0, r0), (c1, r1) in pairwise(coverage):
        assert c1 >= c0 or r1 > r0, coverage
    assert live.feed(np.zeros((640, 640), np.uint8)) == "no board"
    assert p.frames == len(events) + 1
    assert set(p.to_json()) >= {"views", "coverage_percent", "rms_px", "good_enough"}
    # Holding one pose twice adds it once (cells already covered), and motion is not a view.
    once = LiveFisheyeCalibration(BOARD, true.image_size, cell_target=1)
    pose = random_pose(rng, 9, 6, 0.04, theta_deg=30.0, distance=0.4)
    seq = [once.feed(rend.render(pose, 9, 6, 0.04, rng=rng)) for _ in range(6)]
    assert seq[:3] == ["holding", "holding", "accepted"]
    assert "no new coverage" in seq[3:]
    assert once.progress.views == 1
    drift = [once.feed(rend.render(type(pose)(pose.R, pose.t + np.array([0.004 * i, 0, 0])), 9, 6, 0.04, rng=rng))
             for i in range(4)]
    assert drift[-1] == "moving"


class BoardCamera(Camera):
    """A frame source for the live routine: replays rendered board frames through the Camera
    protocol (the simulator has no board scene)."""

    name = "board-sim"

    def __init__(self, frames: list[np.ndarray]) -> None:
        self.frames = frames
        self.seq = 0

    async def open(self) -> None:
        pass

    async def close(self) -> None:
        pass

    @property
    def capabilities(self) -> Capabilities:
        return Capabilities((1e-4, 1.0), (1.0, 1.0), (Mode(640, 640),), True, 0)

    @property
    def mode(self) -> Mode:
        return Mode(640, 640)

    async def set_mode(self, mode: Mode) -> None:
        pass

    async def apply(self, controls: Controls) -> None:
        pass

    async def capture(self, timeout: float = 1.0) -> Frame:  # noqa: ASYNC109 - protocol signature
        data = np.repeat(self.frames[self.seq % len(self.frames)][..., None], 3, axis=2)
        self.seq += 1
        return Frame(data, FrameMetadata(0.01, 1.0, self.seq / 30, self.seq), PixelFormat.RGB8)


async def test_live_run_drives_a_camera() -> None:
    true = lens(190.0)
    rend = BoardRenderer(true, supersample=2)
    rng = np.random.default_rng(8)
    frames = []
    for _ in range(3):
        pose = random_pose(rng, 9, 6, 0.04, theta_deg=rng.uniform(10, 60), distance=0.4)
        frames += [rend.render(pose, 9, 6, 0.04, rng=rng) for _ in range(3)]
    cam = BoardCamera(frames)
    live = LiveFisheyeCalibration(BOARD, true.image_size, min_views=6)
    p = await live.run(cam, max_frames=len(frames))
    assert p.frames == len(frames) == cam.seq
    assert 1 <= p.views <= 3
    assert not p.good_enough  # too few views: the dashboard must not say "done"
    assert p.missing_regions


def test_board_schedule_holds_moves_and_loops() -> None:
    from lightprobe.sim.board import BoardSchedule, interpolate_pose

    sch = BoardSchedule.technician(hold_s=1.0, move_s=0.5)
    assert len(sch.steps) == 23
    assert sch.duration == pytest.approx(23 * 1.5)
    first, second = sch.steps[0].pose, sch.steps[1].pose
    pose, moving = sch.pose_at(0.25)  # moving in from the last pose (loop)
    assert moving
    assert not np.allclose(pose.t, first.t)
    pose, moving = sch.pose_at(0.9)
    assert not moving
    assert pose is first
    assert sch.pose_at(sch.duration + 0.9)[0] is first  # loops
    assert sch.pose_at(1.5 + 0.6)[0] is second
    a = interpolate_pose(first, second, 0.0)
    b = interpolate_pose(first, second, 1.0)
    assert np.allclose(a.R, first.R)
    assert np.allclose(b.R, second.R, atol=1e-9)
    assert np.allclose(b.t, second.t)
    mid = interpolate_pose(first, second, 0.5)
    assert np.allclose(mid.R @ mid.R.T, np.eye(3), atol=1e-9)


async def test_sim_camera_shows_the_board_through_its_lens() -> None:
    """The simulator's own frames carry the board at the scheduled pose: detected corners lie
    where the true lens puts them; show_board(None) takes it away."""
    from lightprobe.calibration.live import frame_to_gray
    from lightprobe.sim.board import BoardSchedule
    from lightprobe.sim.camera import SimCamera

    cam = SimCamera("flashlight")
    truth = cam.truth_calibration().fisheye
    assert truth is not None
    sch = BoardSchedule.technician()  # holds 1 s, moves 0.5 s
    async with cam:
        await cam.apply(Controls(exposure_s=0.02, gain=1.0))
        cam.show_board(sch)
        frames = [await cam.capture() for _ in range(20)]  # 0.63 s: holding the first pose
        tc = true_corners(truth, sch.steps[0].pose, 9, 6, 0.04)
        c = detect_board(frame_to_gray(frames[-1].data), BOARD)
        assert c is not None
        err = min(np.abs(c - tc).max(), np.abs(c[::-1] - tc).max())
        assert err < 1.0, err
        cam.show_board(None)
        await cam.capture()
        assert detect_board(frame_to_gray((await cam.capture()).data), BOARD) is None


def test_bundle_adjustment_and_readmission_recover_the_true_model() -> None:
    """The refinement behind the readmission of views OpenCV cannot initialise: from a 1%-off
    start, exact corners lead back to the true lens and poses; a view rejected as
    ill-conditioned that agrees with the solved model joins, one that does not stays out (boards
    within 90 degrees: cv2.fisheye.projectPoints folds points behind the lens forward)."""
    from lightprobe.calibration.fisheye import _bundle_adjust, _readmit

    true = lens(190.0)
    rng = np.random.default_rng(5)
    views, rvecs, tvecs = [], [], []
    for k in range(8):
        pose = random_pose(rng, BOARD.cols, BOARD.rows, BOARD.square, theta_deg=rng.uniform(0, 45),
                           distance=rng.uniform(0.35, 0.5))
        tc = true_corners(true, pose, BOARD.cols, BOARD.rows, BOARD.square)
        views.append(View(f"v{k}", tc, board_object_points(BOARD)))
        rvecs.append(cv2.Rodrigues(pose.R)[0] + rng.normal(0, 0.01, (3, 1)))
        tvecs.append(pose.t.reshape(3, 1) + rng.normal(0, 0.002, (3, 1)))
    K0 = true.K * np.array([[1.01, 1, 1], [1, 0.99, 1], [1, 1, 1]])
    sol = _bundle_adjust(views, K0, np.asarray(true.D) * 0.9, rvecs, tvecs)
    assert sol is not None
    rms, K, D, _, _ = sol
    assert rms < 1e-6
    np.testing.assert_allclose(K, true.K, rtol=1e-7, atol=1e-6)
    np.testing.assert_allclose(D, true.D, rtol=1e-5, atol=1e-8)
    # readmission: v6 agrees with the model, v7's corners are scrambled
    bad = View("v7", views[7].corners[::-1] + rng.normal(0, 5.0, views[7].corners.shape), views[7].object_points)
    rejected = {"v6": "ill-conditioned (InitExtrinsics)", "v7": "ill-conditioned (InitExtrinsics)"}
    active, sol2, errs = _readmit([*views[:7], bad], views[:6], (rms, K, D, sol[3][:6], sol[4][:6]),
                                  np.full(6, 0.05), rejected, 3.0, 1.0, lambda _m: None)
    assert [v.name for v in active] == [f"v{k}" for k in range(7)]
    assert rejected == {"v7": "ill-conditioned (InitExtrinsics)"}
    assert float(np.max(errs)) < 1e-5
    assert sol2[0] < 1e-5
