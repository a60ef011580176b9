"""Node arithmetic of the Q2-Tree: NUNIQ ids, the power pyramid and light placement.

A node at level k (nside 2^k, solid angle 4 pi / (12 4^k)) with NESTED index i has the id
``u = 4 4^k + i`` (HEALPix NUNIQ). The pyramid is a dense array indexed by u holding a node's
integral of radiance x solid angle: a mip-map of sums, built bottom-up by adding the four
children (NESTED children are 4i..4i+3) above the per-frame coarse level, and summed from the
node's own pixels below it (``._binning``). It gives any quad's power in O(1) like a prefix sum
over the finest map, but without the cancellation a prefix difference suffers next to a 1e9 hot
pixel (dim quads keep full relative precision).

Dtype policy: sums, moments and directions float64; ids int64.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from lightprobe.core.q2wire import jitter_directions

from ._binning import FrameState, equirect_tables, healpix_tables

__all__ = [
    "Pyramid",
    "centroid_directions",
    "level_solid_angles",
    "pyramid_from_equirect",
    "pyramid_from_healpix",
    "reduce_healpix",
    "state_pyramid",
]


@functools.lru_cache(maxsize=32)
def _level_solid_angles(max_level: int) -> np.ndarray:
    dw = 4.0 * np.pi / (12.0 * 4.0 ** np.arange(max_level + 1))
    dw.setflags(write=False)
    return dw


def level_solid_angles(max_level: int) -> np.ndarray:
    """Solid angle of a node at each level 0..max_level: 4 pi / (12 4^k) (Nikodym et al. eq. 1).
    (Read-only, cached.)"""
    return _level_solid_angles(int(max_level))


@dataclass
class Pyramid:
    """Per-node sums of one frame: ``rgb`` (M, 3) and luminance ``lum`` (M,) of radiance x
    solid angle, and, for centroid placement, ``moment`` (M, 3) = sum of lum x direction.
    Inside the sampler only the levels up to the per-frame coarse level and the nodes the tree
    reached are current (see ``._binning``); the ``pyramid_from_*`` functions fill every node."""

    nside: int
    max_level: int
    rgb: np.ndarray
    lum: np.ndarray
    moment: np.ndarray | None


def state_pyramid(state: FrameState) -> Pyramid:
    """The pyramid view of a :class:`._binning.FrameState`'s arrays."""
    k = state.tables.max_level
    return Pyramid(1 << k, k, state.rgb, state.lum, state.moment if state.moments else None)


def reduce_healpix(hp_rgb: np.ndarray, nside: int, target: int) -> np.ndarray:
    """Mean of the (nside / target)^2 NESTED descendants of each pixel at ``target`` (float64):
    the same map at a coarser nside, with its integral unchanged."""
    if target >= nside:
        return np.asarray(hp_rgb, np.float64)
    group = (nside // target) ** 2
    return np.asarray(hp_rgb, np.float64).reshape(-1, group, 3).mean(axis=1)


def pyramid_from_healpix(hp_rgb: np.ndarray, nside: int, moments: bool,
                         reuse: Pyramid | None = None) -> Pyramid:
    """Dense pyramid (every node of every level) of a NESTED radiance map ``hp_rgb``
    (12 nside^2, 3); NaN/inf/negative read as 0. Each pixel contributes radiance x
    4 pi / (12 nside^2) at its centre direction. ``reuse`` is accepted for compatibility."""
    k = int(np.log2(nside))
    state = FrameState(healpix_tables(k, k), moments)
    flat = np.ascontiguousarray(hp_rgb)
    state.load(flat if flat.dtype in (np.float32, np.float64) else flat.astype(np.float64))
    return state_pyramid(state)


def pyramid_from_equirect(clean: np.ndarray, nside: int, moments: bool,
                          reuse: Pyramid | None = None) -> Pyramid:
    """Dense pyramid of an (H, 2H, 3) equirect map, each whole pixel binned into the HEALPix
    pixel at ``nside`` that holds its centre (NaN/inf/negative read as 0).

    Every quad's power is then an exact float64 sum of equirect pixels (radiance x their exact
    solid angle, CONVENTIONS.md), and centroids use the pixels' own centre directions, so the
    lights carry no resampling error. (A quad finer than the equirect pixels may receive no
    pixel: it simply holds no power.) ``reuse`` is accepted for compatibility.
    """
    k = int(np.log2(nside))
    state = FrameState(equirect_tables(clean.shape[0], k, k), moments)
    state.load(np.ascontiguousarray(clean, np.float32).reshape(-1, 3))
    return state_pyramid(state)


def centroid_directions(pyr: Pyramid, uniq: np.ndarray, seed: int, extent: float) -> np.ndarray:
    """Luminance-weighted centroid direction of each node (the normalised first moment);
    the node's jitter point where it has no power."""
    assert pyr.moment is not None
    m = pyr.moment[uniq]
    norm = np.linalg.norm(m, axis=1)
    good = norm > 0
    out = np.empty_like(m)
    out[good] = m[good] / norm[good, None]
    if not good.all():
        out[~good] = jitter_directions(uniq[~good], seed, extent)
    return out
