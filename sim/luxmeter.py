"""A simulated Konica Minolta T-10A on a real pseudo-terminal, with injectable faults.

The meter runs a reader thread on the pty master; clients open the slave path
(:attr:`SimT10A.port`) with pyserial exactly as they would ``/dev/ttyUSB0``, so the real
``lightprobe.drivers.t10a`` code runs end to end. It answers command 54 (PC mode) and 10 (read measurement)
in the frame format of ``lightprobe.drivers.t10a`` and refreshes its reading every ``period_s`` (500 ms on
the real meter) from the true illuminance ``lux`` with relative Gaussian noise ``noise_rel``.
Until PC mode is set it ignores every command but 54 (the client times out).

Faults (:meth:`SimT10A.inject`), each for the next ``count`` replies (``None`` = until cleared):
``"checksum"`` (a wrong BCC), ``"timeout"`` (no reply), ``"garbage"`` (random bytes + CR LF),
``"partial"`` (half a frame, no CR LF), ``"over_range"`` (status '5'), and ``"unplug"`` (closes
the master: the client sees the port vanish). A pty carries bytes but cannot simulate parity
errors. Importing this module does nothing; the thread starts in :meth:`start`.
"""

from __future__ import annotations

import contextlib
import os
import select
import termios
import threading
import time
import tty
from types import TracebackType
from typing import Self

import numpy as np

from lightprobe.drivers.t10a import (
    CMD_PC_MODE,
    CMD_READ,
    CRLF,
    ETX,
    STX,
    bcc,
    encode_block,
    make_frame,
)

__all__ = ["FAULTS", "SimT10A"]

FAULTS = ("checksum", "timeout", "garbage", "partial", "over_range", "unplug")


class SimT10A:
    """Simulated T-10A; use as a context manager or call start()/stop()."""

    def __init__(self, lux: float = 500.0, *, noise_rel: float = 0.0, period_s: float = 0.5,
                 seed: int = 0) -> None:
        self.lux = float(lux)
        self.noise_rel = float(noise_rel)
        self.period_s = float(period_s)
        self._rng = np.random.default_rng(seed)
        self._lock = threading.Lock()
        self._faults: list[tuple[str, int | None]] = []
        self._pc_mode = False
        self._reading = self.lux
        self._last_refresh = -1e9
        self._master = -1
        self._slave = -1
        self._attrs: list = []  # termios attribute list
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self.requests: list[bytes] = []
        self.port = ""

    # -- lifecycle --
    def start(self) -> None:
        self._master, self._slave = os.openpty()
        tty.setraw(self._slave)  # no CR/LF translation, no echo
        # Linux ptys refuse a second pyserial open once 7E1 was requested (tcsetattr EINVAL);
        # the meter restores its raw line settings while idle so clients can reopen the port.
        self._attrs = termios.tcgetattr(self._slave)
        self.port = os.ttyname(self._slave)
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name="sim-t10a", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            self._thread = None
        for fd in (self._master, self._slave):
            if fd >= 0:
                with contextlib.suppress(OSError):
                    os.close(fd)
        self._master = self._slave = -1

    def __enter__(self) -> Self:
        self.start()
        return self

    def __exit__(self, t: type[BaseException] | None, e: BaseException | None, tb: TracebackType | None) -> None:
        self.stop()

    # -- faults --
    def inject(self, kind: str, count: int | None = 1) -> None:
        """Apply fault ``kind`` to the next ``count`` replies (None: until :meth:`clear`)."""
        if kind not in FAULTS:
            raise ValueError(f"unknown fault {kind!r}; choose from {FAULTS}")
        with self._lock:
            self._faults.append((kind, count))

    def clear(self) -> None:
        with self._lock:
            self._faults.clear()

    def _take_fault(self) -> str | None:
        with self._lock:
            if not self._faults:
                return None
            kind, count = self._faults[0]
            if count is not None:
                if count <= 1:
                    self._faults.pop(0)
                else:
                    self._faults[0] = (kind, count - 1)
            return kind

    # -- the meter --
    def _current(self) -> float:
        now = time.monotonic()
        if now - self._last_refresh >= self.period_s:
            self._last_refresh = now
            self._reading = self.lux * (1.0 + self.noise_rel * float(self._rng.normal()))
        return self._reading

    def _answer(self, request: bytes) -> bytes | None:
        body = request[1:-4]
        if len(request) != 14 or request[-5:-4] != ETX or bcc(body) != request[-4:-2]:
            return None  # the real meter ignores frames it cannot read
        head, cmd = int(body[:2]), body[2:4].decode("ascii", "replace")
        if cmd == CMD_PC_MODE:
            self._pc_mode = True
            return make_frame(head, cmd, "    ")
        if cmd == CMD_READ and self._pc_mode:
            value = self._current()
            return make_frame(head, cmd, "  00", encode_block(value) + encode_block(0.0) + encode_block(0.0))
        return None

    def _faulty(self, reply: bytes, kind: str | None) -> bytes | None:
        if kind is None:
            return reply
        if kind == "timeout":
            return None
        if kind == "checksum":
            bad = b"00" if reply[-4:-2] != b"00" else b"11"
            return reply[:-4] + bad + CRLF
        if kind == "garbage":
            return bytes(self._rng.integers(0x20, 0x7F, 20, dtype=np.uint8).tolist()) + CRLF
        if kind == "partial":
            return reply[: len(reply) // 2]
        if kind == "over_range":
            return make_frame(int(reply[1:3]), reply[3:5].decode(), "5 00",
                              encode_block(0) + encode_block(0) + encode_block(0))
        return reply

    def _run(self) -> None:
        buf = b""
        while not self._stop.is_set():
            try:
                ready, _, _ = select.select([self._master], [], [], 0.05)
                if not ready:
                    with contextlib.suppress(termios.error, OSError):
                        termios.tcsetattr(self._slave, termios.TCSANOW, self._attrs)
                    continue
                buf += os.read(self._master, 256)
            except OSError:
                return
            while CRLF in buf:
                line, buf = buf.split(CRLF, 1)
                start = line.rfind(STX)
                if start < 0:
                    continue
                request = line[start:] + CRLF
                self.requests.append(request)
                reply = self._answer(request)
                if reply is None:
                    continue
                kind = self._take_fault()
                if kind == "unplug":
                    self._unplug()
                    return
                out = self._faulty(reply, kind)
                if out:
                    with contextlib.suppress(OSError):
                        os.write(self._master, out)

    def _unplug(self) -> None:
        """Close both ends: the client's next read or write fails as on a pulled USB adapter."""
        for fd in (self._master, self._slave):
            with contextlib.suppress(OSError):
                os.close(fd)
        self._master = self._slave = -1
