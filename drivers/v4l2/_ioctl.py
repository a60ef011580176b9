"""The ioctl transport: the only place that touches a V4L2 device node.

:class:`IoctlTransport` is the seam between the V4L2 logic (``lightprobe.drivers.v4l2.camera``) and the
kernel. :class:`DeviceTransport` is the real one: ``os.open`` (non-blocking) + ``fcntl.ioctl`` +
``mmap``. ``lightprobe.sim.v4l2_fake.FakeV4L2Device`` implements the same interface for tests: it decodes
the request numbers and struct bytes like the kernel would and records every call.

errno mapping (done here, once): ENOENT/ENXIO at open -> CameraUnavailable, EACCES/EPERM ->
CameraUnavailable with a hint about the ``video`` group, EBUSY -> CameraBusy, ENODEV/EIO/ENXIO
while open -> CameraDisconnected. EAGAIN is passed up as ``BlockingIOError`` (no frame yet), EINVAL
as :class:`IoctlError` so callers can turn it into ControlNotSupported where that is what it means.
Importing this module does nothing.
"""

from __future__ import annotations

import contextlib
import ctypes
import errno
import fcntl
import mmap
import os
from typing import Protocol, runtime_checkable

from lightprobe.drivers.base import CameraBusy, CameraDisconnected, CameraError, CameraUnavailable

from ._structs import HOST_ABI, V4L2Abi

__all__ = ["DeviceTransport", "IoctlError", "IoctlTransport", "open_error"]

_GONE = {errno.ENODEV, errno.EIO, errno.ENXIO, errno.ESHUTDOWN}


class IoctlError(CameraError, OSError):
    """An ioctl failed with an errno that is not a disconnect or busy (e.g. EINVAL)."""

    def __init__(self, request: str, err: int, *, device: str | None = None) -> None:
        CameraError.__init__(self, f"{request} failed: {os.strerror(err)}", device=device)
        self.errno = err
        self.request = request


@runtime_checkable
class IoctlTransport(Protocol):
    """What the V4L2 camera needs from a device node."""

    path: str
    abi: V4L2Abi

    def fileno(self) -> int:
        """An fd that polls readable when a buffer is ready to dequeue."""
        ...

    def ioctl(self, request: int, arg: ctypes.Structure | ctypes.c_int) -> None:
        """Run one ioctl; ``arg`` is read and written in place like the kernel does."""
        ...

    def mmap(self, length: int, offset: int) -> memoryview:
        """Map a driver buffer (offset from VIDIOC_QUERYBUF)."""
        ...

    def unmap(self, view: memoryview) -> None:
        """Release a mapping returned by :meth:`mmap`."""
        ...

    def close(self) -> None:
        """Close the node; safe to call twice."""
        ...


def open_error(path: str, err: OSError) -> CameraError:
    """Map an ``os.open`` failure on a video node to a typed camera error."""
    code = err.errno or 0
    if code == errno.EBUSY:
        return CameraBusy(f"{path} is busy: another process is using the camera", device=path)
    if code in (errno.EACCES, errno.EPERM):
        return CameraUnavailable(
            f"no permission to open {path}: add the service user to the 'video' group", device=path
        )
    if code in (errno.ENOENT, errno.ENXIO, errno.ENODEV):
        return CameraUnavailable(f"{path} does not exist (camera not attached?)", device=path)
    return CameraUnavailable(f"cannot open {path}: {os.strerror(code)}", device=path)


class DeviceTransport:
    """A real ``/dev/video*`` node (opened non-blocking, so DQBUF returns EAGAIN when empty).

    Open by the stable ``/dev/v4l/by-id/...`` path: it follows the camera across replugs, where
    the ``/dev/videoN`` number may change.
    """

    def __init__(self, path: str, abi: V4L2Abi = HOST_ABI) -> None:
        self.path = path
        self.abi = abi
        try:
            self._fd: int | None = os.open(path, os.O_RDWR | os.O_NONBLOCK | os.O_CLOEXEC)
        except OSError as e:
            raise open_error(path, e) from e
        self._maps: list[mmap.mmap] = []

    def fileno(self) -> int:
        if self._fd is None:
            raise CameraDisconnected(f"{self.path} is closed", device=self.path)
        return self._fd

    def ioctl(self, request: int, arg: ctypes.Structure | ctypes.c_int) -> None:
        fd = self.fileno()
        while True:
            try:
                fcntl.ioctl(fd, request, arg, True)
            except InterruptedError:
                continue
            except BlockingIOError:
                raise
            except OSError as e:
                raise self._map_error(request, e) from e
            return

    def _map_error(self, request: int, e: OSError) -> Exception:
        name = self.abi.request_name(request)
        code = e.errno or 0
        if code in _GONE:
            return CameraDisconnected(f"{self.path} went away during {name}", device=self.path)
        if code == errno.EBUSY:
            return CameraBusy(f"{self.path}: {name} busy (another process streams?)", device=self.path)
        return IoctlError(name, code, device=self.path)

    def mmap(self, length: int, offset: int) -> memoryview:
        m = mmap.mmap(self.fileno(), length, mmap.MAP_SHARED, mmap.PROT_READ | mmap.PROT_WRITE,
                      offset=offset)  # fmt: skip
        self._maps.append(m)
        return memoryview(m)

    def unmap(self, view: memoryview) -> None:
        obj = view.obj
        view.release()
        if isinstance(obj, mmap.mmap) and obj in self._maps:
            self._maps.remove(obj)
            with contextlib.suppress(BufferError):  # a frame still references it: GC unmaps later
                obj.close()

    def close(self) -> None:
        for m in self._maps:
            with contextlib.suppress(BufferError):  # a view is still exported; GC unmaps later
                m.close()
        self._maps.clear()
        if self._fd is not None:
            fd, self._fd = self._fd, None
            os.close(fd)
