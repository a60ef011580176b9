"""Recordings while the service runs (``POST /api/v1/recordings``, the dashboard's Record button).

A recording (:mod:`lightprobe.drivers.recording`) holds what the camera delivered to the
pipeline. To make its replay (``--camera replay:FILE``) the recorded run bit for bit, a recording
starts the estimate afresh, as a calibration reload does: the pipeline is rebuilt over a
:class:`lightprobe.drivers.recording.RecordingCamera` (same tables and calibration, a new metering
sweep: its first ~0.6 s of sets are marked ``settling``) and the recording begins with its first
frame. The published lights keep flowing; the recording ends at its duration or size, and the
pipeline keeps running over the wrapper (which then only passes frames through).

Files live in ``STATE/recordings/`` (mode 0700), ``<id>.lprec``, written as ``<id>.lprec.part``
and renamed when whole; ``id`` is the start time, UTC (``20261207T174512Z``). Limits
(``[recordings]``): ``max_seconds`` and ``max_mb`` per recording, ``keep_mb`` for all of them (a
start that would not fit is refused with 507: delete old ones). One at a time (409).
"""

from __future__ import annotations

import asyncio
import contextlib
import datetime as _dt
import logging
import os
import re
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from lightprobe.device.service.errors import ApiError

__all__ = ["ID_PATTERN", "Recordings"]

log = logging.getLogger(__name__)

ID_PATTERN = r"^[0-9]{8}T[0-9]{6}Z(-[0-9]{1,3})?$"
_ID = re.compile(ID_PATTERN)
SUFFIX = ".lprec"


@dataclass
class _Active:
    id: str
    camera: Any  # RecordingCamera
    seconds: float
    max_bytes: int
    started: float = field(default_factory=time.time)
    writer: Any = None  # RecordingWriter, from the first frame on
    state: str = "starting"  # starting | recording | finishing | done | failed
    error: str | None = None


class Recordings:
    """The state dir's recordings and the one being made (module docstring)."""

    def __init__(self, state_dir: Path | None) -> None:
        self.folder = Path(state_dir) / "recordings" if state_dir is not None else None
        self.active: _Active | None = None
        self._done: set[asyncio.Task[None]] = set()

    # ---- files ----------------------------------------------------------------------------------
    def _require_folder(self) -> Path:
        if self.folder is None:
            raise ApiError(503, "this service has no state directory to keep recordings in", param="recordings")
        self.folder.mkdir(parents=True, exist_ok=True, mode=0o700)
        return self.folder

    def path(self, rid: str) -> Path:
        """The finished recording ``rid`` (404 when there is none; the id is checked first)."""
        if not _ID.match(rid):
            raise ApiError(400, f"recording id {rid!r} is not a recording id (e.g. 20261207T174512Z)", param="id")
        folder = self._require_folder()
        p = folder / f"{rid}{SUFFIX}"
        a = self.active
        if a is not None and a.id == rid and a.state in ("starting", "recording", "finishing"):
            raise ApiError(409, f"recording {rid} is still being made ({a.state})", param="id",
                           headers={"Retry-After": "1"})
        if not p.is_file():
            raise ApiError(404, f"no recording {rid}", param="id")
        return p

    def used_bytes(self) -> int:
        if self.folder is None or not self.folder.is_dir():
            return 0
        total = 0
        for p in self.folder.iterdir():
            if p.name.endswith((SUFFIX, SUFFIX + ".part")):
                with contextlib.suppress(OSError):
                    total += p.stat().st_size
        return total

    def listing(self) -> dict[str, Any]:
        items: list[dict[str, Any]] = []
        if self.folder is not None and self.folder.is_dir():
            for p in sorted(self.folder.glob(f"*{SUFFIX}")):
                rid = p.name[: -len(SUFFIX)]
                if not _ID.match(rid):
                    continue
                st = p.stat()
                items.append({"id": rid, "state": "done", "bytes": st.st_size,
                              "created": _dt.datetime.fromtimestamp(st.st_mtime, _dt.UTC).isoformat(timespec="seconds")})
        a = self.active
        if a is not None and a.state != "done":
            items = [i for i in items if i["id"] != a.id]
            items.append(self._active_json(a))
        return {"recordings": items, "used_bytes": self.used_bytes()}

    def _active_json(self, a: _Active) -> dict[str, Any]:
        out: dict[str, Any] = {"id": a.id, "state": a.state, "seconds_limit": a.seconds, "bytes_limit": a.max_bytes,
                               "created": _dt.datetime.fromtimestamp(a.started, _dt.UTC).isoformat(timespec="seconds")}
        if a.writer is not None:
            w = a.writer.status()
            out.update({"bytes": w["bytes"], "frames": w["frames"], "seconds": w["seconds"],
                        "lost_frames": w["lost_frames"], "cpu_ms_per_frame": w["cpu_ms_per_frame"]})
        if a.error:
            out["error"] = a.error
        return out

    # ---- making one -----------------------------------------------------------------------------
    def start(self, st: Any, camera: Any, seconds: float, max_mb: float | None) -> dict[str, Any]:
        """Begin a recording of ``seconds`` (at most ``max_mb``) of ``camera`` (the service's,
        :meth:`ServiceState.ensure_camera`) on the service state ``st``."""
        from lightprobe.drivers.recording import RecordingCamera, RecordingWriter

        cfg = st.config
        folder = self._require_folder()
        a = self.active
        if a is not None and a.state in ("starting", "recording", "finishing"):
            raise ApiError(409, f"recording {a.id} is being made; one at a time", param="recordings",
                           headers={"Retry-After": "1"})
        limit_s = float(cfg.get("recordings", "max_seconds"))
        limit_mb = float(cfg.get("recordings", "max_mb"))
        if not seconds > 0:
            raise ApiError(400, f"seconds must be > 0, got {seconds:g}", param="seconds")
        if max_mb is not None and not max_mb > 0:
            raise ApiError(400, f"max_mb must be > 0, got {max_mb:g}", param="max_mb")
        # beyond the installer's limits, the limits: the answer says which are in effect
        seconds = min(seconds, limit_s)
        mb = limit_mb if max_mb is None else min(float(max_mb), limit_mb)
        room = int(float(cfg.get("recordings", "keep_mb")) * 1e6) - self.used_bytes()
        try:
            fs = os.statvfs(folder)
            free = fs.f_bavail * fs.f_frsize
        except OSError:
            free = room
        room = min(room, free - (64 << 20))  # keep 64 MB of the disk for the state dir
        if room < (8 << 20):
            raise ApiError(507, f"no room for a recording: {self.used_bytes() / 1e6:.0f} MB of recordings "
                           f"(recordings.keep_mb) or a full disk; delete old ones", param="recordings")
        max_bytes = int(min(mb * 1e6, room))
        stamp = _dt.datetime.now(_dt.UTC).strftime("%Y%m%dT%H%M%SZ")
        rid, n = stamp, 1
        while (folder / f"{rid}{SUFFIX}").exists() or (folder / f"{rid}{SUFFIX}.part").exists():
            rid, n = f"{stamp}-{n}", n + 1
        inner = camera.inner if isinstance(camera, RecordingCamera) else camera
        active = _Active(rid, RecordingCamera(inner), float(seconds), max_bytes)
        part = folder / f"{rid}{SUFFIX}.part"

        def make_writer(rec: RecordingCamera) -> RecordingWriter:
            header = rec.header(calibration=getattr(rec, "calibration_json", None), source=inner.name,
                                probe=st.probe_id)
            active.writer = RecordingWriter(part, header, max_bytes=max_bytes, max_seconds=active.seconds)
            active.state = "recording"
            return active.writer

        def done(writer: RecordingWriter) -> None:
            active.state = "finishing"
            task = asyncio.get_running_loop().create_task(self._finish(active, writer, part))
            self._done.add(task)
            task.add_done_callback(self._done.discard)

        active.camera.arm(make_writer, done)
        self.active = active
        st.recorder = active.camera
        st.runner.request_fresh_start()
        log.info("recording %s: %g s, at most %.0f MB", rid, seconds, max_bytes / 1e6)
        return self._active_json(active)

    async def _finish(self, a: _Active, writer: Any, part: Path) -> None:
        await asyncio.to_thread(writer.close)
        if writer.error is not None:
            a.state, a.error = "failed", writer.error
            log.error("recording %s failed: %s", a.id, writer.error)
            return
        try:
            await asyncio.to_thread(os.replace, part, part.with_name(part.name[: -len(".part")]))
        except OSError as e:
            a.state, a.error = "failed", f"{part}: {e.strerror or e}"
            return
        a.state = "done"
        log.info("recording %s done: %s", a.id, writer.status())

    async def delete(self, rid: str) -> None:
        """Delete a recording; one being made is stopped first."""
        if not _ID.match(rid):
            raise ApiError(400, f"recording id {rid!r} is not a recording id (e.g. 20261207T174512Z)", param="id")
        folder = self._require_folder()
        a = self.active
        if a is not None and a.id == rid and a.state in ("starting", "recording", "finishing"):
            writer = a.camera.stop()
            if writer is not None:
                await asyncio.to_thread(writer.close)
            await asyncio.gather(*self._done, return_exceptions=True)
            a.state = "done"
            (folder / f"{rid}{SUFFIX}.part").unlink(missing_ok=True)
            (folder / f"{rid}{SUFFIX}").unlink(missing_ok=True)
            return
        p = folder / f"{rid}{SUFFIX}"
        if not p.is_file():
            raise ApiError(404, f"no recording {rid}", param="id")
        p.unlink()

    async def close(self) -> None:
        """At shutdown: a recording being made is closed whole (readable, not renamed)."""
        a = self.active
        if a is not None and a.state in ("starting", "recording", "finishing"):
            writer = a.camera.stop()
            if writer is not None:
                await asyncio.to_thread(writer.close)
                part = self.folder / f"{a.id}{SUFFIX}.part" if self.folder is not None else None
                if part is not None and part.exists():
                    os.replace(part, part.with_name(part.name[: -len(".part")]))
        await asyncio.gather(*self._done, return_exceptions=True)
