"""On-disk cache of the simulated lens's render matrices (:meth:`lightprobe.sim.lens.SimLens.render_matrix`).

Building one costs about a second at VGA (point-sampled overlaps and 12 balancing sweeps); it
depends only on the lens parameters, the equirect height and the code that builds it, so the
file name hashes all three (the sources of :mod:`lightprobe.sim.lens` and :mod:`lightprobe.sim.optics` included: an edited lens model never
reads an old matrix). Files are written atomically (temp file + rename); an unreadable one is
rebuilt. Loading is exact: the cached CSR matrix is the one :meth:`render_matrix` returned.
"""

from __future__ import annotations

import hashlib
import logging
import os
import tempfile
from pathlib import Path

import numpy as np

from lightprobe.sim._sparse import Csr

from . import lens as _lens_module
from . import optics as _optics_module
from .lens import SimLens

__all__ = ["load_render_matrix"]

log = logging.getLogger(__name__)
_HOUSING = True  # render_matrix's default, the one SimCamera renders with


def _path(lens: SimLens, eq_height: int, cache_dir: str) -> Path:
    src = Path(_lens_module.__file__).read_bytes() + Path(_optics_module.__file__).read_bytes()
    fe = lens.fisheye
    key = repr((hashlib.sha256(src).hexdigest(), fe.image_size, np.asarray(fe.K).tolist(),
                np.asarray(fe.D).tolist(), fe.fov_deg, lens.vignetting, lens.circle_deg, lens.ring_deg,
                lens.ring_transmission, eq_height, lens.supersample_for(eq_height), _HOUSING))
    return Path(cache_dir) / f"simlens-{hashlib.sha256(key.encode()).hexdigest()[:20]}.npz"


def load_render_matrix(lens: SimLens, eq_height: int, cache_dir: str) -> None:
    """Make ``lens.render(eq)`` for an ``eq_height`` map cheap: load its matrix from
    ``cache_dir`` into the lens's in-memory cache, or build it and save it there."""
    key = (eq_height, lens.supersample_for(eq_height), _HOUSING)
    if key in lens._cache:
        return
    path = _path(lens, eq_height, cache_dir)
    if path.is_file():
        try:
            with np.load(path, allow_pickle=False) as z:
                m = Csr.checked(z["data"], z["indices"], z["indptr"], z["shape"])
        except (OSError, ValueError, KeyError) as e:
            log.warning("simulated lens cache %s unreadable (%s): rebuilding", path, e)
        else:
            lens._cache[key] = m
            return
    m = lens.render_matrix(eq_height)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", dir=path.parent)
        try:
            with os.fdopen(fd, "wb") as fh:
                np.savez(fh, data=m.data, indices=m.indices, indptr=m.indptr, shape=np.array(m.shape))
            os.replace(tmp, path)
        except BaseException:
            Path(tmp).unlink(missing_ok=True)
            raise
    except OSError as e:  # a read-only or full disk costs only the next start's time
        log.warning("cannot write simulated lens cache %s: %s", path, e)
