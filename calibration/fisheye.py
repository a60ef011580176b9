"""Fisheye geometry from checkerboard views: detection, a robust OpenCV fisheye (KB4) solve,
per-view errors, coverage of the image circle and the field of view.

The model is OpenCV's fisheye (Kannala-Brandt with four coefficients):
``theta_d = theta (1 + k1 theta^2 + k2 theta^4 + k3 theta^6 + k4 theta^8)`` [1, eq. 6]. OpenCV 5
moved the flags to ``cv2.CALIB_*`` (``cv2.CALIB_RECOMPUTE_EXTRINSIC``, ``cv2.CALIB_FIX_SKEW``,
``cv2.CALIB_CHECK_COND``). Strong fisheyes make ``cv2.fisheye.calibrate`` assert in its
extrinsic initialisation (a homography that cannot represent views past ~80 degrees):
:func:`calibrate_views` catches ``cv2.error``, drops the offending view (or the view nearest the
rim when OpenCV does not say which), retries, then rejects outlier views by per-view RMS; the
views it could not initialise are then posed under the solved model and, where they agree,
refined together with the rest (a bundle adjustment on the same objective).

Dtype policy: corner coordinates float64 in this module (OpenCV gets float64 (1, N, 2/3)
arrays); images are whatever ``cv2`` reads (uint8 grey for detection).

References
----------
.. [1] J. Kannala, S. S. Brandt, "A generic camera model and calibration method for conventional,
   wide-angle, and fish-eye lenses", IEEE TPAMI 28(8), 2006.
"""

from __future__ import annotations

import re
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import cv2
import numpy as np

from lightprobe.core.calibration import FisheyeModel

__all__ = [
    "BoardSpec",
    "FisheyeResult",
    "View",
    "board_object_points",
    "calibrate_views",
    "coverage_grid",
    "detect_board",
    "equidistant_guess",
    "field_of_view_deg",
    "orient_corners",
    "parse_board",
    "view_rms",
]

FLAGS = cv2.CALIB_RECOMPUTE_EXTRINSIC | cv2.CALIB_CHECK_COND | cv2.CALIB_FIX_SKEW
CRITERIA = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 200, 1e-10)


@dataclass(frozen=True)
class BoardSpec:
    """A checkerboard: ``cols`` x ``rows`` inner corners, squares of ``square`` (any unit)."""

    cols: int
    rows: int
    square: float = 1.0

    @property
    def n_corners(self) -> int:
        return self.cols * self.rows


def parse_board(text: str, square: float = 1.0) -> BoardSpec:
    """Parse ``COLSxROWS`` (inner corners, CONVENTIONS.md). Raises ValueError on bad input."""
    m = re.fullmatch(r"\s*(\d+)\s*[xX]\s*(\d+)\s*", text)
    if not m or int(m.group(1)) < 2 or int(m.group(2)) < 2:
        raise ValueError(f"board {text!r} is not COLSxROWS with at least 2x2 inner corners")
    if not np.isfinite(square) or square <= 0:
        raise ValueError(f"square size {square!r} must be positive")
    return BoardSpec(int(m.group(1)), int(m.group(2)), float(square))


def board_object_points(board: BoardSpec) -> np.ndarray:
    """Board corners (N, 3) float64 on z = 0, row-major, in the order OpenCV detects them."""
    j, i = np.mgrid[0 : board.rows, 0 : board.cols]
    pts = np.stack([i.ravel(), j.ravel(), np.zeros(board.n_corners)], axis=-1)
    return pts.astype(np.float64) * board.square


def detect_board(image: np.ndarray, board: BoardSpec, *, thorough: bool = True,
                 accurate: bool = False) -> np.ndarray | None:
    """Sub-pixel inner corners (N, 2) float64 of ``board`` in ``image``, or None.

    Default: the fast quad detector ``cv2.findChessboardCorners`` + ``cornerSubPix``, then
    (``thorough``) the sector-based ``cv2.findChessboardCornersSB`` with ``CALIB_CB_ACCURACY``,
    which finds boards the quad detector misses under strong fisheye distortion (it is much
    slower, so a live loop may skip it), its corners polished by a small ``cornerSubPix``.
    ``accurate`` tries the SB detector first: its corners are less biased on small, strongly
    distorted squares. An all-black or constant image
    returns None at once.
    """
    gray = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    if gray.dtype != np.uint8:
        g = np.nan_to_num(gray.astype(np.float64))
        span = g.max() - g.min()
        gray = np.zeros(g.shape, np.uint8) if span <= 0 else ((g - g.min()) * (255 / span)).astype(np.uint8)
    if int(gray.max()) - int(gray.min()) < 16:  # degenerate: no contrast, no board
        return None
    size = (board.cols, board.rows)

    def quads() -> tuple[bool, np.ndarray | None]:
        ok, c = cv2.findChessboardCorners(
            gray, size, flags=cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE | cv2.CALIB_CB_FAST_CHECK)
        if ok:
            c = cv2.cornerSubPix(gray, c, (5, 5), (-1, -1),
                                 (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 50, 1e-3))
        return bool(ok), c

    def sectors() -> tuple[bool, np.ndarray | None]:
        ok, c = cv2.findChessboardCornersSB(gray, size, flags=cv2.CALIB_CB_ACCURACY | cv2.CALIB_CB_NORMALIZE_IMAGE)
        if ok:
            # SB's corners sit slightly inside the true saddle where squares are small and
            # compressed (fisheye rim): a 7 x 7 saddle refinement removes it. Measured: the
            # simulated 190-degree lens, radial bias at r = 200-300 px -0.047 -> -0.003 px; the
            # real lim_8x6 photos (SB path), focal length vs the Ceres result +0.28% -> +0.10%. A
            # corner the polish moves by more than half a pixel (a saddle squeezed past the rim)
            # keeps SB's position: without that guard the 190-degree lens lost views.
            c0 = np.ascontiguousarray(c, np.float32).reshape(-1, 1, 2)
            c1 = cv2.cornerSubPix(gray, c0.copy(), (3, 3), (-1, -1),
                                  (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 100, 1e-4))
            moved = np.linalg.norm((c1 - c0).reshape(-1, 2), axis=1) > 0.5
            c = np.where(moved[:, None, None], c0, c1)
        return bool(ok), c

    tries = [sectors, quads] if accurate else ([quads, sectors] if thorough else [quads])
    ok, corners = False, None
    for fn in tries:
        ok, corners = fn()
        if ok:
            break
    if not ok or corners is None:
        return None
    pts = np.asarray(corners, dtype=np.float64).reshape(-1, 2)
    return pts if pts.shape[0] == board.n_corners else None


def orient_corners(image: np.ndarray, corners: np.ndarray, board: BoardSpec) -> np.ndarray:
    """Order corners so the first one has a *black* square diagonally outside the board.

    OpenCV may return a board's corners in either of the two 180-degree-related orders. For a
    board with one even and one odd corner count the two outer corners differ in colour, which
    fixes the board's x axis (needed for a heading from a floor board). The square centre is
    extrapolated half a square step beyond each end along both grid directions.
    """
    gray = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    c = np.asarray(corners, np.float64).reshape(board.rows, board.cols, 2)

    def outer(a: np.ndarray, right: np.ndarray, down: np.ndarray) -> float:
        p = a - 0.5 * (right - a) - 0.5 * (down - a)
        x, y = int(np.rint(p[0])), int(np.rint(p[1]))
        if not (0 <= x < gray.shape[1] and 0 <= y < gray.shape[0]):
            return float("nan")
        return float(gray[max(y - 1, 0) : y + 2, max(x - 1, 0) : x + 2].mean())

    first = outer(c[0, 0], c[0, 1], c[1, 0])
    last = outer(c[-1, -1], c[-1, -2], c[-2, -1])
    if np.isfinite(first) and np.isfinite(last) and first > last:
        return np.asarray(corners, np.float64).reshape(-1, 2)[::-1].copy()
    return np.asarray(corners, np.float64).reshape(-1, 2)


@dataclass
class View:
    """One detected board view: a name (file), its corners (N, 2) and the board points (N, 3)."""

    name: str
    corners: np.ndarray
    object_points: np.ndarray


@dataclass
class FisheyeResult:
    """Outcome of :func:`calibrate_views`."""

    model: FisheyeModel
    rms_px: float
    per_view_rms: dict[str, float]
    used: list[str]
    rejected: dict[str, str]  # name -> reason
    coverage: np.ndarray  # (rings, sectors) corner counts over the image circle
    coverage_fraction: float
    image_circle: tuple[float, float, float]  # cx, cy, radius (px)
    rvecs: list[np.ndarray] = field(default_factory=list)
    tvecs: list[np.ndarray] = field(default_factory=list)

    def missing_regions(self) -> list[str]:
        """Human-readable names of coverage cells without corners ("ring 3/4, sector 5/8")."""
        rings, sectors = self.coverage.shape
        return [f"ring {i + 1}/{rings}, sector {j + 1}/{sectors}"
                for i in range(rings) for j in range(sectors) if self.coverage[i, j] == 0]


def _solve(views: Sequence[View], image_size: tuple[int, int], flags: int,
           guess: tuple[np.ndarray, np.ndarray] | None = None
           ) -> tuple[float, np.ndarray, np.ndarray, list[np.ndarray], list[np.ndarray]]:
    obj = [v.object_points.reshape(1, -1, 3).astype(np.float64) for v in views]
    img = [v.corners.reshape(1, -1, 2).astype(np.float64) for v in views]
    K: np.ndarray = np.zeros((3, 3))
    D: np.ndarray = np.zeros((4, 1))
    if guess is not None:
        K, D = guess[0].copy(), guess[1].reshape(4, 1).copy()
        flags |= cv2.CALIB_USE_INTRINSIC_GUESS
    rms, K_out, D_out, rvecs, tvecs = cv2.fisheye.calibrate(obj, img, image_size, K, D, flags=flags,
                                                            criteria=CRITERIA)
    K, D = np.asarray(K_out, np.float64), np.asarray(D_out, np.float64)
    return float(rms), K, D.reshape(4), list(rvecs), list(tvecs)


def view_rms(view: View, K: np.ndarray, D: np.ndarray, rvec: np.ndarray, tvec: np.ndarray) -> float:
    """Root-mean-square reprojection error (px) of one view."""
    proj, _ = cv2.fisheye.projectPoints(view.object_points.reshape(1, -1, 3), rvec, tvec, K, D)
    d = proj.reshape(-1, 2) - view.corners
    return float(np.sqrt(np.mean(np.sum(d * d, axis=1))))


def _offending_index(err: cv2.error, n: int) -> int | None:
    m = re.search(r"input array (\d+)", str(err))
    if m and int(m.group(1)) < n:
        return int(m.group(1))
    return None


def _rim_index(views: Sequence[View], image_size: tuple[int, int]) -> int:
    return int(np.argmax([_rim_distance(v, image_size) for v in views]))


Solution = tuple[float, np.ndarray, np.ndarray, list[np.ndarray], list[np.ndarray]]


def calibrate_views(
    views: Sequence[View],
    image_size: tuple[int, int],
    *,
    min_views: int = 4,
    outlier_factor: float = 3.0,
    outlier_floor_px: float = 1.0,
    max_rms_px: float = 1.0,
    image_circle: tuple[float, float, float] | None = None,
    progress: Callable[[str], None] | None = None,
    guess: tuple[np.ndarray, np.ndarray] | None = None,
) -> FisheyeResult:
    """Robust fisheye calibration: retry past InitExtrinsics asserts, reject outlier views.

    First :func:`_robust_loop` on all views. If that fails or its RMS exceeds ``max_rms_px``
    (a wrong detection can drag the whole solve away, after which per-view errors no longer
    single it out), :func:`_grow` restarts from the central views and adds the others while
    they agree with the model. Raises ValueError when no consistent set of ``min_views`` exists.

    ``guess`` (K, D) initialises the solver (``CALIB_USE_INTRINSIC_GUESS``), e.g.
    :func:`equidistant_guess` from the image circle: OpenCV's own start (f = max(w, h) / pi)
    is far off for a circular fisheye on a small sensor and its extrinsic initialisation
    then fails on most views.
    """
    say = progress or (lambda _msg: None)
    starts: list[tuple[np.ndarray, np.ndarray] | None] = [guess]
    if guess is None:
        # OpenCV's own start (f = max(w, h) / pi) fails on some lenses and not on others, and
        # which depends even on the CPU's floating point: if it fails, start from equidistant
        # lenses of common fields of view filling the image circle (given, or the sensor's
        # inscribed circle), the first that solves consistently wins
        w, h = image_size
        circle = image_circle or (w / 2.0, h / 2.0, min(w, h) / 2.0)
        starts += [equidistant_guess(circle, fov) for fov in _START_FOVS]
    last: ValueError | None = None
    for k, start in enumerate(starts):
        if k:
            say(f"retrying from an equidistant {_START_FOVS[k - 1]:.0f}-degree lens filling the image circle")
        rejected: dict[str, str] = {}
        try:
            active, sol, errs = _solve_from(views, image_size, min_views, outlier_factor, outlier_floor_px,
                                            max_rms_px, rejected, say, start)
        except ValueError as e:
            last = e
            continue
        if sol[0] > max_rms_px and k + 1 < len(starts):
            continue
        active, sol, errs = _readmit(views, active, sol, errs, rejected, outlier_factor, outlier_floor_px, say)
        return _result(active, image_size, *sol, errs, rejected, image_circle)
    assert last is not None
    raise last


_START_FOVS = (190.0, 180.0, 210.0, 160.0, 230.0, 140.0, 120.0)


def _solve_from(views: Sequence[View], image_size: tuple[int, int], min_views: int, outlier_factor: float,
                outlier_floor_px: float, max_rms_px: float, rejected: dict[str, str], say: Callable[[str], None],
                guess: tuple[np.ndarray, np.ndarray] | None) -> tuple[list[View], Solution, np.ndarray]:
    """One start: the robust loop over all views, else growth from the central views."""
    try:
        active, sol, errs = _robust_loop(list(views), image_size, min_views, outlier_factor,
                                         outlier_floor_px, rejected, say, guess)
        if sol[0] <= max_rms_px:
            return active, sol, errs
    except ValueError:
        pass
    say("solve over all views is inconsistent: growing from the central views")
    rejected.clear()
    return _grow(views, image_size, min_views, outlier_factor, outlier_floor_px, max_rms_px, rejected, say, guess)


_UNINITIALISED = ("ill-conditioned (InitExtrinsics)", "solver failed near the rim")


def _readmit(views: Sequence[View], active: list[View], sol: Solution, errs: np.ndarray,
             rejected: dict[str, str], outlier_factor: float, outlier_floor_px: float,
             say: Callable[[str], None]) -> tuple[list[View], Solution, np.ndarray]:
    """Give the views OpenCV could not *initialise* a second chance: its homography start fails
    for boards far off-axis (past ~80 degrees; where exactly depends on the CPU's floating point,
    so an AMD and an Intel machine reject different views), and those are the views a fisheye
    calibration needs most at its rim. Each is posed under the solved model (fisheye solvePnP);
    those within the outlier limit join, and intrinsics and every pose are refined together
    (:func:`_bundle_adjust`, the objective ``cv2.fisheye.calibrate`` minimises). A joined view
    that the refined model then fits worse than the limit leaves again; nothing joins unless the
    refinement converges."""
    limit = max(outlier_factor * float(np.median(errs)), outlier_floor_px)
    names = {v.name for v in active}
    _, K, D, rvecs, tvecs = sol
    joining: list[tuple[View, np.ndarray, np.ndarray]] = []
    for v in views:
        if v.name in names or rejected.get(v.name) not in _UNINITIALISED:
            continue
        e, rv, tv = _pnp_pose(v, K, D)
        if e <= limit:
            joining.append((v, rv, tv))
    for _ in range(3):
        if not joining:
            return active, sol, errs
        allv = active + [j[0] for j in joining]
        refined = _bundle_adjust(allv, K, D, list(rvecs) + [j[1] for j in joining], list(tvecs) + [j[2] for j in joining])
        if refined is None:
            return active, sol, errs
        new_errs = np.array([view_rms(v, refined[1], refined[2], r, t)
                             for v, r, t in zip(allv, refined[3], refined[4], strict=True)])
        bad = {allv[i].name for i in range(len(active), len(allv)) if new_errs[i] > limit}
        if bad:
            joining = [j for j in joining if j[0].name not in bad]
            continue
        for v, _r, _t in joining:
            say(f"readmitted {v.name}: posed under the solved model, refined with the others")
            del rejected[v.name]
        return allv, refined, new_errs
    return active, sol, errs


def _bundle_adjust(views: Sequence[View], K: np.ndarray, D: np.ndarray, rvecs: list[np.ndarray],
                   tvecs: list[np.ndarray]) -> Solution | None:
    """Levenberg-Marquardt over (fx, fy, cx, cy, k1..k4) and every view's pose, skew fixed at 0:
    the sum of squared reprojection errors of ``cv2.fisheye.projectPoints``, with its analytic
    Jacobian. ``None`` if it does not converge to finite values."""
    from scipy.optimize import least_squares

    obj = [v.object_points.reshape(1, -1, 3).astype(np.float64) for v in views]
    img = [v.corners.reshape(-1).astype(np.float64) for v in views]
    n = len(views)
    rows = np.cumsum([0] + [o.shape[1] * 2 for o in obj])

    def unpack(x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        k = np.array([[x[0], 0.0, x[2]], [0.0, x[1], x[3]], [0.0, 0.0, 1.0]])
        return k, x[4:8].copy(), x[8:].reshape(n, 6)

    def fun(x: np.ndarray) -> np.ndarray:
        k, d, poses = unpack(x)
        return np.concatenate([cv2.fisheye.projectPoints(o, p[:3].reshape(3, 1), p[3:].reshape(3, 1), k, d)[0].reshape(-1)
                               - c for o, p, c in zip(obj, poses, img, strict=True)])

    def jac(x: np.ndarray) -> np.ndarray:
        k, d, poses = unpack(x)
        J = np.zeros((int(rows[-1]), x.size))
        for j, (o, p) in enumerate(zip(obj, poses, strict=True)):
            _, jj = cv2.fisheye.projectPoints(o, p[:3].reshape(3, 1), p[3:].reshape(3, 1), k, d)
            J[rows[j]:rows[j + 1], :8] = jj[:, :8]
            J[rows[j]:rows[j + 1], 8 + 6 * j:14 + 6 * j] = jj[:, 8:14]
        return J

    parts: list[np.ndarray] = [np.array([K[0, 0], K[1, 1], K[0, 2], K[1, 2]], np.float64),
                               np.asarray(D, np.float64).reshape(4)]
    parts += [np.concatenate([np.asarray(r, np.float64).reshape(3), np.asarray(t, np.float64).reshape(3)])
              for r, t in zip(rvecs, tvecs, strict=True)]
    x0 = np.concatenate(parts)
    try:
        res = least_squares(fun, x0, jac=jac, method="lm", x_scale="jac", xtol=1e-12, ftol=1e-12, max_nfev=200)
    except (cv2.error, ValueError, np.linalg.LinAlgError):
        return None
    if not (res.success and np.all(np.isfinite(res.x)) and res.x[0] > 0 and res.x[1] > 0):
        return None
    k, d, poses = unpack(res.x)
    rms = float(np.sqrt(np.mean(res.fun ** 2) * 2))  # per corner, as cv2.fisheye.calibrate reports
    return rms, k, d, [p[:3].reshape(3, 1) for p in poses], [p[3:].reshape(3, 1) for p in poses]


def _robust_loop(active: list[View], image_size: tuple[int, int], min_views: int, outlier_factor: float,
                 outlier_floor_px: float, rejected: dict[str, str], say: Callable[[str], None],
                 guess: tuple[np.ndarray, np.ndarray] | None = None) -> tuple[list[View], Solution, np.ndarray]:
    """Solve, dropping views OpenCV cannot initialise and per-view RMS outliers.

    Solve with RECOMPUTE_EXTRINSIC | FIX_SKEW; on ``cv2.error`` ask CHECK_COND which view is
    ill-conditioned ("input array i"), else drop the view reaching nearest the rim, and retry.
    After a solve, a view whose RMS exceeds ``max(outlier_factor x median, outlier_floor_px)`` is
    dropped (worst first) and the solve repeated.
    """
    n0 = len(active)
    for _ in range(n0 + 1):
        if len(active) < min_views:
            break
        try:
            rms, K, D, rvecs, tvecs = _solve(active, image_size, FLAGS & ~cv2.CALIB_CHECK_COND, guess)
        except cv2.error as e:
            i = _offending_index(e, len(active))
            if i is None:  # ask CHECK_COND which view is ill-conditioned
                try:
                    _solve(active, image_size, FLAGS, guess)
                except cv2.error as e2:
                    i = _offending_index(e2, len(active))
            reason = "ill-conditioned (InitExtrinsics)" if i is not None else "solver failed near the rim"
            i = _rim_index(active, image_size) if i is None else i
            rejected[active[i].name] = reason
            say(f"rejected {active[i].name}: {reason}")
            del active[i]
            continue
        if not (np.all(np.isfinite(K)) and np.all(np.isfinite(D)) and K[0, 0] > 0 and K[1, 1] > 0):
            i = _rim_index(active, image_size)
            rejected[active[i].name] = "solver diverged"
            del active[i]
            continue
        errs = np.array([view_rms(v, K, D, r, t) for v, r, t in zip(active, rvecs, tvecs, strict=True)])
        limit = max(outlier_factor * float(np.median(errs)), outlier_floor_px)
        worst = int(np.argmax(errs))
        if errs[worst] > limit and len(active) > min_views:
            rejected[active[worst].name] = f"outlier view: rms {errs[worst]:.2f} px > {limit:.2f} px"
            say(f"rejected {active[worst].name}: rms {errs[worst]:.2f} px")
            del active[worst]
            continue
        return active, (rms, K, D, rvecs, tvecs), errs
    raise ValueError(f"fisheye calibration failed: {len(active)} usable views left "
                     f"(need {min_views}); rejected: {', '.join(rejected) or 'none'}")


def _pnp_pose(view: View, K: np.ndarray, D: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """(RMS, rvec, tvec) of one view posed by ``cv2.fisheye.solvePnP`` under a fixed model (RMS
    inf on failure)."""
    none = np.zeros((3, 1))
    try:
        ok, rvec, tvec = cv2.fisheye.solvePnP(view.object_points.reshape(-1, 1, 3),
                                              view.corners.reshape(-1, 1, 2), K, D.reshape(4, 1))
    except cv2.error:
        return float("inf"), none, none
    if not ok:
        return float("inf"), none, none
    e = view_rms(view, K, D, rvec, tvec)
    return (e if np.isfinite(e) else float("inf")), rvec, tvec


def _pnp_rms(view: View, K: np.ndarray, D: np.ndarray) -> float:
    """RMS of one view posed by ``cv2.fisheye.solvePnP`` under a fixed model (inf on failure)."""
    return _pnp_pose(view, K, D)[0]


def _grow(views: Sequence[View], image_size: tuple[int, int], min_views: int, outlier_factor: float,
          outlier_floor_px: float, max_rms_px: float, rejected: dict[str, str], say: Callable[[str], None],
          guess: tuple[np.ndarray, np.ndarray] | None = None) -> tuple[list[View], Solution, np.ndarray]:
    """Seed with the most central views, then add views that agree with the current model.

    Each round poses every pending view with the current intrinsics (fisheye solvePnP); those
    under the outlier limit join and the set is re-solved; views that never agree are rejected.
    """
    order = sorted(views, key=lambda v: _rim_distance(v, image_size))
    sol: Solution | None = None
    # Seed: the smallest central set that solves consistently (near-frontal views alone are
    # often ill-conditioned, so the seed widens until it works).
    for seed_n in range(min(len(order), max(min_views, 6)), len(order) + 1, 3):
        seed_rej: dict[str, str] = {}
        try:
            active, sol, errs = _robust_loop(order[:seed_n], image_size, min_views, outlier_factor,
                                             outlier_floor_px, seed_rej, say, guess)
        except ValueError:
            continue
        if sol[0] <= max_rms_px:
            rejected.update(seed_rej)
            break
        sol = None
    if sol is None:
        raise ValueError("fisheye calibration failed: no consistent set of central views")
    pending = [v for v in order[seed_n:] if v.name not in rejected]
    last: dict[str, float] = {}
    while pending:
        limit = max(outlier_factor * float(np.median(errs)), outlier_floor_px)
        last = {v.name: _pnp_rms(v, sol[1], sol[2]) for v in pending}
        joining = [v for v in pending if last[v.name] <= limit]
        if not joining:
            break
        trial_rej: dict[str, str] = {}
        try:
            a2, s2, e2 = _robust_loop(active + joining, image_size, min_views, outlier_factor,
                                      outlier_floor_px, trial_rej, say, guess=(sol[1], sol[2]))
        except ValueError:
            break
        if s2[0] > max_rms_px:
            break
        active, sol, errs = a2, s2, e2
        rejected.update(trial_rej)
        pending = [v for v in pending if v not in joining]
    for v in pending:
        rejected[v.name] = f"inconsistent with the model: rms {last.get(v.name, float('inf')):.1f} px"
        say(f"rejected {v.name}: {rejected[v.name]}")
    return active, sol, errs


def _rim_distance(view: View, image_size: tuple[int, int]) -> float:
    c = np.array([image_size[0] / 2, image_size[1] / 2])
    return float(np.max(np.linalg.norm(view.corners - c, axis=1)))


def _result(active: list[View], image_size: tuple[int, int], rms: float, K: np.ndarray,
            D: np.ndarray, rvecs: list[np.ndarray], tvecs: list[np.ndarray], errs: np.ndarray,
            rejected: dict[str, str], image_circle: tuple[float, float, float] | None
            ) -> FisheyeResult:
    """Package a converged solve: coverage over the image circle, field of view."""
    w, h = image_size
    if image_circle is None:  # full-frame fisheye: the circle through the farthest image corner
        cx, cy = float(K[0, 2]), float(K[1, 2])
        radius = float(max(np.hypot(x - cx, y - cy) for x in (0, w) for y in (0, h)))
        image_circle = (cx, cy, radius)
    model = FisheyeModel(image_size=(w, h), K=np.asarray(K, np.float64), D=np.asarray(D, np.float64))
    fov = field_of_view_deg(model, image_circle[2])
    model = FisheyeModel(image_size=(w, h), K=model.K, D=model.D, fov_deg=fov, rms_px=rms,
                         views_used=len(active), views_rejected=tuple(rejected))
    grid = coverage_grid(np.concatenate([v.corners for v in active]), image_circle, image_size)
    inside = grid >= 0
    frac = int(np.count_nonzero(grid > 0)) / max(int(np.count_nonzero(inside)), 1)
    return FisheyeResult(model, rms, {v.name: float(e) for v, e in zip(active, errs, strict=True)},
                         [v.name for v in active], rejected, grid, frac, image_circle, rvecs, tvecs)


def equidistant_guess(circle: tuple[float, float, float], fov_deg: float) -> tuple[np.ndarray, np.ndarray]:
    """(K, D) of an equidistant fisheye whose image circle ``(cx, cy, radius)`` spans ``fov_deg``:
    ``f = radius / (fov / 2)`` (rad), D = 0; a start for :func:`calibrate_views`."""
    cx, cy, radius = (float(v) for v in circle)
    if not (radius > 0 and 0 < fov_deg <= 360):
        raise ValueError(f"image circle radius {radius} / field of view {fov_deg} deg out of range")
    f = radius / np.radians(fov_deg / 2)
    return np.array([[f, 0.0, cx], [0.0, f, cy], [0.0, 0.0, 1.0]]), np.zeros(4)


def coverage_grid(corners: np.ndarray, circle: tuple[float, float, float], image_size: tuple[int, int],
                  rings: int = 4, sectors: int = 8) -> np.ndarray:
    """Corner counts in equal-area rings x angular sectors of the image circle.

    Cells that lie entirely outside the image (a circle larger than the sensor) are -1 so they do
    not count as missing. Ring i spans radii ``R sqrt(i/rings) .. R sqrt((i+1)/rings)``.
    """
    cx, cy, radius = circle
    pts = np.asarray(corners, np.float64).reshape(-1, 2)
    r = np.hypot(pts[:, 0] - cx, pts[:, 1] - cy) / radius
    a = np.mod(np.arctan2(pts[:, 1] - cy, pts[:, 0] - cx), 2 * np.pi)
    ri = np.clip((r * r * rings).astype(int), 0, rings - 1)
    si = np.clip((a / (2 * np.pi) * sectors).astype(int), 0, sectors - 1)
    grid = np.zeros((rings, sectors), np.int64)
    ok = r <= 1.0
    np.add.at(grid, (ri[ok], si[ok]), 1)
    # Mark cells whose sample points all fall outside the sensor.
    w, h = image_size
    for i in range(rings):
        for j in range(sectors):
            rr = radius * np.sqrt((i + np.linspace(0.05, 0.95, 5)) / rings)
            aa = 2 * np.pi * (j + np.linspace(0.05, 0.95, 5)) / sectors
            x = cx + rr[:, None] * np.cos(aa[None, :])
            y = cy + rr[:, None] * np.sin(aa[None, :])
            if not np.any((x >= 0) & (x < w) & (y >= 0) & (y < h)) and grid[i, j] == 0:
                grid[i, j] = -1
    return grid


def field_of_view_deg(model: FisheyeModel, radius_px: float) -> float:
    """Full field of view (deg) of the image circle of ``radius_px`` around the principal point.

    theta_d = r / f (f the mean focal length), theta from inverting the KB4 polynomial [1]; if the
    polynomial turns over before r (an extrapolated fit), the turning point bounds the angle.
    """
    f = 0.5 * (model.K[0, 0] + model.K[1, 1])
    td = radius_px / f
    t = np.linspace(0.0, np.pi, 3601)
    dist = model.distort_theta(t)
    mono = np.concatenate([[True], np.diff(dist) > 0])
    last = int(np.argmin(mono)) if not np.all(mono) else len(t)
    t, dist = t[:last], dist[:last]
    if td >= dist[-1]:
        return float(np.degrees(2 * t[-1]))
    return float(np.degrees(2 * np.interp(td, dist, t)))
