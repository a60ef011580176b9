"""The API bearer token: created at first start in the state directory (mode 0600).

Write endpoints always need ``Authorization: Bearer <token>``; so do camera images and maps of
the room unless ``service.public_images`` opens them; other reads need it only when
``service.require_token_for_reads`` is set (``lightprobe.device.service.app.needs_token``). Comparison is
constant-time.
"""

from __future__ import annotations

import contextlib
import hmac
import os
import secrets
from pathlib import Path

__all__ = ["TOKEN_FILE", "check_bearer", "load_or_create_token", "read_token"]

TOKEN_FILE = "token"


def read_token(state_dir: str | os.PathLike[str]) -> str | None:
    """The token stored in ``state_dir``, or None when there is none yet."""
    p = Path(state_dir) / TOKEN_FILE
    try:
        tok = p.read_text(encoding="ascii").strip()
    except FileNotFoundError:
        return None
    return tok or None


def load_or_create_token(state_dir: str | os.PathLike[str]) -> str:
    """Return the token, creating it (43 url-safe chars, file mode 0600) if absent."""
    d = Path(state_dir)
    d.mkdir(parents=True, exist_ok=True, mode=0o700)
    existing = read_token(d)
    if existing:
        return existing
    tok = secrets.token_urlsafe(32)
    p = d / TOKEN_FILE
    tmp = d / f".{TOKEN_FILE}.{os.getpid()}.tmp"
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    try:
        try:
            os.fchmod(fd, 0o600)
            os.write(fd, (tok + "\n").encode("ascii"))
            os.fsync(fd)
        finally:
            os.close(fd)
    except OSError:
        with contextlib.suppress(OSError):  # a full disk: leave nothing behind
            os.unlink(tmp)
        raise
    try:
        os.link(tmp, p)  # fails if another process created it first: keep theirs
    except FileExistsError:
        tok = read_token(d) or tok
    finally:
        os.unlink(tmp)
    return tok


def check_bearer(header: str | None, token: str) -> bool:
    """True when ``header`` is ``Bearer <token>`` (constant-time compare)."""
    if not header or not header.startswith("Bearer "):
        return False
    given = header[len("Bearer "):].strip().encode("utf-8", "replace")
    return hmac.compare_digest(given, token.encode("ascii"))
