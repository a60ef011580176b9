"""Source lighting per direction cluster: L_k = integral of radiance over cluster k (unit x sr).

The map is integrated over the 2^15 leaf cells once (each equirect pixel split into 2 x 2
sub-pixels, each sub-pixel's exact solid-angle share assigned to the leaf containing its centre),
then cumulative sums in tree order make any node's integral ``P[end] - P[start]`` (O(1)).
Energy is conserved: ``sum_leaves L = equirect_integral(map)``.
Dtype policy: float32 maps in, float64 leaf integrals and prefix sums out.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np
import scipy.sparse as sp

from device.sampling.base import LightSet
from device.sphere import directions_from_angles
from hostlink.relight.directions import NDIR, direction_to_leaf

__all__ = ["leaf_light_from_equirect", "leaf_light_from_lightset", "moment_prefix_sums", "prefix_sums"]

_SUB = 2


@lru_cache(maxsize=4)
def _equirect_matrix(height: int, width: int) -> sp.csr_matrix:
    """Sparse (2^15, H*W) matrix: pixel radiance -> leaf integral."""
    r = (np.arange(height * _SUB) + 0.5) / (height * _SUB)
    c = (np.arange(width * _SUB) + 0.5) / (width * _SUB)
    theta = np.pi * r
    phi = 2 * np.pi * c
    cos_edges = np.cos(np.pi * np.arange(height * _SUB + 1) / (height * _SUB))
    sub_dw = (2 * np.pi / (width * _SUB)) * (cos_edges[:-1] - cos_edges[1:])   # exact per sub-row
    tt, pp = np.meshgrid(theta, phi, indexing="ij")
    leaf = direction_to_leaf(directions_from_angles(tt, pp)).ravel()
    pix = ((np.arange(height * _SUB) // _SUB)[:, None] * width + (np.arange(width * _SUB) // _SUB)[None, :]).ravel()
    w = np.broadcast_to(sub_dw[:, None], tt.shape).ravel()
    m = sp.csr_matrix((w, (leaf, pix)), shape=(NDIR, height * width))
    m.sum_duplicates()
    return m


def leaf_light_from_equirect(img: np.ndarray) -> np.ndarray:
    """(2^15, 3) float64 radiance x solid angle per leaf cell of an equirect (H, 2H, 3) map.

    NaN / inf / negative pixels (e.g. lossy EXR) are treated as 0.
    """
    img = np.asarray(img)
    if img.ndim != 3 or img.shape[2] < 3 or img.shape[1] != 2 * img.shape[0]:
        raise ValueError(f"expected an equirect map (H, 2H, 3), got {img.shape}")
    h, w = img.shape[:2]
    x = np.nan_to_num(img[..., :3].astype(np.float64), nan=0.0, posinf=0.0, neginf=0.0)
    x = np.maximum(x, 0.0).reshape(-1, 3)
    return np.asarray(_equirect_matrix(h, w) @ x)


def leaf_light_from_lightset(ls: LightSet) -> np.ndarray:
    """Bin each light's rgb (radiance x solid angle) into the leaf holding its direction."""
    out = np.zeros((NDIR, 3))
    if len(ls) == 0:
        return out
    leaf = direction_to_leaf(np.asarray(ls.directions, np.float64))
    rgb = np.nan_to_num(np.asarray(ls.rgb, np.float64))
    for ch in range(3):
        out[:, ch] = np.bincount(leaf, weights=rgb[:, ch], minlength=NDIR)
    return out


def prefix_sums(leaf_light: np.ndarray) -> np.ndarray:
    """(2^15 + 1, 3) float64 cumulative sums in tree order: node integral = P[end] - P[start]."""
    p = np.zeros((NDIR + 1, 3))
    np.cumsum(np.asarray(leaf_light, np.float64), axis=0, out=p[1:])
    return p


def moment_prefix_sums(leaf_light: np.ndarray) -> np.ndarray:
    """(2^15 + 1, 9) float64 cumulative sums of L_c w_a (column 3 c + a; channel c, direction
    component a): a node's first light moment in O(1), for the cosine-moment correction."""
    from hostlink.relight.directions import leaf_directions

    q = np.zeros((NDIR + 1, 9))
    prod = np.asarray(leaf_light, np.float64)[:, :, None] * leaf_directions()[:, None, :]
    np.cumsum(prod.reshape(NDIR, 9), axis=0, out=q[1:])
    return q
