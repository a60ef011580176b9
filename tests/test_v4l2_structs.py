"""Struct layouts and ioctl numbers of lightprobe.drivers.v4l2._structs against the kernel's videodev2.h.

Two independent checks: (1) sizes, offsets and ioctl numbers written down from videodev2.h for
LP64 (aarch64/x86_64) and 32-bit ARM EABI; (2) when a C compiler and the kernel headers are
present, every field offset and size is compiled against the real header with _Static_assert
(the host's ABI, and -m32 when a 32-bit toolchain is installed; skipped otherwise).
"""

from __future__ import annotations

import ctypes
import shutil
import subprocess
from pathlib import Path

import pytest

from lightprobe.drivers.v4l2 import _structs as S
from lightprobe.drivers.v4l2._structs import ABI32, ABI64, V4L2Abi, fourcc, fourcc_str, ioc

# (struct, LP64 size, ARM EABI size) from videodev2.h
KERNEL_SIZES = {
    "v4l2_capability": (104, 104), "v4l2_fmtdesc": (64, 64), "v4l2_frmsizeenum": (44, 44),
    "v4l2_frmivalenum": (52, 52), "v4l2_format": (208, 204), "v4l2_pix_format": (48, 48),
    "v4l2_requestbuffers": (20, 20), "v4l2_buffer": (88, 68), "v4l2_timecode": (16, 16),
    "v4l2_control": (8, 8), "v4l2_queryctrl": (68, 68), "v4l2_ext_control": (20, 20),
    "v4l2_ext_controls": (32, 24), "v4l2_streamparm": (204, 204),
}  # fmt: skip
# struct v4l2_buffer offsets: (LP64, ARM EABI)
BUFFER_OFFSETS = {
    "index": (0, 0), "type": (4, 4), "bytesused": (8, 8), "flags": (12, 12), "field": (16, 16),
    "timestamp": (24, 20), "timecode": (40, 28), "sequence": (56, 44), "memory": (60, 48),
    "m": (64, 52), "length": (72, 56), "reserved2": (76, 60), "request_fd": (80, 64),
}  # fmt: skip
IOCTLS = {  # name: (LP64, ARM EABI)
    "VIDIOC_QUERYCAP": (0x80685600, 0x80685600), "VIDIOC_ENUM_FMT": (0xC0405602, 0xC0405602),
    "VIDIOC_G_FMT": (0xC0D05604, 0xC0CC5604), "VIDIOC_S_FMT": (0xC0D05605, 0xC0CC5605),
    "VIDIOC_REQBUFS": (0xC0145608, 0xC0145608), "VIDIOC_QUERYBUF": (0xC0585609, 0xC0445609),
    "VIDIOC_QBUF": (0xC058560F, 0xC044560F), "VIDIOC_DQBUF": (0xC0585611, 0xC0445611),
    "VIDIOC_STREAMON": (0x40045612, 0x40045612), "VIDIOC_STREAMOFF": (0x40045613, 0x40045613),
    "VIDIOC_G_PARM": (0xC0CC5615, 0xC0CC5615), "VIDIOC_S_PARM": (0xC0CC5616, 0xC0CC5616),
    "VIDIOC_G_CTRL": (0xC008561B, 0xC008561B), "VIDIOC_S_CTRL": (0xC008561C, 0xC008561C),
    "VIDIOC_QUERYCTRL": (0xC0445624, 0xC0445624), "VIDIOC_G_EXT_CTRLS": (0xC0205647, 0xC0185647),
    "VIDIOC_S_EXT_CTRLS": (0xC0205648, 0xC0185648), "VIDIOC_ENUM_FRAMESIZES": (0xC02C564A, 0xC02C564A),
    "VIDIOC_ENUM_FRAMEINTERVALS": (0xC034564B, 0xC034564B),
}  # fmt: skip


def _struct(abi: V4L2Abi, name: str) -> type[ctypes.Structure]:
    per_abi = {"v4l2_buffer": abi.buffer, "v4l2_format": abi.format, "v4l2_ext_controls": abi.ext_controls}
    return per_abi.get(name) or getattr(S, name)


@pytest.mark.parametrize(("abi", "col"), [(ABI64, 0), (ABI32, 1)], ids=["lp64", "arm32"])
def test_sizes_match_videodev2(abi: V4L2Abi, col: int) -> None:
    got = {name: ctypes.sizeof(_struct(abi, name)) for name in KERNEL_SIZES}
    assert got == {name: sizes[col] for name, sizes in KERNEL_SIZES.items()}


@pytest.mark.parametrize(("abi", "col"), [(ABI64, 0), (ABI32, 1)], ids=["lp64", "arm32"])
def test_buffer_offsets_match_videodev2(abi: V4L2Abi, col: int) -> None:
    got = {name: getattr(abi.buffer, name).offset for name in BUFFER_OFFSETS}
    assert got == {name: off[col] for name, off in BUFFER_OFFSETS.items()}
    assert abi.format.fmt.offset == (8 if abi.bits == 64 else 4)  # the union is 8-aligned on LP64
    assert abi.ext_controls.controls.offset == (24 if abi.bits == 64 else 20)


@pytest.mark.parametrize(("abi", "col"), [(ABI64, 0), (ABI32, 1)], ids=["lp64", "arm32"])
def test_ioctl_numbers(abi: V4L2Abi, col: int) -> None:
    assert {k: abi.ioctls[k] for k in IOCTLS} == {k: v[col] for k, v in IOCTLS.items()}
    assert abi.ioctls["VIDIOC_DQBUF"] == abi.VIDIOC_DQBUF
    assert abi.request_name(abi.VIDIOC_S_FMT) == "VIDIOC_S_FMT"


def test_fixed_offsets_shared_by_both_abis() -> None:
    assert S.v4l2_queryctrl.minimum.offset == 40
    assert S.v4l2_queryctrl.flags.offset == 56
    assert S.v4l2_capability.capabilities.offset == 84
    assert S.v4l2_capability.device_caps.offset == 88
    assert S.v4l2_fmtdesc.pixelformat.offset == 44
    assert S.v4l2_frmsizeenum.discrete.offset == 12
    assert S.v4l2_frmivalenum.discrete.offset == 20
    assert S.v4l2_ext_control.value.offset == 12


def test_ioc_encoding_and_fourcc() -> None:
    assert ioc(3, "V", 17, 88) == 0xC0585611
    with pytest.raises(ValueError, match="14 bits"):
        ioc(3, "V", 1, 1 << 14)
    assert fourcc("YUYV") == 0x56595559
    assert fourcc_str(0x56595559) == "YUYV"
    assert S.V4L2_PIX_FMT_MJPEG == 0x47504A4D
    assert S.V4L2_CID_EXPOSURE_AUTO == 0x009A0901
    assert S.V4L2_CID_EXPOSURE_ABSOLUTE == 0x009A0902
    assert S.V4L2_CID_EXPOSURE_AUTO_PRIORITY == 0x009A0903
    assert S.V4L2_CID_GAIN == 0x00980913
    with pytest.raises(ValueError, match="4 characters"):
        fourcc("YUY")


def test_struct_bytes_roundtrip_little_endian() -> None:
    b = ABI32.buffer(index=3, type=1, memory=1, sequence=0x01020304)
    raw = bytes(b)
    assert len(raw) == 68
    assert raw[0:4] == b"\x03\0\0\0"
    assert raw[44:48] == b"\x04\x03\x02\x01"
    b64 = ABI64.buffer(index=3, sequence=7)
    assert bytes(b64)[56:60] == b"\x07\0\0\0"


# ---- compile-time check against the real header ----------------------------------------------
_C_FIELDS = {
    "v4l2_buffer": list(BUFFER_OFFSETS),
    "v4l2_format": ["type", "fmt"],
    "v4l2_ext_controls": ["which", "count", "error_idx", "request_fd", "controls"],
    "v4l2_queryctrl": ["id", "type", "name", "minimum", "maximum", "step", "default_value", "flags"],
    "v4l2_capability": ["driver", "card", "bus_info", "version", "capabilities", "device_caps"],
    "v4l2_requestbuffers": ["count", "type", "memory", "capabilities", "flags"],
}


def _c_source(abi: V4L2Abi) -> str:
    lines = ["#include <stddef.h>", "#include <linux/videodev2.h>"]
    for name in KERNEL_SIZES:
        size = ctypes.sizeof(_struct(abi, name))
        lines.append(f'_Static_assert(sizeof(struct {name}) == {size}, "sizeof {name}");')
    for name, fields in _C_FIELDS.items():
        cls = _struct(abi, name)
        for f in fields:
            lines.append(f'_Static_assert(offsetof(struct {name}, {f}) == {getattr(cls, f).offset}, "{name}.{f}");')
    for k in IOCTLS:
        lines.append(f'_Static_assert((unsigned long){k} == {abi.ioctls[k]}UL, "{k}");')
    return "\n".join(lines) + "\n"


def _compile(tmp_path: Path, abi: V4L2Abi, flags: list[str]) -> subprocess.CompletedProcess[str]:
    cc = shutil.which("gcc") or shutil.which("cc")
    if cc is None or not Path("/usr/include/linux/videodev2.h").exists():
        pytest.skip("no C compiler or kernel headers (linux-libc-dev)")
    src = tmp_path / "layout.c"
    src.write_text(_c_source(abi))
    return subprocess.run([cc, *flags, "-fsyntax-only", str(src)], capture_output=True, text=True, check=False)


def test_layout_compiles_against_host_videodev2(tmp_path: Path) -> None:
    abi = ABI64 if ctypes.sizeof(ctypes.c_void_p) == 8 else ABI32
    r = _compile(tmp_path, abi, [])
    assert r.returncode == 0, r.stderr


def test_layout_compiles_against_32bit_videodev2(tmp_path: Path) -> None:
    probe = _compile(tmp_path, ABI32, ["-m32", "-include", "stddef.h"])
    if "No such file" in probe.stderr or "unrecognized" in probe.stderr:
        pytest.skip("no 32-bit C headers (gcc-multilib); the hand-written ARM table above still ran")
    assert probe.returncode == 0, probe.stderr
