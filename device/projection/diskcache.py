"""On-disk cache of projection tables, so a probe restarts in a fraction of a second.

Building the tables costs seconds (longer on an ARM board); they depend only on the calibration
(its content id) and the grid parameters, so the service keeps them in its state directory.
A cache file is written atomically (temp file + rename); a file that cannot be read, or was
written by another format version, is ignored and rebuilt.
"""

from __future__ import annotations

import hashlib
import logging
import os
import tempfile
from dataclasses import fields
from pathlib import Path

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


def load_built(path: Path) -> _Built | None:
    if not path.is_file():
        return None
    try:
        with np.load(path, allow_pickle=False) as z:
            if int(z["format"]) != _FORMAT:
                return None
            tables = {}
            for name in z["tables"].tolist():
                kw = {f: z[f"{name}.{f}"] for f in _TABLE_FIELDS}
                kw["ipf_residual"] = float(kw["ipf_residual"])
                tables[name] = _Table(**kw)
            built = _Built(z["lens_mask"], z["pixel_gain"], z["inv_gain"], z["pixel_solid_angle"], tables)
    except (OSError, ValueError, KeyError, TypeError) as e:
        log.warning("projection cache %s unreadable (%s): rebuilding", path, e)
        return None
    for t in built.tables.values():
        for f in _TABLE_FIELDS:
            a = getattr(t, f)
            if isinstance(a, np.ndarray):
                a.flags.writeable = False
    return built
