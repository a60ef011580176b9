"""A room folder's files (:mod:`.room` lists them): the camera, the captures' lights, the edits
(virtual objects, lights, removals), each read with an error naming the file at fault."""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from lightprobe.core.errors import InputError

__all__ = ["CameraCV", "Light", "VirtualObject", "load_camera", "load_edits", "load_lights"]


@dataclass(frozen=True)
class Light:
    position: tuple[float, float, float]
    radius: float
    rgb: tuple[float, float, float]     # emitted power per colour (W)


@dataclass
class CameraCV:
    K: np.ndarray
    R: np.ndarray
    t: np.ndarray
    width: int
    height: int

    @property
    def center(self) -> np.ndarray:
        return np.asarray(-self.R.T @ self.t)

    def scaled(self, s: float) -> CameraCV:
        """The same camera with images ``s`` times the size (pixel centres at integers, as OpenCV)."""
        w, h = max(1, round(self.width * s)), max(1, round(self.height * s))
        sx, sy = w / self.width, h / self.height
        K = np.array(self.K, np.float64, copy=True)
        K[0, 0], K[0, 1], K[0, 2] = K[0, 0] * sx, K[0, 1] * sx, (K[0, 2] + 0.5) * sx - 0.5
        K[1, 1], K[1, 2] = K[1, 1] * sy, (K[1, 2] + 0.5) * sy - 0.5
        return CameraCV(K, self.R, self.t, w, h)


def _read_json(path: Path) -> Any:
    try:
        return json.loads(path.read_text())
    except FileNotFoundError:
        raise InputError(f"{path}: missing", param=path.name) from None
    except OSError as e:
        raise InputError(f"{path}: cannot read ({e.strerror})", param=path.name) from None
    except json.JSONDecodeError as e:
        raise InputError(f"{path}:{e.lineno}: invalid JSON ({e.msg})", param=path.name) from None


def _mat(doc: dict[str, Any], key: str, shape: tuple[int, ...], where: Path) -> np.ndarray:
    try:
        a = np.asarray(doc[key], np.float64)
    except (KeyError, TypeError, ValueError):
        raise InputError(f"{where}: {key!r} must be a {'x'.join(map(str, shape))} array of numbers", param=key) from None
    if a.shape != shape or not np.isfinite(a).all():
        raise InputError(f"{where}: {key!r} must be a finite {'x'.join(map(str, shape))} array, got shape {a.shape}",
                         param=key)
    return a


def load_camera(path: str | Path) -> CameraCV:
    p = Path(path)
    doc = _read_json(p)
    if not isinstance(doc, dict):
        raise InputError(f"{p}: expected an object with K, R, t, width, height", param="camera")
    K, R, t = _mat(doc, "K", (3, 3), p), _mat(doc, "R", (3, 3), p), _mat(doc, "t", (3,), p)
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0:
        raise InputError(f"{p}: 'R' must be a rotation (orthonormal, det +1)", param="R")
    if K[0, 0] <= 0 or K[1, 1] <= 0:
        raise InputError(f"{p}: 'K' needs positive focal lengths", param="K")
    try:
        w, h = int(doc["width"]), int(doc["height"])
    except (KeyError, TypeError, ValueError):
        raise InputError(f"{p}: 'width' and 'height' must be integers", param="width") from None
    if not (0 < w <= 16384 and 0 < h <= 16384):
        raise InputError(f"{p}: width and height must be in 1..16384, got {w} x {h}", param="width")
    return CameraCV(K, R, t, w, h)


def load_lights(path: str | Path) -> list[Light]:
    p = Path(path)
    doc = _read_json(p)
    if not isinstance(doc, dict) or not isinstance(doc.get("lights"), list) or not doc["lights"]:
        raise InputError(f"{p}: expected {{\"lights\": [{{\"position\", \"radius\", \"rgb\"}}, ...]}}", param="lights")
    out = []
    for i, d in enumerate(doc["lights"]):
        if not isinstance(d, dict):
            raise InputError(f"{p}: lights[{i}] must be an object", param="lights")
        pos = _mat(d, "position", (3,), p)
        rgb = _mat(d, "rgb", (3,), p)
        try:
            r = float(d["radius"])
        except (KeyError, TypeError, ValueError):
            raise InputError(f"{p}: lights[{i}].radius must be a number", param="radius") from None
        if not (math.isfinite(r) and r > 0) or (rgb < 0).any():
            raise InputError(f"{p}: lights[{i}] needs radius > 0 and rgb >= 0", param="radius")
        out.append(Light(tuple(pos.tolist()), r, tuple(rgb.tolist())))  # type: ignore[arg-type]
    return out


@dataclass(frozen=True)
class VirtualObject:
    """A virtual mesh inserted into the room: posed vertices (world units), faces, and a
    Lambertian albedo."""

    name: str
    vertices: np.ndarray
    faces: np.ndarray
    albedo: tuple[float, float, float]


def load_edits(path: str | Path) -> tuple[list[Light], list[VirtualObject], list[str]]:
    """EDITS.json: ``{"lights": [...], "objects": [{"mesh": "spot.obj", "albedo": [r, g, b],
    "scale": s, "rotation": [x, y, z], "translation": [x, y, z]}], "remove": ["short_block"]}``:
    the whole edited light set (the captures' format), virtual meshes to insert (OBJ paths
    relative to the file; each scaled about its own origin, rotated by XYZ Euler degrees, then
    translated) and room.obj groups to remove."""
    from lightprobe.hostlink.relight.scene import load_obj, rotation_matrix

    p = Path(path)
    lights = load_lights(p)
    doc = _read_json(p)
    objs = doc.get("objects", [])
    if not isinstance(objs, list):
        raise InputError(f"{p}: 'objects' must be a list", param="objects")
    out = []
    for i, d in enumerate(objs):
        if not isinstance(d, dict) or not isinstance(d.get("mesh"), str):
            raise InputError(f"{p}: objects[{i}] needs a \"mesh\" (an OBJ path)", param="objects")
        alb = _mat(d, "albedo", (3,), p)
        if (alb < 0).any() or (alb > 1).any():
            raise InputError(f"{p}: objects[{i}].albedo must lie in [0, 1]", param="albedo")
        rot = _mat(d, "rotation", (3,), p) if "rotation" in d else np.zeros(3)
        tr = _mat(d, "translation", (3,), p) if "translation" in d else np.zeros(3)
        try:
            sc = float(d.get("scale", 1.0))
        except (TypeError, ValueError):
            raise InputError(f"{p}: objects[{i}].scale must be a number", param="scale") from None
        if not (math.isfinite(sc) and sc > 0):
            raise InputError(f"{p}: objects[{i}].scale must be > 0", param="scale")
        mp = Path(d["mesh"]) if Path(d["mesh"]).is_absolute() else p.parent / d["mesh"]
        mesh = load_obj(mp)
        v = (sc * np.asarray(mesh.vertices, np.float64)) @ rotation_matrix(rot).T + tr
        out.append(VirtualObject(str(d.get("name", mp.stem)), v, np.asarray(mesh.faces, np.int64),
                                 tuple(alb.tolist())))  # type: ignore[arg-type]
    rem = doc.get("remove", [])
    if not isinstance(rem, list) or not all(isinstance(x, str) for x in rem):
        raise InputError(f"{p}: 'remove' must be a list of room.obj group names", param="remove")
    return lights, out, rem
