"""One service per state directory: an advisory lock (``flock``) on ``STATE_DIR/lock`` with the
owner's pid inside, held for the life of the process.

Two services on one state dir would overwrite each other's config and calibration; the second
one is refused at start, naming the directory and the pid that holds it. The lock is released
by the kernel when the process exits, however it exits, so a crash never leaves a stale lock
(the pid in the file is informational).
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import os
from pathlib import Path

from lightprobe.core.errors import InputError

__all__ = ["LOCK_FILE", "StateDirLock"]

LOCK_FILE = "lock"


class StateDirLock:
    """``acquire()`` or raise :class:`InputError` (exit 2) naming the dir and the owner's pid."""

    def __init__(self, state_dir: str | os.PathLike[str]) -> None:
        self.state_dir = Path(state_dir)
        self.path = self.state_dir / LOCK_FILE
        self._fd: int | None = None

    def acquire(self) -> None:
        try:
            self.state_dir.mkdir(parents=True, exist_ok=True, mode=0o700)
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o600)
        except OSError as e:
            raise InputError(f"state dir {self.state_dir}: cannot create its lock file: {e.strerror}",
                             param="--state-dir") from e
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as e:
            owner = ""
            with contextlib.suppress(OSError, ValueError):
                owner = os.pread(fd, 32, 0).decode("ascii").strip()
            os.close(fd)
            if e.errno in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
                who = f"pid {owner}" if owner.isdigit() else "another process"
                raise InputError(f"state dir {self.state_dir.resolve()} is in use by {who} (another "
                                 "lightprobe service); give this one its own --state-dir",
                                 param="--state-dir") from None
            raise InputError(f"state dir {self.state_dir}: cannot lock: {e.strerror}", param="--state-dir") from e
        with contextlib.suppress(OSError):  # informational: who holds it
            os.ftruncate(fd, 0)
            os.pwrite(fd, f"{os.getpid()}\n".encode("ascii"), 0)
        self._fd = fd

    def release(self) -> None:
        if self._fd is not None:
            with contextlib.suppress(OSError):
                os.ftruncate(self._fd, 0)
            os.close(self._fd)
            self._fd = None

    def __enter__(self) -> StateDirLock:
        self.acquire()
        return self

    def __exit__(self, *exc: object) -> None:
        self.release()
