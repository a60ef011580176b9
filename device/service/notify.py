"""systemd notification (sd_notify) over ``$NOTIFY_SOCKET``, without libsystemd.

``READY=1`` once the API listens, ``STATUS=...`` on state changes, ``WATCHDOG=1`` every half
``WatchdogSec`` only while the pipeline makes progress (so a stuck pipeline gets the service
restarted), ``STOPPING=1`` at shutdown. A leading ``@`` in the socket path means an abstract
socket. Without ``$NOTIFY_SOCKET`` every call is a no-op. The environment is read when a
:class:`Notifier` is made, never at import.
"""

from __future__ import annotations

import logging
import os
import socket

__all__ = ["Notifier"]

log = logging.getLogger(__name__)


class Notifier:
    """Send sd_notify datagrams. ``watchdog_interval`` is half of ``$WATCHDOG_USEC`` (or None)."""

    def __init__(self, env: dict[str, str] | None = None) -> None:
        env = dict(os.environ) if env is None else env
        path = env.get("NOTIFY_SOCKET", "")
        self.address: str | None = None
        if path:
            self.address = "\0" + path[1:] if path.startswith("@") else path
        self.watchdog_interval: float | None = None
        usec = env.get("WATCHDOG_USEC", "")
        pid = env.get("WATCHDOG_PID", "")
        if usec.isdigit() and int(usec) > 0 and (not pid or pid == str(os.getpid())):
            self.watchdog_interval = int(usec) / 2e6

    @property
    def enabled(self) -> bool:
        return self.address is not None

    def send(self, *fields: str) -> bool:
        """Send ``fields`` joined by newlines; returns False (and logs) if it could not."""
        if self.address is None:
            return False
        msg = "\n".join(fields).encode("utf-8", "replace")
        try:
            with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC) as s:
                s.sendto(msg, self.address)
        except OSError as e:
            log.warning("sd_notify to %r failed: %s", self.address, e)
            return False
        return True

    def ready(self, status: str = "") -> bool:
        return self.send("READY=1", *([f"STATUS={status}"] if status else []))

    def status(self, status: str) -> bool:
        return self.send(f"STATUS={status}")

    def watchdog(self) -> bool:
        return self.send("WATCHDOG=1")

    def stopping(self) -> bool:
        return self.send("STOPPING=1")
