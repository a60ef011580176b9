"""ctypes mirrors of the videodev2.h structs we use, for both ARM ABIs, and the ioctl numbers.

The project is Apache-2.0, so this is our own layer (linuxpy is GPL-3.0). Every struct is declared
with ``_pack_ = 1`` and *explicit* padding, so a layout does not depend on the host that imports
it: :data:`ABI64` is the LP64 layout (aarch64, x86_64: ``long``/pointers 8 bytes, ``struct
timeval`` 16 bytes, unions holding pointers aligned to 8) and :data:`ABI32` the ILP32 ARM EABI
layout with the kernel's 32-bit ``struct timeval`` (8 bytes; what ``VIDIOC_*_TIME32`` decodes, so
it also works under a 64-bit ``time_t`` libc). The kernel tells the two apart by the size encoded
in the ioctl number, so a struct and its ioctl numbers must always come from the same
:class:`V4L2Abi`.

Sizes (kernel videodev2.h): v4l2_capability 104, v4l2_fmtdesc 64, v4l2_frmsizeenum 44,
v4l2_frmivalenum 52, v4l2_format 208 / 204, v4l2_requestbuffers 20, v4l2_buffer 88 / 68,
v4l2_control 8, v4l2_queryctrl 68, v4l2_ext_control 20 (packed), v4l2_ext_controls 32 / 24,
v4l2_streamparm 204. ioctl numbers use the asm-generic ``_IOC`` encoding (ARM and arm64 share it):
``dir << 30 | size << 16 | type << 8 | nr``.

Importing this module builds a few ctypes classes and does nothing else.
"""

from __future__ import annotations

import ctypes
import itertools
import struct
from dataclasses import dataclass
from typing import Any

__all__ = [
    "ABI32",
    "ABI64",
    "HOST_ABI",
    "V4L2Abi",
    "fourcc",
    "fourcc_str",
    "ioc",
]

# ---- _IOC encoding (include/uapi/asm-generic/ioctl.h) -------------------------------------------
_IOC_NONE, _IOC_WRITE, _IOC_READ = 0, 1, 2


def ioc(direction: int, type_: str, nr: int, size: int) -> int:
    """``_IOC(dir, type, nr, size)``: dir in bits 30-31, size 16-29, type 8-15, nr 0-7."""
    if not 0 <= size < (1 << 14):
        raise ValueError(f"ioctl size {size} does not fit 14 bits")
    return (direction << 30) | (size << 16) | (ord(type_) << 8) | nr


def _ior(nr: int, size: int) -> int:
    return ioc(_IOC_READ, "V", nr, size)


def _iow(nr: int, size: int) -> int:
    return ioc(_IOC_WRITE, "V", nr, size)


def _iowr(nr: int, size: int) -> int:
    return ioc(_IOC_READ | _IOC_WRITE, "V", nr, size)


def fourcc(code: str) -> int:
    """``v4l2_fourcc(a, b, c, d)``: little-endian packing of four ASCII characters."""
    if len(code) != 4:
        raise ValueError(f"fourcc needs 4 characters, got {code!r}")
    a, b, c, d = (ord(ch) for ch in code)
    return a | (b << 8) | (c << 16) | (d << 24)


def fourcc_str(value: int) -> str:
    """Inverse of :func:`fourcc` (the big-endian flag bit 31 is dropped)."""
    value &= 0x7FFFFFFF
    return "".join(chr((value >> (8 * i)) & 0xFF) for i in range(4))


# ---- constants (videodev2.h, v4l2-controls.h) ---------------------------------------------------
V4L2_BUF_TYPE_VIDEO_CAPTURE = 1
V4L2_MEMORY_MMAP = 1
V4L2_FIELD_ANY, V4L2_FIELD_NONE = 0, 1

V4L2_CAP_VIDEO_CAPTURE = 0x00000001
V4L2_CAP_STREAMING = 0x04000000
V4L2_CAP_DEVICE_CAPS = 0x80000000

V4L2_BUF_FLAG_MAPPED = 0x1
V4L2_BUF_FLAG_QUEUED = 0x2
V4L2_BUF_FLAG_DONE = 0x4
V4L2_BUF_FLAG_ERROR = 0x40
V4L2_BUF_FLAG_TIMESTAMP_MASK = 0xE000
V4L2_BUF_FLAG_TIMESTAMP_MONOTONIC = 0x2000
V4L2_BUF_FLAG_TSTAMP_SRC_MASK = 0x70000
V4L2_BUF_FLAG_TSTAMP_SRC_EOF = 0x00000
V4L2_BUF_FLAG_TSTAMP_SRC_SOE = 0x10000

V4L2_FRMSIZE_TYPE_DISCRETE, V4L2_FRMSIZE_TYPE_CONTINUOUS, V4L2_FRMSIZE_TYPE_STEPWISE = 1, 2, 3
V4L2_FRMIVAL_TYPE_DISCRETE = 1

V4L2_CTRL_TYPE_INTEGER, V4L2_CTRL_TYPE_BOOLEAN, V4L2_CTRL_TYPE_MENU = 1, 2, 3
V4L2_CTRL_FLAG_DISABLED = 0x0001
V4L2_CTRL_FLAG_READ_ONLY = 0x0004
V4L2_CTRL_FLAG_INACTIVE = 0x0010

V4L2_CID_BASE = 0x00980900
V4L2_CID_AUTO_WHITE_BALANCE = V4L2_CID_BASE + 12
V4L2_CID_EXPOSURE = V4L2_CID_BASE + 17
V4L2_CID_AUTOGAIN = V4L2_CID_BASE + 18
V4L2_CID_GAIN = V4L2_CID_BASE + 19
V4L2_CID_CAMERA_CLASS_BASE = 0x009A0900
V4L2_CID_EXPOSURE_AUTO = V4L2_CID_CAMERA_CLASS_BASE + 1  # 0x009a0901, menu
V4L2_CID_EXPOSURE_ABSOLUTE = V4L2_CID_CAMERA_CLASS_BASE + 2  # 0x009a0902, 100 us units
V4L2_CID_EXPOSURE_AUTO_PRIORITY = V4L2_CID_CAMERA_CLASS_BASE + 3  # 0x009a0903, bool
V4L2_CID_ANALOGUE_GAIN = 0x009E0903
V4L2_EXPOSURE_AUTO, V4L2_EXPOSURE_MANUAL = 0, 1
V4L2_EXPOSURE_SHUTTER_PRIORITY, V4L2_EXPOSURE_APERTURE_PRIORITY = 2, 3

V4L2_PIX_FMT_YUYV = fourcc("YUYV")
V4L2_PIX_FMT_MJPEG = fourcc("MJPG")
V4L2_PIX_FMT_GREY = fourcc("GREY")
V4L2_PIX_FMT_Y16 = fourcc("Y16 ")
V4L2_PIX_FMT_RGB24 = fourcc("RGB3")
# Bayer: fourcc -> (pattern of the top-left 2x2 block read row-wise, bits per sample).
BAYER_FORMATS: dict[int, tuple[str, int]] = {
    fourcc("BA81"): ("BGGR", 8), fourcc("GBRG"): ("GBRG", 8),
    fourcc("GRBG"): ("GRBG", 8), fourcc("RGGB"): ("RGGB", 8),
    fourcc("BG10"): ("BGGR", 10), fourcc("GB10"): ("GBRG", 10),
    fourcc("BA10"): ("GRBG", 10), fourcc("RG10"): ("RGGB", 10),
    fourcc("BG12"): ("BGGR", 12), fourcc("GB12"): ("GBRG", 12),
    fourcc("BA12"): ("GRBG", 12), fourcc("RG12"): ("RGGB", 12),
    fourcc("BYR2"): ("BGGR", 16), fourcc("GB16"): ("GBRG", 16),
    fourcc("GR16"): ("GRBG", 16), fourcc("RG16"): ("RGGB", 16),
}  # fmt: skip


# ---- layouts ------------------------------------------------------------------------------------
class _S(ctypes.Structure):
    _pack_ = 1


class _U(ctypes.Union):
    _pack_ = 1


_pad_ids = itertools.count()


def _pad(n: int) -> list[tuple[str, Any]]:
    """An explicit padding field of n bytes (none when n == 0)."""
    return [(f"_pad{next(_pad_ids)}", ctypes.c_uint8 * n)] if n else []


u8, u32, s32 = ctypes.c_uint8, ctypes.c_uint32, ctypes.c_int32


class v4l2_capability(_S):
    _fields_ = [("driver", u8 * 16), ("card", u8 * 32), ("bus_info", u8 * 32), ("version", u32),
                ("capabilities", u32), ("device_caps", u32), ("reserved", u32 * 3)]  # fmt: skip


class v4l2_fmtdesc(_S):
    _fields_ = [("index", u32), ("type", u32), ("flags", u32), ("description", u8 * 32),
                ("pixelformat", u32), ("mbus_code", u32), ("reserved", u32 * 3)]  # fmt: skip


class v4l2_frmsize_discrete(_S):
    _fields_ = [("width", u32), ("height", u32)]


class v4l2_frmsize_stepwise(_S):
    _fields_ = [("min_width", u32), ("max_width", u32), ("step_width", u32),
                ("min_height", u32), ("max_height", u32), ("step_height", u32)]  # fmt: skip


class _frmsize_u(_U):
    _fields_ = [("discrete", v4l2_frmsize_discrete), ("stepwise", v4l2_frmsize_stepwise)]


class v4l2_frmsizeenum(_S):
    _anonymous_ = ("u",)
    _fields_ = [("index", u32), ("pixel_format", u32), ("type", u32), ("u", _frmsize_u),
                ("reserved", u32 * 2)]  # fmt: skip


class v4l2_fract(_S):
    _fields_ = [("numerator", u32), ("denominator", u32)]


class _frmival_u(_U):
    _fields_ = [("discrete", v4l2_fract), ("stepwise", v4l2_fract * 3)]


class v4l2_frmivalenum(_S):
    _anonymous_ = ("u",)
    _fields_ = [("index", u32), ("pixel_format", u32), ("width", u32), ("height", u32),
                ("type", u32), ("u", _frmival_u), ("reserved", u32 * 2)]  # fmt: skip


class v4l2_pix_format(_S):
    _fields_ = [("width", u32), ("height", u32), ("pixelformat", u32), ("field", u32),
                ("bytesperline", u32), ("sizeimage", u32), ("colorspace", u32), ("priv", u32),
                ("flags", u32), ("ycbcr_enc", u32), ("quantization", u32), ("xfer_func", u32)]  # fmt: skip


class _format_u(_U):
    _fields_ = [("pix", v4l2_pix_format), ("raw_data", u8 * 200)]


class v4l2_requestbuffers(_S):
    _fields_ = [("count", u32), ("type", u32), ("memory", u32), ("capabilities", u32),
                ("flags", u8), ("reserved", u8 * 3)]  # fmt: skip


class v4l2_timecode(_S):
    _fields_ = [("type", u32), ("flags", u32), ("frames", u8), ("seconds", u8), ("minutes", u8),
                ("hours", u8), ("userbits", u8 * 4)]  # fmt: skip


class v4l2_control(_S):
    _fields_ = [("id", u32), ("value", s32)]


class v4l2_queryctrl(_S):
    _fields_ = [("id", u32), ("type", u32), ("name", u8 * 32), ("minimum", s32), ("maximum", s32),
                ("step", s32), ("default_value", s32), ("flags", u32), ("reserved", u32 * 2)]  # fmt: skip


class _ext_control_u(_U):
    _fields_ = [("value", s32), ("value64", ctypes.c_int64)]


class v4l2_ext_control(_S):  # __attribute__((packed)) in the kernel: same on both ABIs
    _anonymous_ = ("u",)
    _fields_ = [("id", u32), ("size", u32), ("reserved2", u32), ("u", _ext_control_u)]


class v4l2_captureparm(_S):
    _fields_ = [("capability", u32), ("capturemode", u32), ("timeperframe", v4l2_fract),
                ("extendedmode", u32), ("readbuffers", u32), ("reserved", u32 * 4)]  # fmt: skip


class _streamparm_u(_U):
    _fields_ = [("capture", v4l2_captureparm), ("raw_data", u8 * 200)]


class v4l2_streamparm(_S):
    _fields_ = [("type", u32), ("parm", _streamparm_u)]


def _abi_structs(bits: int) -> dict[str, type[ctypes.Structure]]:
    """The structs whose layout differs between LP64 and ILP32 (long, pointers, timeval)."""
    wide = bits == 64
    long_t = ctypes.c_int64 if wide else ctypes.c_int32
    ulong_t = ctypes.c_uint64 if wide else ctypes.c_uint32

    class timeval(_S):
        _fields_ = [("tv_sec", long_t), ("tv_usec", long_t)]

    class _buffer_m(_U):
        _fields_ = [("offset", u32), ("userptr", ulong_t), ("fd", s32)]

    class v4l2_buffer(_S):
        _fields_ = [
            ("index", u32), ("type", u32), ("bytesused", u32), ("flags", u32), ("field", u32),
            *_pad(4 if wide else 0),  # timeval is 8-aligned on LP64
            ("timestamp", timeval), ("timecode", v4l2_timecode), ("sequence", u32),
            ("memory", u32), ("m", _buffer_m), ("length", u32), ("reserved2", u32),
            ("request_fd", s32),
            *_pad(4 if wide else 0),  # tail padding to the 8-byte alignment
        ]  # fmt: skip

    class v4l2_format(_S):
        # the fmt union holds struct v4l2_window (pointers): 8-aligned on LP64
        _fields_ = [("type", u32), *_pad(4 if wide else 0), ("fmt", _format_u)]

    class v4l2_ext_controls(_S):
        _fields_ = [("which", u32), ("count", u32), ("error_idx", u32), ("request_fd", s32),
                    ("reserved", u32), *_pad(4 if wide else 0), ("controls", ulong_t)]  # fmt: skip

    for cls in (timeval, _buffer_m, v4l2_buffer, v4l2_format, v4l2_ext_controls):
        cls.__qualname__ = f"{cls.__name__}_{bits}"
    return {"timeval": timeval, "v4l2_buffer": v4l2_buffer, "v4l2_format": v4l2_format,
            "v4l2_ext_controls": v4l2_ext_controls}  # fmt: skip


@dataclass(frozen=True)
class V4L2Abi:
    """One ABI: its struct classes and the ioctl numbers computed from their sizes."""

    name: str
    bits: int
    buffer: type[ctypes.Structure]
    format: type[ctypes.Structure]
    ext_controls: type[ctypes.Structure]
    ioctls: dict[str, int]

    @classmethod
    def build(cls, name: str, bits: int) -> V4L2Abi:
        s = _abi_structs(bits)
        size = ctypes.sizeof
        buf, fmt, ext = s["v4l2_buffer"], s["v4l2_format"], s["v4l2_ext_controls"]
        ioctls = {
            "VIDIOC_QUERYCAP": _ior(0, size(v4l2_capability)),
            "VIDIOC_ENUM_FMT": _iowr(2, size(v4l2_fmtdesc)),
            "VIDIOC_G_FMT": _iowr(4, size(fmt)),
            "VIDIOC_S_FMT": _iowr(5, size(fmt)),
            "VIDIOC_REQBUFS": _iowr(8, size(v4l2_requestbuffers)),
            "VIDIOC_QUERYBUF": _iowr(9, size(buf)),
            "VIDIOC_QBUF": _iowr(15, size(buf)),
            "VIDIOC_DQBUF": _iowr(17, size(buf)),
            "VIDIOC_STREAMON": _iow(18, size(ctypes.c_int)),
            "VIDIOC_STREAMOFF": _iow(19, size(ctypes.c_int)),
            "VIDIOC_G_PARM": _iowr(21, size(v4l2_streamparm)),
            "VIDIOC_S_PARM": _iowr(22, size(v4l2_streamparm)),
            "VIDIOC_G_CTRL": _iowr(27, size(v4l2_control)),
            "VIDIOC_S_CTRL": _iowr(28, size(v4l2_control)),
            "VIDIOC_QUERYCTRL": _iowr(36, size(v4l2_queryctrl)),
            "VIDIOC_G_EXT_CTRLS": _iowr(71, size(ext)),
            "VIDIOC_S_EXT_CTRLS": _iowr(72, size(ext)),
            "VIDIOC_ENUM_FRAMESIZES": _iowr(74, size(v4l2_frmsizeenum)),
            "VIDIOC_ENUM_FRAMEINTERVALS": _iowr(75, size(v4l2_frmivalenum)),
        }
        return cls(name, bits, buf, fmt, ext, ioctls)

    def request_name(self, request: int) -> str:
        """The VIDIOC_* name of an ioctl number of this ABI (for logs and the fake device)."""
        for k, v in self.ioctls.items():
            if v == request:
                return k
        return f"0x{request:08x}"

    def __getattr__(self, item: str) -> int:
        ioctls = object.__getattribute__(self, "ioctls")
        if item in ioctls:
            return int(ioctls[item])
        raise AttributeError(item)


ABI64 = V4L2Abi.build("lp64", 64)
ABI32 = V4L2Abi.build("arm-eabi-ilp32", 32)
HOST_ABI = ABI64 if struct.calcsize("P") == 8 else ABI32
