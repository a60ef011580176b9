"""Live fisheye calibration a service can drive: the technician holds the board, the routine
grabs a view when the board is still and adds coverage, and reports progress.

Per frame (:meth:`LiveFisheyeCalibration.feed`): detect the board; it is *still* when its
corners moved less than ``still_px`` (max over corners) across the last ``still_frames``
detections; a still view is *accepted* when it puts corners into a coverage cell (rings x
sectors of the image circle, :func:`lightprobe.calibration.fisheye.coverage_grid`) that holds fewer than
``cell_target`` corners, so holding the board in one place adds it once. After each accepted
view (from ``min_views`` on) the robust solve (:func:`lightprobe.calibration.fisheye.calibrate_views`)
runs and updates the RMS; coverage then counts only the views the solve kept. ``good_enough``:
at least ``min_views`` views, RMS <= ``target_rms`` and coverage >= ``target_coverage``.

The frame source is any ``lightprobe.drivers.base.Camera`` (:meth:`run`) or plain images pushed into
:meth:`feed` (a dashboard, a test). Nothing runs at import or construction.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field

import cv2
import numpy as np

from lightprobe.drivers.base import Camera, Frame

from .fisheye import (
    BoardSpec,
    FisheyeResult,
    View,
    board_object_points,
    calibrate_views,
    coverage_grid,
    detect_board,
)

__all__ = ["LiveFisheyeCalibration", "LiveProgress"]


@dataclass
class LiveProgress:
    frames: int = 0
    views: int = 0
    coverage_percent: float = 0.0
    rms_px: float | None = None
    good_enough: bool = False
    last_event: str = ""
    missing_regions: list[str] = field(default_factory=list)
    rejected: list[str] = field(default_factory=list)  # views the robust solve left out
    grid: list[list[int]] = field(default_factory=list)  # corners per ring x sector, -1 off-sensor
    last_corners: list[list[float]] | None = None  # the last detection (px), for drawing
    focal_px: float | None = None

    def to_json(self) -> dict[str, object]:
        return dict(self.__dict__)


def frame_to_gray(data: np.ndarray) -> np.ndarray:
    """uint8 grey of an RGB8 or raw (uint16) frame."""
    if data.dtype != np.uint8:
        d = data.astype(np.float64)
        hi = float(d.max()) if d.size else 0.0
        data = np.zeros(d.shape, np.uint8) if hi <= 0 else np.clip(d * (255.0 / hi), 0, 255).astype(np.uint8)
    return data if data.ndim == 2 else cv2.cvtColor(data, cv2.COLOR_RGB2GRAY)


class LiveFisheyeCalibration:
    """State machine of the live routine (module docs)."""

    def __init__(self, board: BoardSpec, image_size: tuple[int, int], *, still_px: float = 1.0,
                 still_frames: int = 3, cell_target: int = 12, min_views: int = 6,
                 target_rms: float = 0.5, target_coverage: float = 0.6,
                 image_circle: tuple[float, float, float] | None = None,
                 guess: tuple[np.ndarray, np.ndarray] | None = None) -> None:
        self.board = board
        self.image_size = image_size
        self.still_px, self.still_frames = float(still_px), int(still_frames)
        self.cell_target, self.min_views = int(cell_target), int(min_views)
        self.target_rms, self.target_coverage = float(target_rms), float(target_coverage)
        w, h = image_size
        self.circle = image_circle or (w / 2, h / 2, float(np.hypot(w, h) / 2))
        self.views: list[View] = []
        self.result: FisheyeResult | None = None
        self._recent: deque[np.ndarray] = deque(maxlen=self.still_frames)
        self._obj = board_object_points(board)
        self.guess = guess  # (K, D) start for the solver, e.g. fisheye.equidistant_guess
        self.progress = LiveProgress()
        self.progress.grid = self._grid().tolist()

    def _grid(self, extra: np.ndarray | None = None) -> np.ndarray:
        pts = [v.corners for v in self.views] + ([extra] if extra is not None else [])
        if not pts:
            return coverage_grid(np.zeros((0, 2)), self.circle, self.image_size)
        return coverage_grid(np.concatenate(pts), self.circle, self.image_size)

    def feed(self, image: np.ndarray, name: str | None = None) -> str:
        """Process one frame; returns the event ("no board", "moving", "accepted", ...)."""
        p = self.progress
        p.frames += 1
        corners = detect_board(frame_to_gray(image), self.board)
        p.last_corners = None if corners is None else np.round(corners, 2).tolist()
        if corners is None:
            self._recent.clear()
            return self._event("no board")
        if self._recent and self._recent[-1].shape == corners.shape:
            # A flipped detection order of a symmetric board is not motion: compare both orders.
            prev = self._recent[-1]
            if np.max(np.linalg.norm(corners[::-1] - prev, axis=1)) < np.max(np.linalg.norm(corners - prev, axis=1)):
                corners = corners[::-1].copy()
        self._recent.append(corners)
        if len(self._recent) < self.still_frames:
            return self._event("holding")
        first = self._recent[0]
        if max(float(np.max(np.linalg.norm(c - first, axis=1))) for c in self._recent) >= self.still_px:
            return self._event("moving")
        before = self._grid()
        cells = coverage_grid(corners, self.circle, self.image_size) > 0
        if not np.any(cells & (before >= 0) & (before < self.cell_target)):
            return self._event("no new coverage")
        self.views.append(View(name or f"live{p.frames:05d}", np.mean(self._recent, axis=0), self._obj))
        self._recent.clear()
        self._update()
        return self._event("accepted")

    def _set_coverage(self, views: list[View]) -> None:
        """Coverage fields of the progress from the corners of ``views``."""
        p = self.progress
        pts = np.concatenate([v.corners for v in views]) if views else np.zeros((0, 2))
        grid = coverage_grid(pts, self.circle, self.image_size)
        p.grid = grid.tolist()
        p.coverage_percent = 100.0 * int(np.count_nonzero(grid > 0)) / max(int(np.count_nonzero(grid >= 0)), 1)
        rings, sectors = grid.shape
        p.missing_regions = [f"ring {i + 1}/{rings}, sector {j + 1}/{sectors}"
                             for i in range(rings) for j in range(sectors) if grid[i, j] == 0]

    def _update(self) -> None:
        p = self.progress
        p.views = len(self.views)
        self._set_coverage(self.views)
        if len(self.views) >= self.min_views:
            try:
                self.result = calibrate_views(self.views, self.image_size, min_views=min(self.min_views, 4),
                                              image_circle=self.circle, guess=self.guess)
                p.rms_px = self.result.rms_px
                p.rejected = sorted(self.result.rejected)
                p.focal_px = float(0.5 * (self.result.model.K[0, 0] + self.result.model.K[1, 1]))
            except ValueError:
                self.result, p.rms_px, p.focal_px = None, None, None
        if self.result is not None and self.result.rejected:  # coverage counts only the views kept
            self._set_coverage([v for v in self.views if v.name not in self.result.rejected])
        p.good_enough = (len(self.views) >= self.min_views and p.rms_px is not None
                         and p.rms_px <= self.target_rms
                         and p.coverage_percent >= 100.0 * self.target_coverage)

    def _event(self, what: str) -> str:
        self.progress.last_event = what
        return what

    async def run(self, camera: Camera, *, max_frames: int = 1000, capture_timeout: float = 1.0,
                  stop_when_good: bool = True) -> LiveProgress:
        """Feed frames from an open ``camera`` until good enough or ``max_frames``."""
        import asyncio

        for _ in range(max_frames):
            frame: Frame = await camera.capture(capture_timeout)
            await asyncio.to_thread(self.feed, frame.data)
            if stop_when_good and self.progress.good_enough:
                break
        return self.progress
