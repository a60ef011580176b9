"""Exposure and gain controls: the V4L2 implementation and the interface UVC-over-USB shares.

:class:`ControlBackend` is what :class:`lightprobe.drivers.v4l2.camera.V4L2Camera` needs to set exposure and
gain. :class:`V4L2Controls` does it with VIDIOC_QUERYCTRL / S_CTRL / G_CTRL by control *id*
(control names changed across kernels); ``lightprobe.drivers.uvc.UvcControls`` does it with UVC class
requests over pyusb, for devices whose V4L2 node lacks the controls.

Order matters and is always the same (``apply_all``): auto exposure -> manual (1) first, then
exposure auto priority -> 0 (keep the frame rate), then exposure absolute, then gain. UVC cameras
reset every control after a replug or power cycle, so the camera calls ``apply_all`` on every open.
Exposure crosses this boundary in seconds; V4L2 and UVC count 100 us units.
"""

from __future__ import annotations

import ctypes
import errno
import logging
from dataclasses import dataclass
from typing import Protocol, runtime_checkable

from lightprobe.drivers.base import ControlNotSupported

from . import _structs as S
from ._ioctl import IoctlError, IoctlTransport

__all__ = ["EXPOSURE_UNIT_S", "ControlBackend", "ControlInfo", "ControlRanges", "V4L2Controls"]

log = logging.getLogger(__name__)
EXPOSURE_UNIT_S = 1e-4  # V4L2_CID_EXPOSURE_ABSOLUTE and UVC CT_EXPOSURE_TIME_ABSOLUTE: 100 us


@dataclass(frozen=True)
class ControlInfo:
    """A control's range in device units (from QUERYCTRL or UVC GET_MIN/MAX/RES/DEF)."""

    id: int
    name: str
    minimum: int
    maximum: int
    step: int
    default: int
    flags: int = 0


@runtime_checkable
class ControlBackend(Protocol):
    """Exposure (seconds) and gain (factor, 1 = the device's default gain) on one device."""

    def probe(self) -> None:
        """Read control ranges; raise ControlNotSupported when there is no manual exposure."""
        ...

    @property
    def exposure_range(self) -> tuple[float, float]: ...

    @property
    def gain_range(self) -> tuple[float, float]: ...

    def current(self) -> tuple[float, float]:
        """(exposure_s, gain) as the device reports them now."""
        ...

    def apply_all(self, exposure_s: float | None, gain: float | None) -> tuple[float, float]:
        """Manual mode first, then exposure and gain; returns the quantised values set."""
        ...

    def set(self, exposure_s: float | None, gain: float | None) -> tuple[float, float]:
        """Change exposure and/or gain (manual mode already on); returns the values set."""
        ...


class ControlRanges:
    """Exposure and gain ranges in SI from device-unit controls, shared by V4L2 and UVC: exposure
    in 100 us units, gain as a factor of the control's default (1 = the device's unity gain)."""

    exposure: ControlInfo | None
    gain: ControlInfo | None

    @property
    def exposure_range(self) -> tuple[float, float]:
        assert self.exposure is not None
        return (max(self.exposure.minimum, 1) * EXPOSURE_UNIT_S, self.exposure.maximum * EXPOSURE_UNIT_S)

    @property
    def exposure_step_s(self) -> float:
        """The exposure grid: the control's step in 100 us units."""
        assert self.exposure is not None
        return max(self.exposure.step, 1) * EXPOSURE_UNIT_S

    def _unity(self) -> int:
        return max(self.gain.default, 1) if self.gain is not None else 1

    @property
    def gain_range(self) -> tuple[float, float]:
        if self.gain is None:
            return (1.0, 1.0)
        return (max(self.gain.minimum, 1) / self._unity(), self.gain.maximum / self._unity())


class V4L2Controls(ControlRanges):
    """Exposure/gain through V4L2 control ids on an open node.

    Gain: V4L2_CID_GAIN has no unit; the factor reported is ``raw / default`` (the default is
    taken as unity), which the response calibration absorbs. A device without GAIN reports a
    fixed gain of 1.
    """

    def __init__(self, transport: IoctlTransport) -> None:
        self.t = transport
        self.exposure: ControlInfo | None = None
        self.gain: ControlInfo | None = None
        self.has_auto = self.has_priority = False

    # ---- raw access -----------------------------------------------------------------------------
    def query(self, cid: int) -> ControlInfo | None:
        q = S.v4l2_queryctrl(id=cid)
        try:
            self.t.ioctl(self.t.abi.VIDIOC_QUERYCTRL, q)
        except IoctlError as e:
            if e.errno == errno.EINVAL:
                return None
            raise
        if q.flags & S.V4L2_CTRL_FLAG_DISABLED:
            return None
        name = bytes(q.name).split(b"\0", 1)[0].decode("ascii", "replace")
        return ControlInfo(cid, name, q.minimum, q.maximum, q.step, q.default_value, q.flags)

    def get_raw(self, cid: int) -> int:
        c = S.v4l2_control(id=cid)
        self._ioctl(self.t.abi.VIDIOC_G_CTRL, c, cid)
        return int(c.value)

    def set_raw(self, cid: int, value: int) -> None:
        self._ioctl(self.t.abi.VIDIOC_S_CTRL, S.v4l2_control(id=cid, value=int(value)), cid)

    def _ioctl(self, request: int, arg: ctypes.Structure, cid: int) -> None:
        try:
            self.t.ioctl(request, arg)
        except IoctlError as e:
            if e.errno in (errno.EINVAL, errno.ENOTTY, errno.EACCES, errno.ERANGE):
                raise ControlNotSupported(
                    f"{self.t.path}: control 0x{cid:08x} rejected ({e})", device=self.t.path
                ) from e
            raise

    # ---- ControlBackend -------------------------------------------------------------------------
    def probe(self) -> None:
        self.exposure = self.query(S.V4L2_CID_EXPOSURE_ABSOLUTE)
        self.gain = self.query(S.V4L2_CID_GAIN)
        self.has_auto = self.query(S.V4L2_CID_EXPOSURE_AUTO) is not None
        self.has_priority = self.query(S.V4L2_CID_EXPOSURE_AUTO_PRIORITY) is not None
        if self.exposure is None:
            raise ControlNotSupported(
                f"{self.t.path} has no EXPOSURE_ABSOLUTE control (0x009a0902): no manual exposure",
                device=self.t.path,
            )


    def current(self) -> tuple[float, float]:
        exp = self.get_raw(S.V4L2_CID_EXPOSURE_ABSOLUTE) * EXPOSURE_UNIT_S
        gain = self.get_raw(S.V4L2_CID_GAIN) / self._unity() if self.gain is not None else 1.0
        return exp, gain

    def apply_all(self, exposure_s: float | None, gain: float | None) -> tuple[float, float]:
        if self.has_auto:  # manual mode first: exposure absolute is inactive while auto is on
            self.set_raw(S.V4L2_CID_EXPOSURE_AUTO, S.V4L2_EXPOSURE_MANUAL)
        if self.has_priority:
            self.set_raw(S.V4L2_CID_EXPOSURE_AUTO_PRIORITY, 0)
        cur_exp, cur_gain = self.current()
        return self.set(cur_exp if exposure_s is None else exposure_s, cur_gain if gain is None else gain)

    def set(self, exposure_s: float | None, gain: float | None) -> tuple[float, float]:
        assert self.exposure is not None
        cur_exp, cur_gain = self.current()
        if exposure_s is not None:
            raw = _quantise(exposure_s / EXPOSURE_UNIT_S, self.exposure)
            self.set_raw(S.V4L2_CID_EXPOSURE_ABSOLUTE, raw)
            cur_exp = raw * EXPOSURE_UNIT_S
        if gain is not None and self.gain is not None:
            raw = _quantise(gain * self._unity(), self.gain)
            self.set_raw(S.V4L2_CID_GAIN, raw)
            cur_gain = raw / self._unity()
        return cur_exp, cur_gain


def _quantise(value: float, info: ControlInfo) -> int:
    """Round to the control's step grid and clamp to its range."""
    step = max(info.step, 1)
    raw = info.minimum + round((value - info.minimum) / step) * step
    return int(min(max(raw, info.minimum), info.maximum))
