"""On-disk cache of projection tables, so a probe restarts in a fraction of a second.

Building the tables costs seconds (longer on an ARM board); they depend only on the calibration
(its content id) and the grid parameters, so the service keeps them in its state directory.
A cache file is written atomically (temp file + rename); a file that cannot be read, or was
written by another format version, is ignored and rebuilt.

A loaded file is memory-mapped, not read: ``np.savez`` stores its members uncompressed, so each
array is a view of the mapped file (copy-on-write; the tables' arrays read-only as before). On a
small board that makes the tables clean file pages: only the pages a frame touches are resident
(the per-frame kernels read the upper hemisphere's rows; the transpose, the per-pixel solid
angles and the lower rows stay on disk until something asks for them), and the kernel may drop
them under memory pressure instead of swapping.
"""

from __future__ import annotations

import hashlib
import logging
import mmap
import os
import struct
import tempfile
import zipfile
from dataclasses import fields
from pathlib import Path
from typing import Any

import numpy as np

from .tables import _Built, _Table

__all__ = ["cache_path", "load_built", "save_built"]

log = logging.getLogger(__name__)
_FORMAT = 1
_TABLE_FIELDS = [f.name for f in fields(_Table)]


def cache_path(cache_dir: str | os.PathLike[str], key: tuple[object, ...]) -> Path:
    digest = hashlib.sha256(repr((_FORMAT, *key)).encode()).hexdigest()[:20]
    return Path(cache_dir) / f"projection-{digest}.npz"


def save_built(path: Path, built: _Built) -> None:
    arrays: dict[str, np.ndarray] = {
        "format": np.array(_FORMAT), "lens_mask": built.lens_mask, "pixel_gain": built.pixel_gain,
        "inv_gain": built.inv_gain, "pixel_solid_angle": built.pixel_solid_angle,
        "tables": np.array(sorted(built.tables)),
    }
    for name, t in built.tables.items():
        for f in _TABLE_FIELDS:
            arrays[f"{name}.{f}"] = np.asarray(getattr(t, f))
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as fh:
            np.savez(fh, **arrays)  # type: ignore[arg-type]
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def _mapped_members(path: Path) -> dict[str, np.ndarray]:
    """The arrays of an uncompressed ``.npz`` as views of one copy-on-write mapping of it."""
    with path.open("rb") as fh:
        with zipfile.ZipFile(fh) as zf:
            infos = zf.infolist()
        mm = mmap.mmap(fh.fileno(), 0, access=mmap.ACCESS_COPY)
    out: dict[str, np.ndarray] = {}
    for info in infos:
        if info.compress_type != zipfile.ZIP_STORED or not info.filename.endswith(".npy"):
            raise ValueError(f"member {info.filename} is not a stored .npy")
        if mm[info.header_offset:info.header_offset + 4] != b"PK\x03\x04":
            raise ValueError(f"member {info.filename}: no local header")
        name_len, extra_len = struct.unpack_from("<HH", mm, info.header_offset + 26)
        start = info.header_offset + 30 + name_len + extra_len
        member = _MemberReader(mm, start)
        version = np.lib.format.read_magic(member)  # type: ignore[arg-type]
        read_header = np.lib.format.read_array_header_1_0 if version == (1, 0) else np.lib.format.read_array_header_2_0
        shape, fortran, dtype = read_header(member)  # type: ignore[arg-type]
        if dtype.hasobject:
            raise ValueError(f"member {info.filename} holds objects")
        count = int(np.prod(shape))
        a = np.frombuffer(mm, dtype, count, member.pos) if count else np.zeros(0, dtype)
        out[info.filename[:-4]] = a.reshape(shape, order="F" if fortran else "C")
    return out


class _MemberReader:
    """A file-like reader over a mapping from ``pos`` on (what np.lib.format reads headers from)."""

    def __init__(self, mm: mmap.mmap, pos: int) -> None:
        self.mm, self.pos = mm, pos

    def read(self, n: int) -> bytes:
        b = self.mm[self.pos:self.pos + n]
        self.pos += len(b)
        return b


def load_built(path: Path) -> _Built | None:
    if not path.is_file():
        return None
    try:
        z = _mapped_members(path)
        if int(z["format"]) != _FORMAT:
            return None
        tables = {}
        for name in z["tables"].tolist():
            kw: dict[str, Any] = {f: z[f"{name}.{f}"] for f in _TABLE_FIELDS}
            kw["ipf_residual"] = float(kw["ipf_residual"])
            tables[name] = _Table(**kw)
        built = _Built(z["lens_mask"], z["pixel_gain"], z["inv_gain"], z["pixel_solid_angle"], tables)
    except (OSError, ValueError, KeyError, TypeError, zipfile.BadZipFile, struct.error) as e:
        log.warning("projection cache %s unreadable (%s): rebuilding", path, e)
        return None
    for t in built.tables.values():
        for f in _TABLE_FIELDS:
            a = getattr(t, f)
            if isinstance(a, np.ndarray):
                a.flags.writeable = False
    return built
