"""Compact binary encoding of a Q2-Tree's leaves (``GET /api/v1/q2tree``).

A Q2-Tree (Wan et al. 2005) partitions the sphere into HEALPix NESTED quads; its leaves are
enough to rebuild the whole tree (every interior node is the sum of its children, Nikodym et al.
2013, Algorithm 2 step 1). A leaf at level k (nside 2^k) with NESTED index i has the NUNIQ id
``u = 4 4^k + i`` (:func:`nodes_to_uniq`). This module is the wire format and the node
arithmetic both sides share (ids, levels, the fixed jittered point of a leaf's light).

Format, version 1 (all integers little-endian)::

    offset size  field
    0      4     magic  b"LPQ2"
    4      1     version = 1
    5      1     flags: bit 0 = rgb stored as float16 (else float32); other bits 0
    6      1     max_level L (the tree's finest level; nside_max = 2^L), L <= 29
    7      1     reserved = 0
    8      4     count n (number of leaves, uint32)
    12     ...   n leaf ids, sorted ascending, delta-coded (first delta from 0), each an
                 unsigned LEB128 varint
    ...    n*3*s rgb of each leaf (integral of radiance x solid angle, unit x sr), in id order,
                 float32 (s = 4) or float16 (s = 2)
    end-4  4     CRC-32 (zlib) of every byte before it

A decoded encoding is checked, not trusted: the CRC, the exact length, strictly increasing ids
at levels <= L, leaves that tile the sphere exactly (no gap, no overlap: the sum of
``4^(L - level)`` is ``12 4^L`` and no leaf contains another) and finite non-negative rgb.
Anything else raises :class:`Q2DecodeError`, so a damaged encoding can never decode into a
different tree. At 256 lights a float32 encoding takes about 3.6 KB.

Dtype policy: ids int64, rgb float64 in memory (float32/float16 on the wire).
"""

from __future__ import annotations

import struct
import zlib
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from lightprobe.core.errors import LightprobeError

__all__ = [
    "MAGIC",
    "Q2DecodeError",
    "Q2Tree",
    "decode_q2tree",
    "encode_q2tree",
    "jitter_directions",
    "node_points",
    "nodes_to_uniq",
    "uniq_levels",
    "uniq_to_nodes",
]

MAGIC = b"LPQ2"
VERSION = 1
MAX_LEVEL = 29  # uniq ids of level 29 still fit in int64
_HEADER = struct.Struct("<4sBBBBI")
_FLAG_HALF = 0x01


class Q2DecodeError(LightprobeError, ValueError):
    """A Q2-Tree encoding is corrupt, truncated or not a Q2-Tree encoding."""


def nodes_to_uniq(level: np.ndarray, index: np.ndarray) -> np.ndarray:
    """NUNIQ ids ``4 4^level + index`` (int64)."""
    level = np.asarray(level, np.int64)
    return (np.int64(4) << (2 * level)) + np.asarray(index, np.int64)


def uniq_to_nodes(uniq: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(level, NESTED index at nside 2^level) of NUNIQ ids (exact: the float log2 is guarded
    at the powers of four)."""
    u = np.asarray(uniq, np.int64)
    if np.any(u < 4):
        raise ValueError("NUNIQ ids start at 4")
    level = (np.floor(np.log2(u.astype(np.float64))).astype(np.int64) // 2) - 1
    level = np.where(u >= (np.int64(4) << (2 * (level + 1))), level + 1, level)
    level = np.where(u < (np.int64(4) << (2 * level)), level - 1, level)
    return level, u - (np.int64(4) << (2 * level))


def uniq_levels(uniq: np.ndarray) -> np.ndarray:
    """Level of each NUNIQ id."""
    return uniq_to_nodes(uniq)[0]


def _hash_unit(uniq: np.ndarray, seed: int, stream: int) -> np.ndarray:
    """splitmix64 of (uniq, seed, stream) -> uniform floats in [0, 1) (deterministic)."""
    with np.errstate(over="ignore"):
        x = (uniq.astype(np.uint64) * np.uint64(0x9E3779B97F4A7C15)
             + np.uint64((seed * 2654435761 + stream * 40503) & 0xFFFFFFFFFFFFFFFF))
        x = (x ^ (x >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
        x = (x ^ (x >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
        x = x ^ (x >> np.uint64(31))
    return (x >> np.uint64(11)).astype(np.float64) * (1.0 / (1 << 53))


def node_points(uniq: np.ndarray, fx: np.ndarray, fy: np.ndarray) -> np.ndarray:
    """Directions of the points (fx, fy) in [0, 1]^2 of each node's own square."""
    from .healpix import face_xy_to_directions, nest_to_xyf

    level, index = uniq_to_nodes(uniq)
    out = np.empty((len(uniq), 3), np.float64)
    for k in np.unique(level):
        sel = level == k
        ns = 1 << int(k)
        ix, iy, face = nest_to_xyf(ns, index[sel])
        out[sel] = face_xy_to_directions(face, (ix + fx[sel]) / ns, (iy + fy[sel]) / ns)
    return out


def jitter_directions(uniq: np.ndarray, seed: int, extent: float) -> np.ndarray:
    """A fixed point per node: its centre jittered by ``extent`` of its size, hashed from
    (level, index, seed), so a light stays put while its leaf survives (Wan et al. 2005). The
    probe and a host merging trees place a leaf's light at the same point."""
    uniq = np.asarray(uniq, np.int64)
    fx = 0.5 + extent * (_hash_unit(uniq, seed, 1) - 0.5)
    fy = 0.5 + extent * (_hash_unit(uniq, seed, 2) - 0.5)
    return node_points(uniq, fx, fy)


@dataclass
class Q2Tree:
    """The leaves of one Q2-Tree: NUNIQ ``uniq`` (n,) int64 sorted, ``rgb`` (n, 3) float64
    (integral of radiance x solid angle per leaf), the finest level ``max_level`` and optional
    metadata (probe id, frame, unit, pose) carried beside the encoding, not inside it."""

    uniq: np.ndarray
    rgb: np.ndarray
    max_level: int
    meta: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        u = np.asarray(self.uniq, np.int64).reshape(-1)
        rgb = np.asarray(self.rgb, np.float64).reshape(-1, 3)
        if len(u) != len(rgb):
            raise ValueError("uniq and rgb must have the same length")
        order = np.argsort(u, kind="stable")
        self.uniq, self.rgb = u[order], rgb[order]
        self.max_level = int(self.max_level)

    @classmethod
    def from_nodes(cls, level: np.ndarray, index: np.ndarray, rgb: np.ndarray,
                   max_level: int | None = None, meta: dict[str, Any] | None = None) -> Q2Tree:
        """From (level, NESTED index) leaf arrays, e.g. ``Q2TreeSampler.to_nodes()``."""
        level = np.asarray(level, np.int64)
        top = int(level.max()) if max_level is None and level.size else int(max_level or 0)
        return cls(nodes_to_uniq(level, index), rgb, top, dict(meta or {}))

    @property
    def level(self) -> np.ndarray:
        return uniq_levels(self.uniq)

    @property
    def index(self) -> np.ndarray:
        return self.uniq - (np.int64(4) << (2 * self.level))

    @property
    def total(self) -> np.ndarray:
        """Sum of the leaves' rgb (the map's integral), float64."""
        return self.rgb.sum(axis=0)

    def __len__(self) -> int:
        return len(self.uniq)

    def same_tree(self, other: Q2Tree) -> bool:
        """Same leaves, same finest level, bit-identical rgb."""
        return (self.max_level == other.max_level and np.array_equal(self.uniq, other.uniq)
                and np.array_equal(self.rgb, other.rgb))


# ---- varints ------------------------------------------------------------------------------------
def _encode_varints(values: np.ndarray) -> bytes:
    out = bytearray()
    for v in values.tolist():
        while v >= 0x80:
            out.append((v & 0x7F) | 0x80)
            v >>= 7
        out.append(v)
    return bytes(out)


def _decode_varints(buf: bytes, start: int, n: int, end: int) -> tuple[np.ndarray, int]:
    vals = np.empty(n, np.int64)
    pos = start
    for j in range(n):
        v = shift = 0
        while True:
            if pos >= end:
                raise Q2DecodeError("truncated leaf ids")
            b = buf[pos]
            pos += 1
            v |= (b & 0x7F) << shift
            if not b & 0x80:
                break
            shift += 7
            if shift > 63:
                raise Q2DecodeError("leaf id varint too long")
        if v >= 1 << 62:
            raise Q2DecodeError("leaf id out of range")
        vals[j] = v
    return vals, pos


# ---- checks -------------------------------------------------------------------------------------
def check_partition(uniq: np.ndarray, max_level: int) -> None:
    """Raise :class:`Q2DecodeError` unless the sorted ids ``uniq`` are leaves that tile the
    sphere exactly at levels 0..max_level."""
    if len(uniq) == 0:
        raise Q2DecodeError("a Q2-Tree has at least one leaf per base quad (12)")
    if np.any(uniq < 4) or np.any(np.diff(uniq) <= 0):
        raise Q2DecodeError("leaf ids must be >= 4 and strictly increasing")
    if int(uniq[-1]) >= (4 << (2 * (max_level + 1))):
        raise Q2DecodeError(f"leaf id {int(uniq[-1])} is deeper than max_level {max_level}")
    level = uniq_levels(uniq)
    index = uniq - (np.int64(4) << (2 * level))
    shift = 2 * (max_level - level)
    start = index << shift  # first descendant at max_level
    stop = (index + 1) << shift
    order = np.argsort(start, kind="stable")
    start, stop = start[order], stop[order]
    # Tiling: contiguous ranges [start, stop) from 0 to 12 4^L without gap or overlap
    if start[0] != 0 or stop[-1] != 12 << (2 * max_level) or np.any(start[1:] != stop[:-1]):
        raise Q2DecodeError("leaves do not tile the sphere (gap or overlap)")


# ---- encode / decode ----------------------------------------------------------------------------
def encode_q2tree(tree: Q2Tree, *, half: bool = False) -> bytes:
    """The version-1 encoding of ``tree`` (see the module docstring).

    ``half`` stores rgb as float16 (about 40% smaller; 3 significant digits, values up to
    65504): it raises ``ValueError`` when a value would overflow.
    """
    uniq = tree.uniq
    if not 0 <= tree.max_level <= MAX_LEVEL:
        raise ValueError(f"max_level must be in [0, {MAX_LEVEL}], got {tree.max_level}")
    check_partition(uniq, tree.max_level)
    rgb = np.asarray(tree.rgb, np.float64)
    if not np.all(np.isfinite(rgb)) or np.any(rgb < 0):
        raise ValueError("leaf rgb must be finite and non-negative")
    if half:
        if np.any(rgb > np.finfo(np.float16).max):
            raise ValueError("leaf rgb exceeds the float16 range: encode with half=False")
        payload = rgb.astype("<f2").tobytes()
    else:
        payload = rgb.astype("<f4").tobytes()
    head = _HEADER.pack(MAGIC, VERSION, _FLAG_HALF if half else 0, tree.max_level, 0, len(uniq))
    deltas = np.diff(uniq, prepend=np.int64(0))
    body = head + _encode_varints(deltas) + payload
    return body + struct.pack("<I", zlib.crc32(body))


def decode_q2tree(data: bytes, meta: dict[str, Any] | None = None) -> Q2Tree:
    """Parse and check an encoding; raises :class:`Q2DecodeError` on any damage."""
    buf = bytes(data)
    if len(buf) < _HEADER.size + 4:
        raise Q2DecodeError(f"encoding too short ({len(buf)} bytes)")
    magic, version, flags, max_level, reserved, n = _HEADER.unpack_from(buf, 0)
    if magic != MAGIC:
        raise Q2DecodeError("not a Q2-Tree encoding (bad magic)")
    if zlib.crc32(buf[:-4]) != struct.unpack_from("<I", buf, len(buf) - 4)[0]:
        raise Q2DecodeError("CRC mismatch: the encoding is corrupt or truncated")
    if version != VERSION:
        raise Q2DecodeError(f"unsupported Q2-Tree encoding version {version}")
    if flags & ~_FLAG_HALF or reserved != 0 or max_level > MAX_LEVEL:
        raise Q2DecodeError("bad header (flags, reserved byte or max_level)")
    itemsize = 2 if flags & _FLAG_HALF else 4
    end = len(buf) - 4
    if n < 12 or n > 12 << (2 * max_level) or n > (end - _HEADER.size) // (1 + 3 * itemsize):
        raise Q2DecodeError(f"leaf count {n} does not fit the encoding")
    deltas, pos = _decode_varints(buf, _HEADER.size, n, end)
    if pos + n * 3 * itemsize != end:
        raise Q2DecodeError("encoding length does not match its leaf count")
    uniq = np.cumsum(deltas)
    check_partition(uniq, max_level)
    rgb = np.frombuffer(buf, "<f2" if itemsize == 2 else "<f4", 3 * n, pos).astype(np.float64)
    rgb = rgb.reshape(n, 3)
    if not np.all(np.isfinite(rgb)) or np.any(rgb < 0):
        raise Q2DecodeError("leaf rgb must be finite and non-negative")
    return Q2Tree(uniq, rgb, int(max_level), dict(meta or {}))
