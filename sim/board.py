"""Checkerboard views rendered through a known fisheye lens, for testing the calibration.

Each sensor sub-pixel is unprojected to a camera ray with the true KB4 model
(:meth:`calibration.model.FisheyeModel.unproject`), intersected with the board plane and shaded
by the checker pattern; ``supersample`` x ``supersample`` sub-pixels per pixel give
anti-aliasing, then Gaussian noise and 8-bit quantisation. The rays are computed once per
renderer, so a view costs one plane intersection per sub-pixel.

Board geometry: ``cols`` x ``rows`` inner corners at ``(i s, j s, 0)`` in the board frame, the
same points as :func:`calibration.fisheye.board_object_points`; the squares span
``[-s, cols s] x [-s, rows s]`` and a white quiet zone of one square surrounds them.
Camera frame: OpenCV (x right, y down, z along the optical axis); a pose maps board points to the
camera, ``X_cam = R X_board + t``.

Dtype policy: rays and poses float64; rendered images uint8 (H, W) grey.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from calibration.model import FisheyeModel

__all__ = ["BoardPose", "BoardRenderer", "random_pose", "true_corners"]


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


def true_corners(model: FisheyeModel, pose: BoardPose, cols: int, rows: int, square: float) -> np.ndarray:
    """Exact pixel positions (N, 2) of the inner corners under the true lens."""
    pts = _board_grid(cols, rows, square) @ pose.R.T + pose.t
    return model.project(pts)


class BoardRenderer:
    """Renders checkerboard views through ``model``; rays are precomputed (float32 to save memory)."""

    def __init__(self, model: FisheyeModel, *, supersample: int = 3, background: float = 0.45,
                 max_theta_deg: float | None = None) -> None:
        self.model = model
        self.ss = int(supersample)
        w, h = model.image_size
        off = (np.arange(self.ss) + 0.5) / self.ss - 0.5
        ys = (np.arange(h)[:, None] + off[None, :]).ravel()
        xs = (np.arange(w)[:, None] + off[None, :]).ravel()
        px = np.stack(np.meshgrid(xs, ys), axis=-1)  # (h ss, w ss, 2)
        rays = model.unproject(px)
        theta_max = np.radians(max_theta_deg if max_theta_deg is not None else model.fov_deg / 2)
        self.valid = np.arccos(np.clip(rays[..., 2], -1, 1)) <= theta_max
        self.rays = rays.astype(np.float32)
        self.background = float(background)

    def render(self, pose: BoardPose, cols: int, rows: int, square: float, *,
               noise: float = 2.0, rng: np.random.Generator | None = None) -> np.ndarray:
        """A uint8 (H, W) view of the board at ``pose``, with Gaussian noise of ``noise`` levels."""
        R, t = pose.R.astype(np.float64), pose.t.astype(np.float64)
        n = R[:, 2]
        denom = self.rays @ n.astype(np.float32)
        lam = float(n @ t) / np.where(np.abs(denom) > 1e-9, denom, np.nan)
        hit = self.rays * lam[..., None] - t.astype(np.float32)
        local = hit @ R.astype(np.float32)  # R^T (lam d - t)
        u = local[..., 0] / square
        v = local[..., 1] / square
        ok = np.isfinite(lam) & (lam > 0) & self.valid
        on_board = ok & (u >= -2) & (u < cols + 1) & (v >= -2) & (v < rows + 1)
        squares = ok & (u >= -1) & (u < cols) & (v >= -1) & (v < rows)
        img = np.full(u.shape, self.background, np.float32)
        img[~self.valid] = 0.02  # outside the image circle: dark
        img[on_board] = 0.92
        black = squares & ((np.floor(u).astype(np.int64) + np.floor(v).astype(np.int64)) % 2 == 0)
        img[black] = 0.08
        h, w = self.model.image_size[1], self.model.image_size[0]
        img = img.reshape(h, self.ss, w, self.ss).mean(axis=(1, 3))
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
