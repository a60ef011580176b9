"""Connection limits that hold on a small board: the listening socket's protocol, wrapped.

aiohttp reads a request's headers with no deadline and accepts every connection the kernel hands
it, so a host on the LAN that opens a thousand connections and sends a header byte now and then
holds every file descriptor the service has: accepts fail (and asyncio logs each failure), and
nobody, ``/healthz`` included, is served. :class:`ConnectionGuard` sits between the socket and
aiohttp's :class:`~aiohttp.web_protocol.RequestHandler`:

- at most ``max_connections`` open connections, and ``max_per_peer`` from one address; the rest
  are reset at once (they cost one accept, no buffer, no timer);
- a request's headers must arrive within ``header_timeout`` seconds of its first byte (or of the
  connection, for the first request), and its body (``Content-Length`` bytes, or a chunked body
  to its last chunk) within ``body_timeout`` of the headers; a connection that misses either is
  closed. A WebSocket, once upgraded, is no longer timed (its
  own heartbeat and send timeout apply);
- refusals and timeouts are logged once per ``log_interval`` with their counts, never per event.

The idle time between two requests on a kept-alive connection is aiohttp's
``keepalive_timeout``, which the service sets from config. The counts are in ``/status``.

:func:`raise_fd_limit` lifts the soft file-descriptor limit to the hard one and returns the
connection cap that fits below it, so the caps hold before the fds run out.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import resource
import socket
import time
from collections import Counter
from dataclasses import dataclass, field
from typing import Any

from aiohttp import web

__all__ = ["ConnectionGuard", "GuardedSite", "RateLimitFilter", "install_log_limits", "raise_fd_limit"]

log = logging.getLogger(__name__)

_HEADER_END = b"\r\n\r\n"


def raise_fd_limit(reserve: int = 128) -> int:
    """Raise the soft RLIMIT_NOFILE to the hard limit (where allowed); return the number of
    connections that fit below it with ``reserve`` descriptors left for the service's files,
    camera, threads and mDNS sockets."""
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if hard == resource.RLIM_INFINITY or hard > soft:
        target = hard if hard != resource.RLIM_INFINITY else max(soft, 65536)
        try:
            resource.setrlimit(resource.RLIMIT_NOFILE, (target, hard))
            soft = target
        except (ValueError, OSError):
            pass
    return max(16, soft - reserve)


@dataclass
class ConnectionGuard:
    max_connections: int = 512
    max_per_peer: int = 64
    header_timeout: float = 10.0
    body_timeout: float = 30.0
    log_interval: float = 10.0
    open: int = 0
    per_peer: Counter[str] = field(default_factory=Counter)
    refused: int = 0
    timed_out: int = 0
    _logged: dict[str, tuple[float, int]] = field(default_factory=dict)

    def admit(self, peer: str) -> bool:
        if self.open >= self.max_connections or self.per_peer[peer] >= self.max_per_peer:
            self.refused += 1
            self._note("refused", f"connection limit reached ({self.open} open, {self.per_peer[peer]} "
                       f"from {peer}; caps {self.max_connections} / {self.max_per_peer} per peer)")
            return False
        self.open += 1
        self.per_peer[peer] += 1
        return True

    def release(self, peer: str) -> None:
        self.open -= 1
        self.per_peer[peer] -= 1
        if self.per_peer[peer] <= 0:
            del self.per_peer[peer]

    def timeout(self, peer: str, what: str) -> None:
        self.timed_out += 1
        self._note("timeout", f"{what} not received in time from {peer}: connection closed")

    def _note(self, kind: str, msg: str) -> None:
        """Log the first event of a kind, then at most once per interval with the count since."""
        now = time.monotonic()
        last, count = self._logged.get(kind, (-1e18, 0))
        if now - last >= self.log_interval:
            suffix = f" (and {count} more like it in the last {self.log_interval:.0f} s)" if count else ""
            log.warning("%s%s", msg, suffix)
            self._logged[kind] = (now, 0)
        else:
            self._logged[kind] = (last, count + 1)

    def stats(self) -> dict[str, Any]:
        return {"open": self.open, "peers": len(self.per_peer), "refused": self.refused,
                "timed_out": self.timed_out, "max_connections": self.max_connections,
                "max_per_peer": self.max_per_peer}


def _content_length(head: bytes) -> int | None:
    """The Content-Length of a lower-cased header block, or None."""
    i = head.find(b"\r\ncontent-length:")
    if i < 0:
        return None
    value = head[i + len(b"\r\ncontent-length:"):].split(b"\r\n", 1)[0].strip()
    return int(value) if value.isdigit() else None


class _GuardedProtocol(asyncio.Protocol):
    """Counts the connection, times its headers and bodies, delegates everything to aiohttp's
    request handler."""

    def __init__(self, factory: Any, guard: ConnectionGuard) -> None:
        self._factory, self._guard = factory, guard
        self._inner: Any = None
        self._transport: asyncio.Transport | None = None
        self._peer = ""
        self._timer: asyncio.TimerHandle | None = None
        self._tail = b""  # the last bytes seen, to find a header end split across reads
        self._in_headers = True  # waiting for a header block
        self._head = bytearray()  # the header block so far (capped), to spot an upgrade
        self._upgraded = False
        self._body_left = 0  # Content-Length bytes still to come
        self._chunked = False  # inside a chunked body

    # ---- asyncio.Protocol ----
    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        assert isinstance(transport, asyncio.Transport)
        peer = transport.get_extra_info("peername")
        self._peer = str(peer[0]) if isinstance(peer, tuple) and peer else "?"
        if not self._guard.admit(self._peer):
            sock = transport.get_extra_info("socket")
            if sock is not None:  # reset, not a FIN handshake: nothing lingers
                with contextlib.suppress(OSError):
                    sock.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, b"\x01\x00\x00\x00\x00\x00\x00\x00")
            transport.abort()
            return
        self._transport = transport
        self._inner = self._factory()
        self._inner.connection_made(transport)
        self._arm(self._guard.header_timeout, "request headers")

    def data_received(self, data: bytes) -> None:
        if self._inner is None:
            return
        if not self._upgraded:
            self._watch(data)
        self._inner.data_received(data)

    def eof_received(self) -> bool | None:
        return self._inner.eof_received() if self._inner is not None else None

    def connection_lost(self, exc: Exception | None) -> None:
        if self._inner is None:
            return
        self._disarm()
        self._guard.release(self._peer)
        inner, self._inner = self._inner, None
        inner.connection_lost(exc)

    def pause_writing(self) -> None:
        if self._inner is not None:
            self._inner.pause_writing()

    def resume_writing(self) -> None:
        if self._inner is not None:
            self._inner.resume_writing()

    # ---- timing ----
    def _watch(self, data: bytes) -> None:
        """Follow the request framing just enough to time it: a header block (ends with a blank
        line), then ``Content-Length`` bytes of body (or a chunked body up to its last chunk)."""
        if self._body_left > 0:  # inside a body
            self._body_left -= len(data)
            if self._body_left <= 0:
                self._body_left = 0
                self._disarm()
            return
        if self._chunked:
            if b"0\r\n\r\n" in self._tail + data:
                self._chunked = False
                self._tail = b""
                self._disarm()
            else:
                self._tail = (self._tail + data)[-4:]
            return
        if not self._in_headers:  # the first bytes of the next request on a kept-alive connection
            self._in_headers = True
            self._head.clear()
            self._arm(self._guard.header_timeout, "request headers")
        buf = self._tail + data
        end = buf.find(_HEADER_END)
        if len(self._head) < 16384:
            self._head += data[: 16384 - len(self._head)]
        if end < 0:
            self._tail = buf[-3:]
            return
        self._tail = b""
        self._in_headers = False
        self._disarm()
        head = bytes(self._head).lower()
        if b"\r\nupgrade: websocket" in head or b"\r\nupgrade:websocket" in head:
            self._upgraded = True  # a WebSocket: its heartbeat and send timeout take over
            return
        after = len(buf) - end - len(_HEADER_END)  # body bytes already in this read
        length = _content_length(head)
        if length is not None and length > after:
            self._body_left = length - after
            self._arm(self._guard.body_timeout, "request body")
        elif b"\r\ntransfer-encoding:" in head and b"chunked" in head:
            self._chunked = True
            self._arm(self._guard.body_timeout, "request body")

    def _arm(self, seconds: float, what: str) -> None:
        self._disarm()
        if seconds > 0:
            self._timer = asyncio.get_running_loop().call_later(seconds, self._expire, what)

    def _disarm(self) -> None:
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None

    def _expire(self, what: str) -> None:
        self._timer = None
        if self._transport is not None and not self._transport.is_closing():
            self._guard.timeout(self._peer, what)
            self._transport.abort()


class GuardedSite(web.SockSite):
    """:class:`aiohttp.web.SockSite` with a :class:`ConnectionGuard` in front of aiohttp.

    asyncio accepts up to ``backlog`` connections per wake-up before any of them reaches its
    protocol, so the accept batch stays small (``accept_batch``: refused ones are closed before
    the next batch, and a burst never holds more descriptors than that), while the kernel's
    listen queue is made long (``queue``) so that a burst of connects is queued, not dropped (a
    dropped SYN costs a legitimate client a 1 s retransmit)."""

    def __init__(self, runner: web.BaseRunner, sock: socket.socket, guard: ConnectionGuard, *,
                 accept_batch: int = 64, queue: int = 2048, **kw: Any) -> None:
        super().__init__(runner, sock, backlog=accept_batch, **kw)
        self.guard, self.queue = guard, queue

    async def start(self) -> None:
        await web.BaseSite.start(self)
        loop = asyncio.get_running_loop()
        server = self._runner.server
        assert server is not None
        guard = self.guard
        self._server = await loop.create_server(lambda: _GuardedProtocol(server, guard), sock=self._sock,
                                                backlog=self._backlog)
        self._sock.listen(self.queue)  # the kernel's queue; asyncio keeps its batch of accept_batch


class RateLimitFilter(logging.Filter):
    """Let one record matching any of ``patterns`` through per ``interval`` (with the count of
    those held back), without its traceback: asyncio logs every failed ``accept()`` (EMFILE, out
    of descriptors) and aiohttp every malformed request (an over-long request line) with a full
    traceback, thousands of lines a second under a flood. Other records pass untouched."""

    def __init__(self, patterns: tuple[str, ...], interval: float = 10.0) -> None:
        super().__init__()
        self.patterns, self.interval = patterns, interval
        self._last, self._count = -1e18, 0

    def filter(self, record: logging.LogRecord) -> bool:
        if not any(p in str(record.msg) for p in self.patterns):
            return True
        msg = record.getMessage()
        now = time.monotonic()
        if now - self._last < self.interval:
            self._count += 1
            return False
        record.msg = msg
        if record.exc_info and record.exc_info[1] is not None:
            record.msg = f"{msg}: {type(record.exc_info[1]).__name__}: {str(record.exc_info[1])[:200]}"
        if self._count:
            record.msg = f"{record.msg} ({self._count} more like it in the last {self.interval:.0f} s)"
        record.exc_info, record.exc_text, record.args = None, None, ()
        self._last, self._count = now, 0
        return True


def install_log_limits(interval: float = 10.0) -> None:
    """Rate-limit the flood-prone records of asyncio (accept errors) and aiohttp (bad requests)."""
    logging.getLogger("asyncio").addFilter(RateLimitFilter(("socket.accept() out of system resource",), interval))
    logging.getLogger("aiohttp.server").addFilter(RateLimitFilter(("Error handling request",), interval))
