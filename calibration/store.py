"""Versioned calibration files in the probe's state directory, crash-safe, with rollback.

Layout (``STATE`` is the service's state directory)::

    STATE/calibration/history/000001-<id>.json   one file per saved version, never rewritten
    STATE/calibration/current                     "<file name> <sha256 of its bytes>\\n"

A save writes the version file atomically (temp file in the same directory, fsync, rename,
fsync the directory), then replaces ``current`` the same way. A writer killed at any point
leaves either the old pointer or the new one, each naming a complete, checksummed file; stray
temp files are ignored and swept by the next save. Loading checks the pointer's sha256 against
the file bytes, then the schema (``Calibration.from_json``, which also checks the content id).

A corrupt or missing current version raises :class:`CorruptCalibration` (an InputError naming
the file) from :meth:`CalibrationStore.load_current`; :meth:`CalibrationStore.load` instead
falls back to the newest valid version and reports the error, so the previous good calibration
stays in use. :meth:`CalibrationStore.rollback` points ``current`` at an earlier version.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import os
import re
from dataclasses import dataclass
from pathlib import Path

from lightprobe.core.calibration import Calibration
from lightprobe.core.errors import InputError
from lightprobe.core.fsutil import atomic_write

__all__ = ["CalibrationStore", "CorruptCalibration", "LoadResult", "Version", "atomic_write",
           "load_calibration"]

log = logging.getLogger(__name__)

_NAME = re.compile(r"^(\d{6,})-([0-9a-f]{16})\.json$")


class CorruptCalibration(InputError):
    """A calibration file failed its checksum or schema check; the message names the file."""


@dataclass(frozen=True)
class Version:
    number: int
    id: str
    path: Path


@dataclass(frozen=True)
class LoadResult:
    """What :meth:`CalibrationStore.load` found: the calibration in use and any errors met."""

    calibration: Calibration | None
    version: Version | None
    errors: tuple[str, ...] = ()


class CalibrationStore:
    """Calibration history under ``state_dir/calibration``. Creating it touches nothing."""

    def __init__(self, state_dir: str | os.PathLike[str]) -> None:
        self.root = Path(state_dir) / "calibration"
        self.history_dir = self.root / "history"
        self.current_path = self.root / "current"

    # -- queries --
    def versions(self) -> list[Version]:
        """All version files, oldest first (unchecked)."""
        if not self.history_dir.is_dir():
            return []
        out = []
        for p in self.history_dir.iterdir():
            m = _NAME.match(p.name)
            if m:
                out.append(Version(int(m.group(1)), m.group(2), p))
        return sorted(out, key=lambda v: v.number)

    def _pointer(self) -> tuple[str, str]:
        try:
            text = self.current_path.read_text(encoding="ascii")
        except FileNotFoundError as e:
            raise CorruptCalibration(f"{self.current_path}: no current calibration", param=str(self.current_path)) from e
        except (OSError, UnicodeDecodeError) as e:
            raise CorruptCalibration(f"{self.current_path}: unreadable ({e})", param=str(self.current_path)) from e
        parts = text.split()
        if len(parts) != 2 or not _NAME.match(parts[0]) or not re.fullmatch(r"[0-9a-f]{64}", parts[1]):
            raise CorruptCalibration(f"{self.current_path}: malformed pointer {text[:80]!r}", param=str(self.current_path))
        return parts[0], parts[1]

    def current_version(self) -> Version:
        name, _ = self._pointer()
        m = _NAME.match(name)
        assert m is not None
        return Version(int(m.group(1)), m.group(2), self.history_dir / name)

    def read_version(self, version: Version, sha256: str | None = None) -> Calibration:
        """Load one version file, checking its sha256 (if given), JSON, schema and content id."""
        p = version.path
        try:
            data = p.read_bytes()
        except OSError as e:
            raise CorruptCalibration(f"{p}: cannot read ({e.strerror})", param=str(p)) from e
        if sha256 is not None and hashlib.sha256(data).hexdigest() != sha256:
            raise CorruptCalibration(f"{p}: checksum mismatch (file changed or torn)", param=str(p))
        try:
            cal = Calibration.from_json(json.loads(data))
        except (json.JSONDecodeError, UnicodeDecodeError) as e:
            raise CorruptCalibration(f"{p}: not valid JSON ({e})", param=str(p)) from e
        except InputError as e:
            raise CorruptCalibration(f"{p}: {e}", param=str(p)) from e
        if cal.id != version.id:
            raise CorruptCalibration(f"{p}: content id {cal.id} does not match the file name", param=str(p))
        return cal

    def load_current(self) -> Calibration:
        """The current calibration; raises CorruptCalibration naming the file at fault."""
        _, digest = self._pointer()
        return self.read_version(self.current_version(), digest)

    def load(self) -> LoadResult:
        """The current calibration, or the newest valid earlier one if current is corrupt."""
        errors: list[str] = []
        try:
            return LoadResult(self.load_current(), self.current_version())
        except CorruptCalibration as e:
            errors.append(str(e))
        try:
            limit = self.current_version().number
        except CorruptCalibration:
            limit = None
        for v in reversed(self.versions()):
            if limit is not None and v.number >= limit:
                continue
            try:
                return LoadResult(self.read_version(v), v, tuple(errors))
            except CorruptCalibration as e:
                errors.append(str(e))
        return LoadResult(None, None, tuple(errors))

    # -- changes --
    def save(self, cal: Calibration) -> Version:
        """Write ``cal`` as a new version and make it current."""
        self.history_dir.mkdir(parents=True, exist_ok=True)
        self._sweep()
        versions = self.versions()
        number = versions[-1].number + 1 if versions else 1
        data = (json.dumps(cal.to_json(), indent=1, sort_keys=False) + "\n").encode("utf-8")
        version = Version(number, cal.id, self.history_dir / f"{number:06d}-{cal.id}.json")
        atomic_write(version.path, data)
        self._point_to(version.path.name, hashlib.sha256(data).hexdigest())
        return version

    def rollback(self, number: int | None = None) -> Version:
        """Make version ``number`` (default: the newest valid one before current) current."""
        try:
            cur = self.current_version().number
        except CorruptCalibration:
            cur = None
        candidates = [v for v in self.versions()
                      if (v.number == number if number is not None else (cur is None or v.number < cur))]
        for v in reversed(candidates):
            data = v.path.read_bytes()
            self.read_version(v)  # raises CorruptCalibration if that version is bad
            self._point_to(v.path.name, hashlib.sha256(data).hexdigest())
            return v
        what = f"version {number}" if number is not None else "an earlier version"
        raise InputError(f"{self.history_dir}: no {what} to roll back to", param="version")

    def _point_to(self, name: str, digest: str) -> None:
        atomic_write(self.current_path, f"{name} {digest}\n".encode("ascii"))

    def _sweep(self) -> None:
        """Remove temp files left by writers that died before their rename."""
        for d in (self.root, self.history_dir):
            for p in d.glob(".*.tmp"):
                with contextlib.suppress(OSError):
                    p.unlink()


def load_calibration(state_dir: str | os.PathLike[str], camera: object) -> Calibration:
    """The calibration a probe uses, in this order:

    1. the calibration store in ``state_dir`` (the current version, or the newest valid earlier
       one when current is corrupt, with the error logged);
    2. ``state_dir/calibration.json`` (a file an installer copied in by hand);
    3. the camera's own (``Camera.factory_calibration``: the simulator's ground truth).

    A camera with none of these gets an InputError naming what to do.
    """
    state = Path(state_dir)
    store = CalibrationStore(state)
    found = store.load()
    if store.versions():  # a store that exists but is damaged: say so (a fresh unit has none)
        for err in found.errors:
            log.error("calibration store: %s", err)
    if found.calibration is not None:
        return found.calibration
    p = state / "calibration.json"
    if p.exists():
        try:
            return Calibration.from_json(json.loads(p.read_text(encoding="utf-8")))
        except (OSError, ValueError) as e:
            raise InputError(f"{p}: {e}", param="calibration") from e
    own = getattr(camera, "factory_calibration", None)
    cal = own() if callable(own) else None
    if cal is not None:
        return cal  # type: ignore[no-any-return]
    raise InputError(f"no calibration for camera {getattr(camera, 'name', '?')!r} in {state} "
                     "(make one with 'lightprobe calibrate fisheye ... --state DIR')", param="calibration")
