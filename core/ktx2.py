"""KTX 2.0 cube maps, uncompressed RGBA16F (Khronos KTX File Format Specification 2.0).

Written: ``vkFormat = VK_FORMAT_R16G16B16A16_SFLOAT`` (97), ``typeSize = 2``, ``faceCount = 6``
(faces +X, -X, +Y, -Y, +Z, -Z), ``levelCount`` mips, no supercompression; a Basic Data Format
Descriptor (RGBSDA, BT.709 primaries, linear transfer, four signed-float 16-bit samples R, G, B,
A) and key/value data ``KTXwriter`` plus ``lightprobe.roughness`` (the mips' GGX roughness,
comma separated) and ``lightprobe.unit``. Mip data are laid out smallest first, as the
specification requires, each level 8-byte aligned; within a level the faces follow each other,
rows top to bottom. Alpha is 1.

:func:`read_ktx2_cubemap` reads back what :func:`ktx2_cubemap_bytes` writes (and checks the
header), for tests and host code; it is not a general KTX2 reader.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from typing import Any

import numpy as np

from lightprobe.core.errors import InputError

__all__ = ["IDENTIFIER", "VK_FORMAT_R16G16B16A16_SFLOAT", "CubeMap", "ktx2_cubemap_bytes", "read_ktx2_cubemap"]

IDENTIFIER = b"\xabKTX 20\xbb\r\n\x1a\n"
VK_FORMAT_R16G16B16A16_SFLOAT = 97
_KHR_DF_MODEL_RGBSDA = 1
_KHR_DF_PRIMARIES_BT709 = 1
_KHR_DF_TRANSFER_LINEAR = 1
_KHR_DF_SAMPLE_DATATYPE_FLOAT = 0x80
_KHR_DF_SAMPLE_DATATYPE_SIGNED = 0x40
_CHANNELS = (0, 1, 2, 15)  # R, G, B, A channel ids of the RGBSDA model
_HEADER = struct.Struct("<12sIIIIIIIII")  # identifier, vkFormat, typeSize, w, h, d, layers, faces, levels, sc
_INDEX = struct.Struct("<IIIIQQ")


def _dfd() -> bytes:
    samples = b""
    for i, ch in enumerate(_CHANNELS):
        ctype = ch | _KHR_DF_SAMPLE_DATATYPE_FLOAT | _KHR_DF_SAMPLE_DATATYPE_SIGNED
        samples += struct.pack("<HBBBBBBff", 16 * i, 15, ctype, 0, 0, 0, 0, -1.0, 1.0)
    block_size = 24 + len(samples)
    block = struct.pack("<IHH", 0, 2, block_size)  # vendorId 0 / descriptorType 0, version 2, size
    block += bytes([_KHR_DF_MODEL_RGBSDA, _KHR_DF_PRIMARIES_BT709, _KHR_DF_TRANSFER_LINEAR, 0])
    block += bytes([0, 0, 0, 0])  # texel block dimensions (1x1x1x1, stored minus one)
    block += bytes([8, 0, 0, 0, 0, 0, 0, 0])  # bytesPlane0 = 8, planes 1..7 unused
    block += samples
    return struct.pack("<I", 4 + len(block)) + block


def _kvd(pairs: dict[str, str]) -> bytes:
    out = b""
    for k in sorted(pairs):
        kv = k.encode() + b"\0" + pairs[k].encode() + b"\0"
        out += struct.pack("<I", len(kv)) + kv
        out += b"\0" * (-len(out) % 4)
    return out


def ktx2_cubemap_bytes(mips: list[np.ndarray], metadata: dict[str, str] | None = None) -> bytes:
    """A KTX2 file of cube-map mips, each (6, n, n, 3) float (n halving from level 0)."""
    if not mips:
        raise InputError("a cube map needs at least one mip level", param="mips")
    n0 = int(np.asarray(mips[0]).shape[1])
    for m, a in enumerate(mips):
        a = np.asarray(a)
        want = (6, max(n0 >> m, 1), max(n0 >> m, 1), 3)
        if a.shape != want:
            raise InputError(f"mip {m} has shape {a.shape}, expected {want}", param="mips")
    levels = len(mips)
    dfd = _dfd()
    kv = {"KTXwriter": "lightprobe"}
    kv.update(metadata or {})
    kvd = _kvd(kv)
    index_end = _HEADER.size + _INDEX.size + 24 * levels
    dfd_off = index_end
    kvd_off = dfd_off + len(dfd)
    data_start = kvd_off + len(kvd)
    data_start += -data_start % 8
    blobs = []
    for a in mips:
        rgba = np.ones((*np.asarray(a).shape[:3], 4), np.float16)
        rgba[..., :3] = np.clip(np.nan_to_num(np.asarray(a, np.float32), nan=0.0, posinf=65504.0),
                                -65504.0, 65504.0)
        blobs.append(rgba.astype("<f2").tobytes())
    # smallest level first in the file
    offsets = [0] * levels
    body = b""
    for m in reversed(range(levels)):
        body += b"\0" * (-(data_start + len(body)) % 8)
        offsets[m] = data_start + len(body)
        body += blobs[m]
    header = _HEADER.pack(IDENTIFIER, VK_FORMAT_R16G16B16A16_SFLOAT, 2, n0, n0, 0, 0, 6, levels, 0)
    index = _INDEX.pack(dfd_off, len(dfd), kvd_off, len(kvd), 0, 0)
    level_index = b"".join(struct.pack("<QQQ", offsets[m], len(blobs[m]), len(blobs[m])) for m in range(levels))
    head = header + index + level_index + dfd + kvd
    head += b"\0" * (data_start - len(head))
    return head + body


def read_ktx2_cubemap(data: bytes) -> tuple[list[np.ndarray], dict[str, Any]]:
    """Mips (6, n, n, 4) float32 and the key/value pairs of a file written by
    :func:`ktx2_cubemap_bytes`; raises ``InputError`` on anything else."""
    if len(data) < _HEADER.size + _INDEX.size or data[:12] != IDENTIFIER:
        raise InputError("not a KTX 2.0 file", param="ktx2")
    _, vk, _ts, w, h, _d, _layers, faces, levels, sc = _HEADER.unpack_from(data, 0)
    if vk != VK_FORMAT_R16G16B16A16_SFLOAT or faces != 6 or sc != 0 or w != h:
        raise InputError(f"not an uncompressed RGBA16F cube map (vkFormat {vk}, faces {faces})", param="ktx2")
    dfd_off, dfd_len, kvd_off, kvd_len, _, _ = _INDEX.unpack_from(data, _HEADER.size)
    kv: dict[str, Any] = {}
    p = kvd_off
    while p < kvd_off + kvd_len:
        (n,) = struct.unpack_from("<I", data, p)
        k, v = data[p + 4: p + 4 + n].split(b"\0")[:2]
        kv[k.decode()] = v.decode()
        p += 4 + n
        p += -p % 4
    kv["dfd"] = data[dfd_off: dfd_off + dfd_len]
    mips = []
    for m in range(max(levels, 1)):
        off, length, _ = struct.unpack_from("<QQQ", data, _HEADER.size + _INDEX.size + 24 * m)
        n = max(w >> m, 1)
        a = np.frombuffer(data, "<f2", count=6 * n * n * 4, offset=off).reshape(6, n, n, 4)
        if length != a.nbytes:
            raise InputError(f"level {m}: {length} bytes, expected {a.nbytes}", param="ktx2")
        mips.append(a.astype(np.float32))
    return mips, kv


@dataclass
class CubeMap:
    """A decoded ``cubemap.ktx2``: ``mips[m]`` (6, n, n, 3) float32 (faces +X..-Z, probe frame),
    ``roughness[m]`` (GGX, perceptual), and the file's key/value data."""

    mips: list[np.ndarray]
    roughness: list[float]
    meta: dict[str, Any]
