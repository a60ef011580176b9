"""Checkerboard views rendered through a known fisheye lens, for testing the calibration.

Each sensor sub-pixel is unprojected to a camera ray with the true KB4 model
(:meth:`lightprobe.sim.optics.Kb4Lens.unproject`), intersected with the board plane and shaded
by the checker pattern; ``supersample`` x ``supersample`` sub-pixels per pixel give
anti-aliasing, then Gaussian noise and 8-bit quantisation. The rays are computed once per
renderer, so a view costs one plane intersection per sub-pixel.

Board geometry: ``cols`` x ``rows`` inner corners at ``(i s, j s, 0)`` in the board frame, the
same points as :func:`lightprobe.calibration.fisheye.board_object_points`; the squares span
``[-s, cols s] x [-s, rows s]`` and a white quiet zone of one square surrounds them.
Camera frame: OpenCV (x right, y down, z along the optical axis); a pose maps board points to the
camera, ``X_cam = R X_board + t``.

Dtype policy: rays and poses float64; rendered images uint8 (H, W) grey.
"""

from __future__ import annotations

import threading
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import cv2
import numpy as np

from .optics import Kb4Lens

if TYPE_CHECKING:
    from .lens import SimLens

__all__ = ["BoardPose", "BoardRenderer", "BoardSchedule", "BoardStep", "aimed_pose", "interpolate_pose",
           "random_pose", "true_corners"]


@dataclass(frozen=True)
class BoardPose:
    """Board -> camera: ``X_cam = R @ X_board + t`` (metres or the board's unit)."""

    R: np.ndarray
    t: np.ndarray

    @property
    def rvec(self) -> np.ndarray:
        return cv2.Rodrigues(self.R)[0].reshape(3)


def _board_grid(cols: int, rows: int, square: float) -> np.ndarray:
    j, i = np.mgrid[0:rows, 0:cols]
    return np.stack([i.ravel(), j.ravel(), np.zeros(i.size)], axis=-1).astype(np.float64) * square


def true_corners(model: Kb4Lens, pose: BoardPose, cols: int, rows: int, square: float) -> np.ndarray:
    """Exact pixel positions (N, 2) of the inner corners under the true lens."""
    pts = _board_grid(cols, rows, square) @ pose.R.T + pose.t
    return model.project(pts)


class BoardRenderer:
    """Renders checkerboard views through ``model``; rays are precomputed (float32 to save memory)."""

    def __init__(self, model: Kb4Lens, *, supersample: int = 3, background: float = 0.45,
                 max_theta_deg: float | None = None) -> None:
        self.model = model
        self.ss = int(supersample)
        w, h = model.image_size
        off = (np.arange(self.ss) + 0.5) / self.ss - 0.5
        ys = (np.arange(h)[:, None] + off[None, :]).ravel()
        xs = (np.arange(w)[:, None] + off[None, :]).ravel()
        px = np.stack(np.meshgrid(xs, ys), axis=-1)  # (h ss, w ss, 2)
        rays = model.unproject(px)
        rays[~np.isfinite(rays).all(axis=-1)] = (0.0, 0.0, -1.0)  # beyond the lens model: invalid
        theta_max = np.radians(max_theta_deg if max_theta_deg is not None else model.fov_deg / 2)
        self.valid = np.arccos(np.clip(rays[..., 2], -1, 1)) <= theta_max
        self.rays = rays.astype(np.float32)
        self.background = float(background)

    def _subpixels(self, pose: BoardPose, cols: int, rows: int, square: float
                   ) -> tuple[np.ndarray, np.ndarray]:
        """Per sub-pixel (on_board bool, reflectance float32: 0.08 black, 0.92 white, 0 off)."""
        R, t = pose.R.astype(np.float64), pose.t.astype(np.float64)
        n = R[:, 2]
        denom = self.rays @ n.astype(np.float32)
        with np.errstate(divide="ignore", invalid="ignore"):
            lam = float(n @ t) / np.where(np.abs(denom) > 1e-9, denom, np.nan)
        hit = self.rays * lam[..., None] - t.astype(np.float32)
        local = hit @ R.astype(np.float32)  # R^T (lam d - t)
        u = local[..., 0] / square
        v = local[..., 1] / square
        ok = np.isfinite(lam) & (lam > 0) & self.valid
        on_board = ok & (u >= -2) & (u < cols + 1) & (v >= -2) & (v < rows + 1)
        squares = ok & (u >= -1) & (u < cols) & (v >= -1) & (v < rows)
        black = squares & ((np.floor(u).astype(np.int64) + np.floor(v).astype(np.int64)) % 2 == 0)
        refl = np.where(black, np.float32(0.08), np.float32(0.92)) * on_board
        return on_board, refl.astype(np.float32)

    def _pool(self, x: np.ndarray) -> np.ndarray:
        h, w = self.model.image_size[1], self.model.image_size[0]
        return x.astype(np.float32).reshape(h, self.ss, w, self.ss).mean(axis=(1, 3))

    def coverage(self, pose: BoardPose, cols: int, rows: int, square: float
                 ) -> tuple[np.ndarray, np.ndarray]:
        """(alpha, albedo) float32 (H, W): the fraction of each pixel covered by the board
        (quiet zone included) and ``alpha x`` the board's mean reflectance there, so a pixel
        over a background ``B`` reads ``albedo + (1 - alpha) B``."""
        on_board, refl = self._subpixels(pose, cols, rows, square)
        return self._pool(on_board), self._pool(refl)

    def render(self, pose: BoardPose, cols: int, rows: int, square: float, *,
               noise: float = 2.0, rng: np.random.Generator | None = None) -> np.ndarray:
        """A uint8 (H, W) view of the board at ``pose``, with Gaussian noise of ``noise`` levels."""
        on_board, refl = self._subpixels(pose, cols, rows, square)
        img = np.full(on_board.shape, self.background, np.float32)
        img[~self.valid] = 0.02  # outside the image circle: dark
        img[on_board] = refl[on_board]
        img = self._pool(img)
        rng = rng or np.random.default_rng(0)
        out = img * 255.0 + rng.normal(0.0, noise, img.shape)
        return np.clip(np.rint(out), 0, 255).astype(np.uint8)


def random_pose(rng: np.random.Generator, cols: int, rows: int, square: float, *,
                theta_deg: float, distance: float, tilt_deg: float = 35.0) -> BoardPose:
    """A board centred in direction (theta_deg off-axis, random azimuth) at ``distance``,
    facing the camera with a random tilt up to ``tilt_deg`` and a random in-plane rotation."""
    th = np.radians(theta_deg)
    ph = rng.uniform(0, 2 * np.pi)
    d = np.array([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)])
    # Board normal (board +z, pointing away from the camera) = d, tilted.
    axis = np.cross(d, rng.normal(size=3))
    axis /= np.linalg.norm(axis)
    tilt = np.radians(rng.uniform(-tilt_deg, tilt_deg))
    normal = cv2.Rodrigues(axis * tilt)[0] @ d
    x0 = np.cross(normal, rng.normal(size=3))
    x0 /= np.linalg.norm(x0)
    spin = rng.uniform(0, 2 * np.pi)
    x_axis = cv2.Rodrigues(normal * spin)[0] @ x0
    y_axis = np.cross(normal, x_axis)
    R = np.stack([x_axis, y_axis, normal], axis=1)
    centre_board = np.array([(cols - 1) * square / 2, (rows - 1) * square / 2, 0.0])
    t = distance * d - R @ centre_board
    return BoardPose(R, t)


def aimed_pose(theta_deg: float, phi_deg: float, distance: float, cols: int, rows: int, square: float,
               *, tilt_deg: float = 0.0, tilt_dir_deg: float = 0.0, spin_deg: float = 0.0) -> BoardPose:
    """A board centred in camera direction (``theta_deg`` off-axis, azimuth ``phi_deg``) at
    ``distance``, facing the camera, then tilted by ``tilt_deg`` about an in-plane axis at
    ``tilt_dir_deg`` and spun by ``spin_deg`` about its normal (deterministic :func:`random_pose`)."""
    th, ph = np.radians(theta_deg), np.radians(phi_deg)
    d = np.array([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)])
    # An orthonormal frame (e1, e2, d) around the viewing direction
    helper = np.array([0.0, 0.0, 1.0]) if abs(d[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    e1 = np.cross(helper, d)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(d, e1)
    a = np.radians(tilt_dir_deg)
    axis = np.cos(a) * e1 + np.sin(a) * e2
    normal = cv2.Rodrigues(axis * np.radians(tilt_deg))[0] @ d
    x0 = np.cross(normal, e2 if abs(normal @ e2) < 0.9 else e1)
    x0 /= np.linalg.norm(x0)
    x_axis = cv2.Rodrigues(normal * np.radians(spin_deg))[0] @ x0
    y_axis = np.cross(normal, x_axis)
    R = np.stack([x_axis, y_axis, normal], axis=1)
    centre_board = np.array([(cols - 1) * square / 2, (rows - 1) * square / 2, 0.0])
    return BoardPose(R, distance * d - R @ centre_board)


def interpolate_pose(a: BoardPose, b: BoardPose, s: float) -> BoardPose:
    """Pose a fraction ``s`` in [0, 1] of the way from ``a`` to ``b``: rotation along the
    geodesic (axis-angle of ``R_b R_a^T``), translation linearly."""
    s = float(np.clip(s, 0.0, 1.0))
    rel = cv2.Rodrigues(b.R @ a.R.T)[0].reshape(3)
    R = cv2.Rodrigues(rel * s)[0] @ a.R
    return BoardPose(R, (1.0 - s) * a.t + s * b.t)


@dataclass(frozen=True)
class BoardStep:
    """Move to ``pose`` over ``move_s`` seconds, then hold it still for ``hold_s`` seconds."""

    pose: BoardPose
    move_s: float
    hold_s: float


@dataclass
class BoardSchedule:
    """A technician holding a checkerboard in front of the simulated probe.

    A deterministic list of :class:`BoardStep`: the board moves (interpolated poses) to a new
    region of the image circle, is held still, moves on; after the last step it starts over
    (``loop``) or stays. :meth:`composite` puts the board over the scene's sensor-plane radiance
    for :class:`lightprobe.sim.camera.SimCamera` (``camera.show_board(schedule)``), so the camera's noise,
    vignetting and response apply to board frames as to any other.

    ``white_radiance`` is the radiance of the board's white squares in the scene's unit; None
    picks 2x the 95th percentile of the scene inside the image circle on the first frame (a board
    in the light). Times are seconds of the camera's virtual clock since the board appeared.
    """

    steps: Sequence[BoardStep]
    cols: int = 9
    rows: int = 6
    square: float = 0.04
    white_radiance: float | None = None
    loop: bool = True
    _renderers: dict[tuple[int, int], BoardRenderer] = field(default_factory=dict, repr=False)
    _lock: threading.Lock = field(default_factory=threading.Lock, repr=False)  # frames render in threads

    @property
    def duration(self) -> float:
        return float(sum(s.move_s + s.hold_s for s in self.steps))

    def pose_at(self, t: float) -> tuple[BoardPose, bool]:
        """(pose, moving) at time ``t`` (s) since the board appeared."""
        if not self.steps:
            raise ValueError("a board schedule needs at least one step")
        total = self.duration
        t = float(t) % total if self.loop and total > 0 else min(float(t), total)
        prev = self.steps[-1].pose if self.loop else self.steps[0].pose
        for step in self.steps:
            if t < step.move_s:
                return interpolate_pose(prev, step.pose, t / step.move_s), True
            t -= step.move_s
            if t < step.hold_s:
                return step.pose, False
            t -= step.hold_s
            prev = step.pose
        return self.steps[-1].pose, False

    def still_poses(self) -> list[BoardPose]:
        return [s.pose for s in self.steps]

    def renderer(self, lens: SimLens) -> BoardRenderer:
        """The board renderer for ``lens`` (rays cached per sensor size, 2x2 sub-pixels)."""
        key = lens.fisheye.image_size
        with self._lock:
            if key not in self._renderers:
                self._renderers[key] = BoardRenderer(lens.fisheye, supersample=2,
                                                     max_theta_deg=lens.circle_deg / 2)
            return self._renderers[key]

    def composite(self, radiance: np.ndarray, t: float, lens: SimLens) -> np.ndarray:
        """Scene sensor-plane radiance (H, W, 3) float32 with the board in front at time ``t``."""
        rend = self.renderer(lens)
        with self._lock:
            if self.white_radiance is None:  # degenerate (black) scene: a board of radiance 1
                lum = radiance.mean(axis=-1)[rend.valid[:: rend.ss, :: rend.ss]]
                q = float(np.quantile(lum, 0.95)) if lum.size else 0.0
                self.white_radiance = 2.0 * q / 0.92 if q > 0 else 1.0
        pose, _ = self.pose_at(t)
        alpha, albedo = rend.coverage(pose, self.cols, self.rows, self.square)
        out = radiance * (1.0 - alpha)[..., None] + (albedo * np.float32(self.white_radiance))[..., None]
        return out.astype(np.float32)

    @classmethod
    def technician(cls, cols: int = 9, rows: int = 6, square: float = 0.04, *, seed: int = 0,
                   hold_s: float = 1.0, move_s: float = 0.5, distance: float = 0.5,
                   rings: Sequence[tuple[float, int]] = ((0.0, 1), (35.0, 6), (55.0, 8), (68.0, 8)),
                   white_radiance: float | None = None) -> BoardSchedule:
        """Poses that sweep the image circle ring by ring: ``rings`` lists (off-axis angle of the
        board centre in deg, number of azimuths); each pose gets a seeded tilt (10-30 deg
        about a random in-plane axis) and spin (+-25 deg)."""
        rng = np.random.default_rng(seed)
        steps = []
        for k, (theta, count) in enumerate(rings):
            for j in range(count):
                phi = 360.0 * (j + 0.5 * (k % 2)) / max(count, 1)
                pose = aimed_pose(theta, phi, distance * (1.0 + 0.15 * rng.uniform(-1, 1)), cols, rows, square,
                                  tilt_deg=float(rng.uniform(10, 30)) if theta > 0 else float(rng.uniform(0, 20)),
                                  tilt_dir_deg=float(rng.uniform(0, 360)), spin_deg=float(rng.uniform(-25, 25)))
                steps.append(BoardStep(pose, move_s, hold_s))
        return cls(steps, cols, rows, square, white_radiance)
