"""Scene files for relighting: meshes (OBJ), materials, transforms, a ground plane, a camera.

Scene file (JSON, ``version: 1``; mesh paths relative to the scene file)::

    {"version": 1,
     "materials": {"clay": {"type": "phong", "kd": [0.6, 0.5, 0.4], "ks": [0.3, 0.3, 0.3],
                            "exponent": 40},
                   "floor": {"type": "lambert", "kd": [0.5, 0.5, 0.5]}},
     "objects": [{"name": "spot", "mesh": "spot.obj", "material": "clay", "movable": true,
                  "translation": [0, 0, 0], "rotation_deg": [0, 30, 0], "scale": 1.0}],
     "ground": {"y": "auto", "size": 4.0, "resolution": 64, "material": "floor"},
     "camera": {"position": [2, 1.5, 2.5], "look_at": [0, 0, 0], "up": [0, 1, 0],
                "fov_deg": 40, "width": 640, "height": 480}}

A deforming object lists its shapes: ``"frames": ["spot_000.obj", "spot_001.obj", ...]``, OBJ files
with the mesh's vertex count and faces, transformed like the mesh; ``--method sg`` renders any of
them with no precompute (``lightprobe relight SCENE --method sg --frame K``;
:meth:`lightprobe.hostlink.relight.sg.relighter.SGRelighter.set_frame`), the cuts use ``mesh``.

Material types: ``lambert`` (kd), ``phong`` / ``blinn-phong`` (kd, ks, exponent), ``ward`` (kd,
ks, alpha). Rotations are XYZ Euler angles in degrees, applied after scale and before translation.
Errors in the file raise :class:`lightprobe.core.errors.InputError` naming the file (and line for OBJ).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from lightprobe.core.errors import InputError

__all__ = [
    "MATERIAL_TYPES",
    "Camera",
    "Material",
    "Mesh",
    "Scene",
    "SceneObject",
    "load_obj",
    "load_obj_groups",
    "load_scene",
    "rotation_matrix",
    "vertex_normals",
]

MATERIAL_TYPES = {"lambert": 0, "phong": 1, "blinn-phong": 2, "ward": 3}


@dataclass
class Mesh:
    vertices: np.ndarray   # (V, 3) float64
    faces: np.ndarray      # (F, 3) int64


@dataclass
class Material:
    type: str = "lambert"
    kd: tuple[float, float, float] = (0.5, 0.5, 0.5)
    ks: tuple[float, float, float] = (0.0, 0.0, 0.0)
    exponent: float = 32.0
    alpha: float = 0.2

    def row(self) -> np.ndarray:
        """Packed parameters for the render kernels: type, kd(3), ks(3), exponent-or-alpha."""
        p = self.alpha if self.type == "ward" else self.exponent
        return np.array([MATERIAL_TYPES[self.type], *self.kd, *self.ks, p], np.float64)


@dataclass
class SceneObject:
    name: str
    mesh: Mesh             # world-space at the precompute pose
    material: str
    movable: bool = False
    frames: list[np.ndarray] = field(default_factory=list)   # deforming: (V, 3) world vertices per frame


@dataclass
class Camera:
    position: np.ndarray = field(default_factory=lambda: np.array([0.0, 1.0, 3.0]))
    look_at: np.ndarray = field(default_factory=lambda: np.zeros(3))
    up: np.ndarray = field(default_factory=lambda: np.array([0.0, 1.0, 0.0]))
    fov_deg: float = 40.0
    width: int = 320
    height: int = 240


@dataclass
class Scene:
    objects: list[SceneObject]
    materials: dict[str, Material]
    camera: Camera
    source: str = "<memory>"


# ---- OBJ ---------------------------------------------------------------------------------------
def _obj_index(tok: str, n: int, where: str) -> int:
    try:
        k = int(tok.split("/")[0])
    except ValueError:
        raise InputError(f"{where}: malformed face index {tok!r}") from None
    if k == 0 or abs(k) > n:
        raise InputError(f"{where}: face index {k} out of range (1..{n} vertices so far)")
    return k - 1 if k > 0 else n + k


def load_obj(path: str | Path) -> Mesh:
    """Parse vertices and faces (polygons fan-triangulated; v/vt/vn and negative indices)."""
    return load_obj_groups(path)[0]


def load_obj_groups(path: str | Path) -> tuple[Mesh, np.ndarray, list[str]]:
    """:func:`load_obj` plus each face's group (``o`` / ``g`` name; faces before any are
    ``"default"``): (mesh, (F,) group index, group names)."""
    p = Path(path)
    try:
        text = p.read_text(errors="replace")
    except OSError as e:
        raise InputError(f"{p}: cannot read mesh ({e.strerror})") from None
    verts: list[tuple[float, float, float]] = []
    faces: list[tuple[int, int, int]] = []
    fgroup: list[int] = []
    names: list[str] = ["default"]
    current = 0
    for lineno, line in enumerate(text.splitlines(), 1):
        parts = line.split("#", 1)[0].split()
        if not parts:
            continue
        where = f"{p}:{lineno}"
        if parts[0] == "v":
            if len(parts) < 4:
                raise InputError(f"{where}: vertex needs 3 coordinates: {line.strip()[:60]!r}")
            try:
                xyz = (float(parts[1]), float(parts[2]), float(parts[3]))
            except ValueError:
                raise InputError(f"{where}: malformed vertex {line.strip()[:60]!r}") from None
            if not all(np.isfinite(xyz)):
                raise InputError(f"{where}: non-finite vertex coordinate")
            verts.append(xyz)
        elif parts[0] in ("o", "g"):
            name = " ".join(parts[1:]) or "default"
            if name not in names:
                names.append(name)
            current = names.index(name)
        elif parts[0] == "f":
            if len(parts) < 4:
                raise InputError(f"{where}: face needs at least 3 vertices: {line.strip()[:60]!r}")
            idx = [_obj_index(t, len(verts), where) for t in parts[1:]]
            faces.extend((idx[0], idx[i], idx[i + 1]) for i in range(1, len(idx) - 1))
            fgroup.extend([current] * (len(idx) - 2))
    if not verts or not faces:
        raise InputError(f"{p}: no vertices or faces")
    return Mesh(np.array(verts, np.float64), np.array(faces, np.int64)), np.array(fgroup, np.int64), names


def vertex_normals(mesh: Mesh) -> np.ndarray:
    """Area-weighted vertex normals (float64, unit; +y for isolated vertices)."""
    v, f = mesh.vertices, mesh.faces
    fn = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    n = np.zeros_like(v)
    for k in range(3):
        np.add.at(n, f[:, k], fn)
    ln = np.linalg.norm(n, axis=1, keepdims=True)
    return np.where(ln > 0, n / np.where(ln > 0, ln, 1), np.array([0.0, 1.0, 0.0]))


# ---- scene JSON ---------------------------------------------------------------------------------
def _vec(d: dict[str, Any], key: str, default: list[float], where: str) -> np.ndarray:
    val = d.get(key, default)
    try:
        arr = np.asarray(val, np.float64).reshape(3)
    except (ValueError, TypeError):
        raise InputError(f"{where}: {key} must be 3 numbers, got {val!r}") from None
    return arr


def rotation_matrix(deg: np.ndarray) -> np.ndarray:
    """Rotation matrix of XYZ Euler angles in degrees (x first): ``Rz Ry Rx``."""
    ax, ay, az = np.radians(deg)
    rx = np.array([[1, 0, 0], [0, np.cos(ax), -np.sin(ax)], [0, np.sin(ax), np.cos(ax)]])
    ry = np.array([[np.cos(ay), 0, np.sin(ay)], [0, 1, 0], [-np.sin(ay), 0, np.cos(ay)]])
    rz = np.array([[np.cos(az), -np.sin(az), 0], [np.sin(az), np.cos(az), 0], [0, 0, 1]])
    return rz @ ry @ rx


def _material(name: str, d: Any, where: str) -> Material:
    if not isinstance(d, dict) or d.get("type") not in MATERIAL_TYPES:
        t = d.get("type") if isinstance(d, dict) else d
        raise InputError(f"{where}: material {name!r} has unknown type {t!r} "
                         f"(one of {', '.join(MATERIAL_TYPES)})")
    try:
        kd = tuple(float(x) for x in d.get("kd", (0.5, 0.5, 0.5)))
        ks = tuple(float(x) for x in d.get("ks", (0.0, 0.0, 0.0)))
        m = Material(d["type"], kd, ks, float(d.get("exponent", 32.0)), float(d.get("alpha", 0.2)))  # type: ignore[arg-type]
    except (TypeError, ValueError):
        raise InputError(f"{where}: material {name!r} has malformed parameters") from None
    if len(m.kd) != 3 or len(m.ks) != 3 or m.exponent < 0 or m.alpha <= 0:
        raise InputError(f"{where}: material {name!r}: kd/ks need 3 values, exponent >= 0, alpha > 0")
    return m


def ground_mesh(y: float, size: float, res: int, center: np.ndarray) -> Mesh:
    """A square grid of (res+1)^2 vertices in the plane y, facing +y."""
    t = np.linspace(-size / 2, size / 2, res + 1)
    gx, gz = np.meshgrid(t + center[0], t + center[2], indexing="ij")
    v = np.stack([gx.ravel(), np.full(gx.size, y), gz.ravel()], axis=1)
    i, j = np.meshgrid(np.arange(res), np.arange(res), indexing="ij")
    a = (i * (res + 1) + j).ravel()
    b, c, d = a + 1, a + res + 1, a + res + 2
    f = np.concatenate([np.stack([a, b, c], 1), np.stack([b, d, c], 1)])
    return Mesh(v, f.astype(np.int64))


def _line_of(text: str, needle: str) -> int:
    for k, line in enumerate(text.splitlines(), 1):
        if needle in line:
            return k
    return 1


def load_scene(path: str | Path) -> Scene:
    """Read a scene file; every error raises InputError naming the file and line."""
    p = Path(path)
    try:
        text = p.read_text()
    except OSError as e:
        raise InputError(f"{p}: cannot read scene ({e.strerror})") from None
    try:
        doc = json.loads(text)
    except json.JSONDecodeError as e:
        raise InputError(f"{p}:{e.lineno}: invalid JSON ({e.msg})") from None
    if not isinstance(doc, dict) or not isinstance(doc.get("objects"), list):
        raise InputError(f"{p}:1: scene needs an 'objects' list")
    mats: dict[str, Material] = {}
    for name, d in (doc.get("materials") or {}).items():
        mats[name] = _material(name, d, f"{p}:{_line_of(text, json.dumps(name))}")
    objects: list[SceneObject] = []
    for k, od in enumerate(doc["objects"]):
        name = str(od.get("name", f"object{k}"))
        where = f"{p}:{_line_of(text, json.dumps(od.get('mesh', name)))}"
        if "mesh" not in od:
            raise InputError(f"{where}: object {name!r} has no 'mesh'")
        mesh_path = (p.parent / od["mesh"]).resolve()
        if not mesh_path.is_file():
            raise InputError(f"{where}: mesh file {od['mesh']!r} of object {name!r} not found")
        mat = od.get("material", "default")
        if mat not in mats and mat != "default":
            raise InputError(f"{p}:{_line_of(text, json.dumps(mat))}: unknown material {mat!r} "
                             f"in object {name!r}")
        mesh = load_obj(mesh_path)
        rot = rotation_matrix(_vec(od, "rotation_deg", [0, 0, 0], where))
        scale = float(od.get("scale", 1.0))
        tr = _vec(od, "translation", [0, 0, 0], where)
        v = mesh.vertices * scale @ rot.T + tr
        frames = []
        fl = od.get("frames", [])
        if not isinstance(fl, list) or not all(isinstance(x, str) for x in fl):
            raise InputError(f"{where}: 'frames' of object {name!r} must be a list of OBJ file names")
        for fname in fl:
            fp = (p.parent / fname).resolve()
            if not fp.is_file():
                raise InputError(f"{where}: frame file {fname!r} of object {name!r} not found")
            fm = load_obj(fp)
            if fm.vertices.shape != mesh.vertices.shape or not np.array_equal(fm.faces, mesh.faces):
                raise InputError(f"{fp}: frame of object {name!r} must have the mesh's {len(mesh.vertices)} "
                                 f"vertices and its faces (has {len(fm.vertices)} vertices, {len(fm.faces)} faces)")
            frames.append(fm.vertices * scale @ rot.T + tr)
        objects.append(SceneObject(name, Mesh(v, mesh.faces), mat, bool(od.get("movable", False)), frames))
    mats.setdefault("default", Material())
    g = doc.get("ground")
    if g:
        # a ground alone (no objects) sits at y = 0 about the origin, 4 units wide by default
        allv = np.concatenate([o.mesh.vertices for o in objects]) if objects else np.array([[-0.5, 0, -0.5], [0.5, 0, 0.5]])
        y = float(allv[:, 1].min()) if g.get("y", "auto") == "auto" else float(g["y"])
        gm = g.get("material", "default")
        if gm not in mats:
            raise InputError(f"{p}:{_line_of(text, json.dumps(gm))}: unknown material {gm!r} in ground")
        center = allv.mean(axis=0)
        size = float(g.get("size", 4 * np.ptp(allv, axis=0).max()))
        objects.append(SceneObject("ground", ground_mesh(y, size, int(g.get("resolution", 64)), center), gm))
    cd = doc.get("camera") or {}
    cam = Camera(_vec(cd, "position", [0, 1, 3], str(p)), _vec(cd, "look_at", [0, 0, 0], str(p)),
                 _vec(cd, "up", [0, 1, 0], str(p)), float(cd.get("fov_deg", 40.0)),
                 int(cd.get("width", 320)), int(cd.get("height", 240)))
    return Scene(objects, mats, cam, str(p))
