"""Konica Minolta T-10A illuminance meter over a serial port (pyserial).

Protocol (T-10A communication specification; see ../shared/NOTES.md): 9600 baud, 7 data bits,
even parity, 1 stop bit. Every frame is ``STX head(2) command(2) parameter(4) ETX BCC(2) CR LF``
where BCC is the XOR of the bytes after STX up to and including ETX, written as two upper-case
ASCII hex digits. Replies echo head and command, carry a 4-character status in place of the
parameter and, for command 10 (read measurement), three 6-byte data blocks (illuminance, delta,
percent) between status and ETX: ``sign d d d d e`` with value = dddd x 10^(e-4). Command 54
with parameter ``"1   "`` puts the meter in PC mode and must be sent first. The meter refreshes
its reading every 500 ms, so reading faster returns repeated values.

Status (as implemented here): character 0 is the error flag, ``' '`` or ``'0'`` normal,
``'1'`` receptor head off, ``'2'``/``'3'`` EEPROM error, ``'5'`` over range; character 3 is
``'1'`` when the battery is low (a warning, not an error).

Errors are typed (:class:`T10AChecksumError`, :class:`T10ATimeout`, :class:`T10AGarbage`,
:class:`T10ADisconnected`, :class:`T10AMeterError`); a transaction is retried at most
``retries`` times for checksum, garbage and timeout errors, never for a disconnect, and every
read has a deadline, so no call can hang. Importing this module opens nothing.
"""

from __future__ import annotations

import contextlib
import termios
import time
from dataclasses import dataclass
from types import TracebackType
from typing import Any, Self

import serial

from lightprobe.core.errors import LightprobeError

__all__ = [
    "T10A",
    "Reply",
    "T10AChecksumError",
    "T10ADisconnected",
    "T10AError",
    "T10AGarbage",
    "T10AMeterError",
    "T10ATimeout",
    "bcc",
    "decode_block",
    "encode_block",
    "make_frame",
    "parse_reply",
]

STX, ETX, CRLF = b"\x02", b"\x03", b"\r\n"
CMD_READ, CMD_INTEGRATED, CMD_CLEAR, CMD_PC_MODE, CMD_HOLD = "10", "11", "28", "54", "55"
SHORT_LEN, LONG_LEN = 14, 32
POLL_S = 0.05  # read granularity; the port timeout is fixed so reads never reconfigure the tty
STATUS_ERRORS = {"1": "receptor head power is off", "2": "EEPROM error 1", "3": "EEPROM error 2",
                 "5": "measurement over range", "6": "measurement error"}


class T10AError(LightprobeError):
    """Base class of lux meter errors; ``port`` names the serial port."""

    def __init__(self, message: str, *, port: str = "") -> None:
        super().__init__(f"{port}: {message}" if port else message)
        self.port = port


class T10AChecksumError(T10AError):
    """A reply's BCC does not match its content."""


class T10ATimeout(T10AError, TimeoutError):
    """No complete reply within the timeout."""


class T10AGarbage(T10AError):
    """Bytes that are not a T-10A frame (wrong length, framing, head, command or digits)."""


class T10ADisconnected(T10AError):
    """The serial port went away (unplugged adapter, closed pty)."""


class T10AMeterError(T10AError):
    """The meter answered with an error status (head off, EEPROM, over range)."""


def bcc(body: bytes) -> bytes:
    """Block check: XOR of ``body`` (the bytes after STX through ETX) as two hex digits."""
    x = 0
    for b in body:
        x ^= b
    return f"{x:02X}".encode("ascii")


def make_frame(head: int, command: str, parameter: str, data: bytes = b"") -> bytes:
    """``STX head command parameter [data] ETX BCC CR LF`` (parameter padded to 4 chars)."""
    body = f"{head:02d}{command}{parameter:<4.4s}".encode("ascii") + data + ETX
    return STX + body + bcc(body) + CRLF


def encode_block(value: float) -> bytes:
    """A 6-byte data block ``sign dddd e`` with value = dddd x 10^(e-4), e in 0..9."""
    sign = b"-" if value < 0 else b"+"
    v = abs(float(value))
    e = 0
    while e < 9 and round(v / 10.0 ** (e - 4)) > 9999:
        e += 1
    digits = min(round(v / 10.0 ** (e - 4)), 9999)
    return sign + f"{digits:04d}{e:d}".encode("ascii")


def decode_block(block: bytes) -> float:
    """Value of a 6-byte data block; raises T10AGarbage on anything else."""
    if len(block) != 6 or block[:1] not in (b"+", b"-", b" ") or not block[1:].isdigit():
        raise T10AGarbage(f"bad data block {block!r}")
    value = int(block[1:5]) * 10.0 ** (int(block[5:6]) - 4)
    return -value if block[:1] == b"-" else value


@dataclass(frozen=True)
class Reply:
    head: int
    command: str
    status: str
    values: tuple[float, ...]

    @property
    def battery_low(self) -> bool:
        return self.status[3:4] == "1"


def parse_reply(raw: bytes, command: str, head: int = 0) -> Reply:
    """Validate framing, checksum, head and command of one reply; decode its data blocks."""
    start = raw.rfind(STX)
    if start < 0 or not raw.endswith(CRLF):
        raise T10AGarbage(f"no STX...CR LF frame in {raw[:40]!r}")
    frame = raw[start:]
    if len(frame) not in (SHORT_LEN, LONG_LEN) or frame[-5:-4] != ETX:
        raise T10AGarbage(f"malformed frame {frame!r}")
    body, check = frame[1:-4], frame[-4:-2]
    if bcc(body) != check:
        raise T10AChecksumError(f"BCC mismatch: got {check!r}, computed {bcc(body)!r}")
    try:
        text = body[:-1].decode("ascii")
    except UnicodeDecodeError as e:
        raise T10AGarbage(f"non-ASCII frame {frame!r}") from e
    if text[:2] != f"{head:02d}" or text[2:4] != command:
        raise T10AGarbage(f"reply for head {text[:2]!r} command {text[2:4]!r}, expected {head:02d}/{command}")
    status = text[4:8]
    blocks = body[8:-1]
    values = tuple(decode_block(blocks[i : i + 6]) for i in range(0, len(blocks), 6))
    return Reply(head, command, status, values)


class T10A:
    """Client of one T-10A on ``port`` (a device path or any pyserial URL).

    Parameters
    ----------
    timeout
        Seconds to wait for one complete reply.
    retries
        Extra attempts after a checksum, garbage or timeout error (disconnects are not retried).
    """

    def __init__(self, port: str, *, head: int = 0, timeout: float = 1.0, retries: int = 2) -> None:
        self.port = port
        self.head = head
        self.timeout = float(timeout)
        self.retries = int(retries)
        self._ser: Any = None
        self.battery_low = False

    # -- lifecycle --
    def open(self) -> None:
        """Open the port and switch the meter to PC mode (command 54)."""
        try:
            self._ser = serial.serial_for_url(self.port, baudrate=9600, bytesize=serial.SEVENBITS,
                                              parity=serial.PARITY_EVEN, stopbits=serial.STOPBITS_ONE,
                                              timeout=POLL_S, write_timeout=self.timeout)
        except (serial.SerialException, OSError, termios.error) as e:
            raise T10ADisconnected(f"cannot open serial port ({e})", port=self.port) from e
        self.connect()

    def close(self) -> None:
        if self._ser is not None:
            with contextlib.suppress(serial.SerialException, OSError, termios.error):
                self._ser.close()
            self._ser = None

    def __enter__(self) -> Self:
        self.open()
        return self

    def __exit__(self, t: type[BaseException] | None, e: BaseException | None, tb: TracebackType | None) -> None:
        self.close()

    # -- commands --
    def connect(self) -> None:
        """PC-connect mode (command 54, parameter ``"1   "``)."""
        self._transact(CMD_PC_MODE, "1   ")

    def read_lux(self, *, ccf: bool = False, range_: int = 0) -> float:
        """One illuminance reading in lux (command 10: run, CCF on/off, range 0 = auto)."""
        param = f"0{3 if ccf else 2}{range_:d}0"
        reply = self._transact(CMD_READ, param)
        if not reply.values:
            raise T10AGarbage("measurement reply without data blocks", port=self.port)
        return reply.values[0]

    def read_many(self, n: int, *, interval: float = 0.5) -> list[float]:
        """``n`` readings ``interval`` seconds apart (the meter refreshes every 500 ms)."""
        out = []
        for i in range(n):
            if i:
                time.sleep(interval)
            out.append(self.read_lux())
        return out

    # -- transport --
    def _transact(self, command: str, parameter: str) -> Reply:
        if self._ser is None:
            raise T10ADisconnected("port is not open", port=self.port)
        frame = make_frame(self.head, command, parameter)
        last: T10AError | None = None
        for _attempt in range(self.retries + 1):
            try:
                raw = self._exchange(frame)
                reply = parse_reply(raw, command, self.head)
            except (T10AChecksumError, T10AGarbage, T10ATimeout) as e:
                last = e if e.port else type(e)(str(e), port=self.port)
                continue
            code = reply.status[:1]
            if code not in (" ", "0"):
                raise T10AMeterError(STATUS_ERRORS.get(code, f"status {reply.status!r}"), port=self.port)
            self.battery_low = reply.battery_low
            return reply
        assert last is not None
        raise type(last)(f"{last} (after {self.retries + 1} attempts)")

    def _exchange(self, frame: bytes) -> bytes:
        """Write one frame, read one reply line before the deadline."""
        ser = self._ser
        try:
            ser.reset_input_buffer()
            ser.write(frame)
            ser.flush()
            deadline = time.monotonic() + self.timeout
            buf = b""
            while not buf.endswith(CRLF) and time.monotonic() < deadline:
                buf += ser.read(max(1, min(ser.in_waiting, 128)))
                if len(buf) >= 128:
                    raise T10AGarbage(f"no frame end in {buf[:40]!r}...", port=self.port)
        except (serial.SerialException, OSError, termios.error) as e:
            self.close()
            raise T10ADisconnected(f"serial port lost ({e})", port=self.port) from e
        if not buf:
            raise T10ATimeout(f"no reply within {self.timeout:g} s", port=self.port)
        if not buf.endswith(CRLF):
            raise T10ATimeout(f"incomplete reply {buf[:40]!r} within {self.timeout:g} s", port=self.port)
        return buf
