"""Rasterising the scene from a camera: ID buffer with perspective-correct barycentrics (the
visible-vertex culling of Iwasaki et al. Sec. V-B), view rays, background lookup, tone mapping.
Dtype policy: float64 geometry, float32 barycentrics and rays, 8-bit output of :func:`tonemap`.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numba import njit, prange

from lightprobe.core.errors import InputError
from lightprobe.core.sphere import luminance
from lightprobe.hostlink.relight.scene import Camera

__all__ = ["Raster", "camera_basis", "lookup_equirect", "rasterize", "resolve", "tonemap", "view_rays",
           "visible_vertices"]


@dataclass
class Raster:
    tri: np.ndarray     # (H, W) int64 triangle id, -1 for background
    bary: np.ndarray    # (H, W, 3) float32 perspective-correct barycentrics
    rays: np.ndarray | None  # (H, W, 3) float32 view ray directions (world), if asked for


def camera_basis(cam: Camera) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    f = np.asarray(cam.look_at, float) - np.asarray(cam.position, float)
    f /= np.linalg.norm(f)
    r = np.cross(f, np.asarray(cam.up, float))
    if np.linalg.norm(r) < 1e-9:
        r = np.cross(f, np.array([0.0, 0.0, 1.0]))
    r /= np.linalg.norm(r)
    return r, np.cross(r, f), f


@njit(cache=True)
def raster_triangles(sx: np.ndarray, sy: np.ndarray, z: np.ndarray, faces: np.ndarray, W: int, H: int,
            tri: np.ndarray, bary: np.ndarray, depth: np.ndarray) -> None:
    for t in range(faces.shape[0]):
        a, b, c = faces[t, 0], faces[t, 1], faces[t, 2]
        if z[a] <= 1e-6 or z[b] <= 1e-6 or z[c] <= 1e-6:     # near clipping: drop triangle
            continue
        x0 = max(int(np.floor(min(sx[a], sx[b], sx[c]))), 0)
        x1 = min(int(np.ceil(max(sx[a], sx[b], sx[c]))), W - 1)
        y0 = max(int(np.floor(min(sy[a], sy[b], sy[c]))), 0)
        y1 = min(int(np.ceil(max(sy[a], sy[b], sy[c]))), H - 1)
        den = (sy[b] - sy[c]) * (sx[a] - sx[c]) + (sx[c] - sx[b]) * (sy[a] - sy[c])
        if abs(den) < 1e-12:
            continue
        for py in range(y0, y1 + 1):
            for px in range(x0, x1 + 1):
                l0 = ((sy[b] - sy[c]) * (px - sx[c]) + (sx[c] - sx[b]) * (py - sy[c])) / den
                l1 = ((sy[c] - sy[a]) * (px - sx[c]) + (sx[a] - sx[c]) * (py - sy[c])) / den
                l2 = 1 - l0 - l1
                if l0 < 0 or l1 < 0 or l2 < 0:
                    continue
                iz = l0 / z[a] + l1 / z[b] + l2 / z[c]          # perspective-correct 1/z
                if iz <= depth[py, px]:
                    continue
                depth[py, px] = iz
                tri[py, px] = t
                bary[py, px, 0] = l0 / z[a] / iz
                bary[py, px, 1] = l1 / z[b] / iz
                bary[py, px, 2] = l2 / z[c] / iz


def rasterize(cam: Camera, vertices: np.ndarray, faces: np.ndarray, rays: bool = True) -> Raster:
    """ID buffer with z-buffer (pixel centres, vertical field of view ``cam.fov_deg``); view
    rays only if ``rays``."""
    W, H = int(cam.width), int(cam.height)
    r, u, f = camera_basis(cam)
    rel = vertices - np.asarray(cam.position, float)
    xc, yc, zc = rel @ r, rel @ u, rel @ f
    th = np.tan(np.radians(cam.fov_deg) / 2)
    aspect = W / H
    zsafe = np.where(zc > 1e-6, zc, 1e-6)
    sx = (xc / (zsafe * th * aspect) + 1) / 2 * W - 0.5
    sy = (1 - yc / (zsafe * th)) / 2 * H - 0.5
    tri = np.full((H, W), -1, np.int64)
    bary = np.zeros((H, W, 3), np.float32)
    raster_triangles(sx, sy, zc, np.asarray(faces, np.int64), W, H, tri, bary, np.zeros((H, W)))
    return Raster(tri, bary, view_rays(cam) if rays else None)


def view_rays(cam: Camera) -> np.ndarray:
    """(H, W, 3) float32 unit view-ray directions (world) through the pixel centres."""
    W, H = int(cam.width), int(cam.height)
    r, u, f = camera_basis(cam)
    th = np.tan(np.radians(cam.fov_deg) / 2)
    px = ((np.arange(W, dtype=np.float32) + 0.5) / W * 2 - 1) * th * (W / H)
    py = (1 - (np.arange(H, dtype=np.float32) + 0.5) / H * 2) * th
    rays = (f[None, None] + px[None, :, None] * r[None, None] + py[:, None, None] * u[None, None]).astype(np.float32)
    rays /= np.linalg.norm(rays, axis=2, keepdims=True)
    return rays


@njit(cache=True)
def visible_vertices(tri: np.ndarray, faces: np.ndarray, nverts: int) -> np.ndarray:
    """Sorted ids of the vertices of every triangle in the ID buffer (Sec. V-B culling)."""
    mask = np.zeros(nverts, np.bool_)
    for y in range(tri.shape[0]):
        for x in range(tri.shape[1]):
            t = tri[y, x]
            if t >= 0:
                mask[faces[t, 0]] = True
                mask[faces[t, 1]] = True
                mask[faces[t, 2]] = True
    return np.flatnonzero(mask)


@njit(cache=True, parallel=True)
def resolve(tri: np.ndarray, bary: np.ndarray, faces: np.ndarray, rad: np.ndarray,
            img: np.ndarray) -> None:
    """img[p] = sum_k bary[p, k] rad[faces[tri[p], k]] for covered pixels (others untouched)."""
    for y in prange(tri.shape[0]):
        for x in range(tri.shape[1]):
            t = tri[y, x]
            if t < 0:
                continue
            a, b, c = faces[t, 0], faces[t, 1], faces[t, 2]
            for ch in range(3):
                img[y, x, ch] = bary[y, x, 0] * rad[a, ch] + bary[y, x, 1] * rad[b, ch] + bary[y, x, 2] * rad[c, ch]


def tonemap(img: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
    """Linear HDR -> 8-bit BGR for cv2.imwrite: exposure puts the 99th luminance percentile
    (of ``mask`` pixels) at 0.9, then sRGB encoding. All-black input -> black image."""
    x = np.nan_to_num(np.asarray(img, np.float64), nan=0.0, posinf=0.0)
    y = luminance(np.asarray(x, np.float64))
    sel = y[mask] if mask is not None and mask.any() else y.ravel()
    ref = float(np.percentile(sel, 99)) if sel.size else 0.0
    x = np.clip(x * (0.9 / ref if ref > 0 else 0.0), 0, 1)
    s = np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)
    return (s[..., ::-1] * 255 + 0.5).astype(np.uint8)


def lookup_equirect(img: np.ndarray, d: np.ndarray) -> np.ndarray:
    from lightprobe.core.sphere import angles_from_directions

    theta, phi = angles_from_directions(d.astype(np.float64))
    h, w = img.shape[:2]
    r = np.clip((theta / np.pi * h).astype(int), 0, h - 1)
    c = np.clip((np.mod(phi, 2 * np.pi) / (2 * np.pi) * w).astype(int), 0, w - 1)
    return img[r, c, :3]


def write_image(path: Path, img: np.ndarray, mask: np.ndarray | None = None) -> None:
    """PNG (tone-mapped, cv2) or EXR (linear, lightprobe.core.imageio.write_exr)."""
    if path.suffix.lower() == ".exr":
        from lightprobe.core.imageio import write_exr

        write_exr(path, img.astype(np.float32), {"unit": "relative", "source": "lightprobe relight"})
        return
    import cv2

    path.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(path), tonemap(img, mask)):
        raise InputError(f"{path}: cannot write image", param="--out")
