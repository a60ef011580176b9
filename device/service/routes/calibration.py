"""Live fisheye calibration through the probe service: routes under ``/api/v1/calibration``.

- ``GET  /api/v1/calibration``: the calibration serving now (id, summary) and the store history.
- ``POST /api/v1/calibration/live`` (token): start a session. Body (JSON, all optional but
  ``board``): ``{"board": {"cols": 9, "rows": 6, "square": 0.04}, "targets": {"min_views": 6,
  "rms_px": 0.5, "coverage": 0.6}, "exposure_s": null, "timeout_s": 900, "idle_timeout_s": 120}``.
  The runner pauses the light pipeline (:meth:`lightprobe.device.service.runner.Runner.camera_lease`:
  lights stay served with ``stale: true``, ``/status`` shows the camera ``calibrating``); the
  session meters once (unless ``exposure_s`` is given), then grabs frames at that fixed exposure
  and feeds :class:`lightprobe.calibration.live.LiveFisheyeCalibration`.
- ``GET  /api/v1/calibration/live``: progress (views accepted/rejected, coverage grid and
  percent, RMS, ``good_enough``, the last detection's corners for drawing).
- ``GET  /api/v1/calibration/live/frame.jpg``: the last frame the session saw.
- ``POST /api/v1/calibration/live/commit`` (token): 409 until good enough; then the solve is
  written to the calibration store (atomic, :mod:`lightprobe.calibration.store`) and the pipeline restarts on
  it. A failed solve or write keeps the previous calibration serving (the session ends).
- ``DELETE /api/v1/calibration/live`` (token): cancel; the pipeline resumes.

At most one session runs (409 for a second). A session ends by itself after ``timeout_s`` or
when nobody polled it for ``idle_timeout_s``. Blocking work (detection, solves, the store, JPEG)
runs in worker threads. The technician's page is ``/calibrate`` (``static/calibrate.html`` + ``calibrate.js``).
Wire it with ``add_routes(app, state_dir)``.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import logging
import math
import secrets
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from aiohttp import web

from lightprobe.core.errors import InputError
from lightprobe.device.service.errors import ApiError
from lightprobe.device.service.state import STATE, ServiceState

__all__ = ["LiveSession", "add_routes"]

log = logging.getLogger(__name__)

ROUTE = "/api/v1/calibration"
FINAL = ("committed", "cancelled", "expired", "failed")


@dataclass
class LiveSession:
    """One live calibration session (state shared by its task and the handlers)."""

    id: str
    live: Any  # lightprobe.calibration.live.LiveFisheyeCalibration
    base: Any  # the Calibration serving when the session started
    circle: tuple[float, float, float]
    targets: dict[str, float]
    exposure_s: float | None
    timeout_s: float
    idle_timeout_s: float
    state: str = "starting"  # metering, capturing, committing, then one of FINAL
    error: str | None = None
    committed: dict[str, Any] | None = None
    started: float = field(default_factory=time.monotonic)
    last_poll: float = field(default_factory=time.monotonic)
    stop: str | None = None  # "commit" | "cancel" once asked
    frame: np.ndarray | None = None
    frame_no: int = 0
    jpeg: tuple[int, bytes] | None = None
    task: asyncio.Task[None] | None = None
    leased: asyncio.Event = field(default_factory=asyncio.Event)  # the camera is ours

    def to_json(self) -> dict[str, Any]:
        p = self.live.progress
        now = time.monotonic()
        rings, sectors = np.asarray(p.grid).shape if p.grid else (0, 0)
        return {
            "session": self.id, "active": self.state not in FINAL, "state": self.state, "error": self.error,
            "board": dataclasses.asdict(self.live.board), "targets": self.targets,
            "exposure_s": self.exposure_s, "frames": p.frames, "views": p.views,
            "views_rejected": len(p.rejected), "rejected": p.rejected,
            "coverage": {"percent": round(p.coverage_percent, 2), "grid": p.grid, "rings": rings,
                         "sectors": sectors, "missing": p.missing_regions},
            "rms_px": p.rms_px, "focal_px": p.focal_px, "good_enough": p.good_enough,
            "last_event": p.last_event, "last_corners": p.last_corners,
            "image_size": list(self.live.image_size), "image_circle": list(self.circle),
            "age_s": round(now - self.started, 3),
            "expires_in_s": round(max(0.0, min(self.started + self.timeout_s,
                                                   self.last_poll + self.idle_timeout_s) - now), 3),
            "committed": self.committed,
        }


@dataclass
class Desk:
    """The calibration desk on the app: the store's state dir and the (last) session."""

    state_dir: Path | None
    session: LiveSession | None = None
    lock: asyncio.Lock = field(default_factory=asyncio.Lock)


DESK: web.AppKey[Desk] = web.AppKey("lightprobe_calibration_desk", Desk)


# ---- request parsing ------------------------------------------------------------------------------
def _number(d: dict[str, Any], key: str, prefix: str, lo: float, hi: float, default: float | None,
            integer: bool = False) -> float | None:
    name = f"{prefix}{key}"
    v = d.get(key, default)
    if v is None:
        if default is not None:  # an explicit null where a number (or the default) belongs
            kind = "an integer" if integer else "a number"
            raise InputError(f"{name} must be {kind} in [{lo:g}, {hi:g}], got null", param=name)
        return None  # absent or null with no default: exposure_s meters, cols/rows are checked after
    if integer and isinstance(v, float) and v.is_integer():  # JSON's 6.0 is the integer 6
        v = int(v)
    ok = isinstance(v, int) if integer else isinstance(v, int | float)
    if isinstance(v, bool) or not ok or not math.isfinite(float(v)) or not lo <= float(v) <= hi:
        kind = "an integer" if integer else "a number"
        raise InputError(f"{name} must be {kind} in [{lo:g}, {hi:g}], got {str(v)[:40]!r}", param=name)
    return float(v)


def _object(body: dict[str, Any], key: str, required: bool = False) -> dict[str, Any]:
    v = body.get(key)
    if v is None and not required and key not in body:
        return {}
    if not isinstance(v, dict):
        raise InputError(f"{key} must be an object", param=key)
    return v


def parse_start(body: Any) -> dict[str, Any]:
    """Validate a POST /live body; returns the settings. Raises InputError naming the field."""
    if not isinstance(body, dict):
        raise InputError("body must be a JSON object", param="body")
    unknown = set(body) - {"board", "targets", "exposure_s", "timeout_s", "idle_timeout_s"}
    if unknown:
        raise InputError(f"unknown field {sorted(unknown)[0][:40]!r}", param=sorted(unknown)[0][:40])
    b = _object(body, "board", required=True)
    t = _object(body, "targets")
    cols = int(_number(b, "cols", "board.", 2, 64, None, integer=True) or 0)
    rows = int(_number(b, "rows", "board.", 2, 64, None, integer=True) or 0)
    if not cols or not rows:
        raise InputError("board needs cols and rows (inner corners)", param="board.cols" if not cols else "board.rows")
    return {
        "cols": cols, "rows": rows, "square": _number(b, "square", "board.", 1e-6, 1e4, 1.0),
        "min_views": int(_number(t, "min_views", "targets.", 3, 200, 6, integer=True) or 6),
        "rms_px": _number(t, "rms_px", "targets.", 0.01, 10.0, 0.5),
        "coverage": _number(t, "coverage", "targets.", 0.0, 1.0, 0.6),
        "exposure_s": _number(body, "exposure_s", "", 1e-6, 10.0, None),
        "timeout_s": _number(body, "timeout_s", "", 5.0, 7200.0, 900.0),
        "idle_timeout_s": _number(body, "idle_timeout_s", "", 2.0, 3600.0, 120.0),
    }


async def _json_body(request: web.Request) -> Any:
    import json

    if request.content_type != "application/json":
        raise InputError(f"Content-Type must be application/json, got {request.content_type!r}",
                         param="Content-Type")
    try:
        return json.loads(await request.read())
    except (ValueError, UnicodeDecodeError, RecursionError) as e:
        raise InputError(f"body is not valid JSON: {str(e)[:80]}", param="body") from None


# ---- the serving calibration ----------------------------------------------------------------------
def _serving(st: ServiceState, desk: Desk) -> Any:
    """The calibration the pipeline uses (blocking: may read the store)."""
    cal = getattr(st.runner.pipeline, "calibration", None)
    if cal is not None or desk.state_dir is None:
        return cal
    from lightprobe.calibration.store import load_calibration

    try:
        return load_calibration(desk.state_dir, st.camera)
    except (InputError, OSError):
        return None


def image_circle(cal: Any, size: tuple[int, int]) -> tuple[float, float, float]:
    """(cx, cy, radius) of the image circle: the lens mask, else the fisheye's field of view,
    else the circle inscribed in the frame."""
    w, h = size
    if cal is not None and cal.mask is not None:
        return float(cal.mask.center[0]), float(cal.mask.center[1]), float(cal.mask.radius_px)
    fe = getattr(cal, "fisheye", None)
    if fe is not None:
        edge = fe.project(np.array([np.sin(np.radians(fe.fov_deg / 2)), 0.0, np.cos(np.radians(fe.fov_deg / 2))]))
        return float(fe.K[0, 2]), float(fe.K[1, 2]), float(abs(edge[0] - fe.K[0, 2]))
    return w / 2, h / 2, min(w, h) / 2


def _summary(cal: Any) -> dict[str, Any] | None:
    if cal is None:
        return None
    out: dict[str, Any] = {"id": cal.id, "source": cal.source, "created": cal.created,
                           "sections": list(cal.body())}
    if cal.fisheye is not None:
        fe = cal.fisheye
        out["fisheye"] = {"fx": float(fe.K[0, 0]), "fy": float(fe.K[1, 1]), "cx": float(fe.K[0, 2]),
                          "cy": float(fe.K[1, 2]), "fov_deg": float(fe.fov_deg), "rms_px": fe.rms_px,
                          "image_size": list(fe.image_size), "views_used": fe.views_used}
    return out


def _history(state_dir: Path | None) -> list[dict[str, Any]]:
    from lightprobe.calibration.store import CalibrationStore, CorruptCalibration

    if state_dir is None:
        return []
    store = CalibrationStore(state_dir)
    try:
        cur = store.current_version().number
    except CorruptCalibration:
        cur = None
    out = []
    for v in store.versions():
        try:
            store.read_version(v)
            ok, err = True, None
        except CorruptCalibration as e:
            ok, err = False, str(e)
        out.append({"version": v.number, "id": v.id, "current": v.number == cur, "valid": ok, "error": err})
    return out


# ---- the session task -----------------------------------------------------------------------------
async def _meter(camera: Any, sess: LiveSession, tries: int = 6) -> float:
    """A fixed exposure for the session: the 99th percentile of the frame near 75% of full
    scale (a few capture/adjust rounds, waiting out the control latency)."""
    from lightprobe.drivers.base import Controls

    lo, hi = camera.capabilities.exposure_range
    exposure = float(np.clip(sess.exposure_s or 1.0 / 60.0, lo, hi))
    for i in range(tries if sess.exposure_s is None else 1):
        await camera.apply(Controls(exposure_s=exposure, gain=1.0))
        frame = None
        for _ in range(camera.capabilities.control_latency_frames + 4):
            frame = await camera.capture(max(1.0, 3 * exposure + 0.5))
            if abs(frame.meta.exposure_s - exposure) <= 1e-3 * exposure:
                break
        if frame is None or sess.exposure_s is not None or i == tries - 1:
            break
        d = frame.data.astype(np.float64)
        level = (float(np.quantile(d, 0.99)) - frame.black_level) / max(frame.white_level - frame.black_level, 1.0)
        if 0.6 <= level <= 0.9:
            break
        factor = 0.25 if level >= 0.98 else 0.75 / max(level, 0.01)
        exposure = float(np.clip(exposure * factor, lo, hi))
    return exposure


async def _capture_loop(st: ServiceState, camera: Any, sess: LiveSession) -> None:
    """Grab frames and feed the routine until asked to stop or the session times out."""
    while sess.stop is None:
        now = time.monotonic()
        if now - sess.started > sess.timeout_s or now - sess.last_poll > sess.idle_timeout_s:
            sess.stop = "expire"
            break
        frame = await camera.capture(max(1.0, 3 * (sess.exposure_s or 0.0) + 0.5))
        st.runner.last_activity = time.monotonic()  # the systemd watchdog: still alive
        await asyncio.to_thread(sess.live.feed, frame.data)
        sess.frame, sess.frame_no = frame.data, sess.frame_no + 1


def _commit_blocking(desk: Desk, sess: LiveSession) -> dict[str, Any]:
    """Write the solve into the store as a new version (other sections kept)."""
    from lightprobe.calibration.store import CalibrationStore
    from lightprobe.core.calibration import Calibration

    res = sess.live.result
    if res is None or desk.state_dir is None:
        raise ValueError("no solve to commit")
    base = sess.base if sess.base is not None else Calibration()
    cal = base.with_(fisheye=res.model, source="live", created="")
    version = CalibrationStore(desk.state_dir).save(cal)
    return {"id": cal.id, "version": version.number, "rms_px": res.rms_px,
            "fx": float(res.model.K[0, 0]), "fy": float(res.model.K[1, 1]), "fov_deg": res.model.fov_deg}


async def _run_session(st: ServiceState, desk: Desk, sess: LiveSession, cam: Any) -> None:
    from lightprobe.drivers.base import BoardTarget, CameraError

    try:
        async with st.runner.camera_lease(cam) as camera:
            b = sess.live.board
            # A bench rig (or the simulator's technician) can present the board itself
            presented = camera.present_board(BoardTarget(b.cols, b.rows, b.square))
            sess.leased.set()
            try:
                fe = getattr(sess.base, "fisheye", None)
                mode = camera.mode
                if fe is not None and (mode.width, mode.height) != tuple(fe.image_size):
                    match = [m for m in camera.capabilities.modes
                             if (m.width, m.height) == tuple(fe.image_size) and m.format == mode.format]
                    if match:
                        await camera.set_mode(match[0])
                sess.state = "metering"
                sess.exposure_s = await _meter(camera, sess)
                sess.state = "capturing"
                await _capture_loop(st, camera, sess)
            finally:
                if presented:
                    camera.present_board(None)
            if sess.stop == "commit":
                sess.state = "committing"
                sess.committed = await asyncio.to_thread(_commit_blocking, desk, sess)
        sess.state = {"commit": "committed", "expire": "expired"}.get(sess.stop or "", "cancelled")
    except asyncio.CancelledError:
        sess.state = "cancelled"
        raise
    except (CameraError, OSError, ValueError) as e:
        sess.state, sess.error = "failed", f"{type(e).__name__}: {e}"
        log.warning("live calibration %s failed: %s", sess.id, sess.error)
    except Exception as e:
        sess.state, sess.error = "failed", f"{type(e).__name__}: {e}"
        log.exception("live calibration %s failed", sess.id)


# ---- handlers -------------------------------------------------------------------------------------
def _desk(request: web.Request) -> tuple[ServiceState, Desk]:
    return request.app[STATE], request.app[DESK]


def _active(desk: Desk) -> LiveSession:
    s = desk.session
    if s is None or s.state in FINAL:
        raise ApiError(404, "no live calibration session is running (POST /api/v1/calibration/live)",
                       param="session")
    return s


async def get_calibration(request: web.Request) -> web.Response:
    st, desk = _desk(request)
    cal = await asyncio.to_thread(_serving, st, desk)
    hist = await asyncio.to_thread(_history, desk.state_dir)
    s = desk.session
    return web.json_response({
        "serving_id": getattr(st.runner.result, "calibration_id", None) if st.runner.result is not None else None,
        "current": _summary(cal), "history": hist,
        "store": str(desk.state_dir / "calibration") if desk.state_dir is not None else None,
        "live": {"session": s.id, "state": s.state} if s is not None else None,
    })


async def start_live(request: web.Request) -> web.Response:
    from lightprobe.calibration.fisheye import BoardSpec, equidistant_guess
    from lightprobe.calibration.live import LiveFisheyeCalibration

    st, desk = _desk(request)
    opts = parse_start(await _json_body(request))
    if desk.state_dir is None:
        raise ApiError(503, "this service has no calibration store (state directory)", param="state_dir")
    ensure = getattr(st, "ensure_camera", None)
    camera = await ensure() if ensure is not None else st.camera
    if camera is None:
        raise ApiError(503, "no camera", param="camera")
    async with desk.lock:
        if desk.session is not None and desk.session.state not in FINAL:
            raise ApiError(409, f"a live calibration session is already running ({desk.session.id}): "
                           "commit or DELETE it first", param="session")
        base = await asyncio.to_thread(_serving, st, desk)
        fe = getattr(base, "fisheye", None)
        size = tuple(fe.image_size) if fe is not None else (camera.mode.width, camera.mode.height)
        circle = image_circle(base, size)
        live = LiveFisheyeCalibration(
            BoardSpec(opts["cols"], opts["rows"], opts["square"]), size, min_views=opts["min_views"],
            target_rms=opts["rms_px"], target_coverage=opts["coverage"], image_circle=circle,
            guess=equidistant_guess(circle, float(fe.fov_deg) if fe is not None else 185.0))
        sess = LiveSession(secrets.token_hex(6), live, base, circle,
                           {"min_views": opts["min_views"], "rms_px": opts["rms_px"], "coverage": opts["coverage"]},
                           opts["exposure_s"], opts["timeout_s"], opts["idle_timeout_s"])
        sess.task = asyncio.create_task(_run_session(st, desk, sess, camera), name=f"calibration-{sess.id}")
        desk.session = sess
        # Answer once the pipeline is paused and the camera is ours (or the start failed)
        leased = asyncio.ensure_future(sess.leased.wait())
        await asyncio.wait({leased, sess.task}, timeout=15.0, return_when=asyncio.FIRST_COMPLETED)
        leased.cancel()
    if sess.state == "failed":
        raise ApiError(503, f"cannot start the session: {sess.error}", param="camera")
    return web.json_response(sess.to_json(), status=201)


async def get_live(request: web.Request) -> web.Response:
    _, desk = _desk(request)
    s = desk.session
    if s is None:
        raise ApiError(404, "no live calibration session yet (POST /api/v1/calibration/live)", param="session")
    s.last_poll = time.monotonic()
    return web.json_response(s.to_json())


def _encode(frame: np.ndarray) -> bytes:
    from lightprobe.device.service.encode import encode_jpeg

    rgb = frame if frame.dtype == np.uint8 and frame.ndim == 3 else None
    if rgb is None:
        from lightprobe.calibration.live import frame_to_gray

        g = frame_to_gray(frame)
        rgb = np.repeat(g[..., None], 3, axis=2)
    return encode_jpeg(rgb, 80)


async def live_frame(request: web.Request) -> web.Response:
    _, desk = _desk(request)
    s = desk.session
    if s is None or s.frame is None:
        raise ApiError(404, "no calibration frame yet", param="session", headers={"Retry-After": "1"})
    if s.jpeg is None or s.jpeg[0] != s.frame_no:
        s.jpeg = (s.frame_no, await asyncio.to_thread(_encode, s.frame))
    return web.Response(body=s.jpeg[1], content_type="image/jpeg", headers={"X-Lightprobe-Frame": str(s.jpeg[0])})


async def _finish(sess: LiveSession, how: str) -> None:
    sess.stop = how
    if sess.task is not None:
        await asyncio.shield(sess.task)


async def commit_live(request: web.Request) -> web.Response:
    _, desk = _desk(request)
    s = _active(desk)
    if s.state != "capturing" or not s.live.progress.good_enough:
        p = s.live.progress
        raise ApiError(409, f"not good enough yet: {p.views} views, coverage {p.coverage_percent:.0f}%, "
                       f"rms {p.rms_px if p.rms_px is None else round(p.rms_px, 3)} px "
                       f"(targets: {s.targets})", param="good_enough")
    await _finish(s, "commit")
    if s.state != "committed":
        raise ApiError(500, f"commit failed, the previous calibration stays in use: {s.error}", param="commit")
    return web.json_response(s.to_json())


async def cancel_live(request: web.Request) -> web.Response:
    _, desk = _desk(request)
    s = _active(desk)
    await _finish(s, "cancel")
    return web.json_response(s.to_json())


async def _shutdown(app: web.Application) -> None:
    s = app[DESK].session
    if s is not None and s.task is not None and not s.task.done():
        s.task.cancel()
        with contextlib.suppress(asyncio.CancelledError, Exception):
            await asyncio.wait_for(s.task, 3.0)


def _static(path: Path, content_type: str) -> Any:
    async def handler(request: web.Request) -> web.StreamResponse:
        return web.FileResponse(path, headers={"Content-Type": content_type})

    return handler


def add_routes(app: web.Application, state_dir: str | Path | None, static_dir: Path) -> None:
    """Register the routes; ``state_dir`` holds the calibration store (None: read-only),
    ``static_dir`` the technician's page."""
    app[DESK] = Desk(Path(state_dir) if state_dir is not None else None)
    r = app.router
    r.add_get(ROUTE, get_calibration)
    r.add_post(f"{ROUTE}/live", start_live)
    r.add_get(f"{ROUTE}/live", get_live)
    r.add_delete(f"{ROUTE}/live", cancel_live)
    r.add_get(f"{ROUTE}/live/frame.jpg", live_frame)
    r.add_post(f"{ROUTE}/live/commit", commit_live)
    static = static_dir
    for url, name, kind in (("/calibrate", "calibrate.html", "text/html"),
                            ("/static/calibrate.js", "calibrate.js", "text/javascript")):
        r.add_get(url, _static(static / name, kind))
    app.on_shutdown.append(_shutdown)
