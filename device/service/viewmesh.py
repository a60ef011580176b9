"""The mesh ``/view`` shows beside its spheres (``[view] mesh``, ``lightprobe serve --view-mesh``):
a Wavefront OBJ an installer points at (a product, a figurine, the shared ``spot.obj``), read and
checked once at start-up and served as it is at ``GET /view/mesh.obj`` for the page's own OBJ
reader. Only what that reader uses is checked: ``v x y z`` lines and ``f`` lines whose vertex
indices (1-based, or negative = relative, ``v/vt/vn`` forms) name existing vertices; other
statements (``vt``, ``vn``, ``g``, ``usemtl``, ...) pass through unread. A bad file stops the
start with an error naming it (exit 2), never a blank view."""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

from lightprobe.core.errors import InputError

__all__ = ["MAX_BYTES", "ViewMesh", "load_view_mesh"]

MAX_BYTES = 32 << 20  # a browser parses it: a few hundred thousand triangles at most


@dataclass(frozen=True)
class ViewMesh:
    name: str
    body: bytes
    vertices: int
    triangles: int  # after fan triangulation of polygons, as the page draws them


def load_view_mesh(path: str | Path, param: str = "view.mesh") -> ViewMesh:
    p = Path(path)
    try:
        if not p.exists():
            raise InputError(f"{p}: cannot read {param}: no such file", param=param)
        if not p.is_file():  # not a directory, FIFO or device (/dev/zero would never end)
            raise InputError(f"{p}: {param} is not a regular file", param=param)
        with p.open("rb") as f:
            body = f.read(MAX_BYTES + 1)  # bounded even if the file grows meanwhile
    except OSError as e:
        raise InputError(f"{p}: cannot read {param}: {e.strerror or e}", param=param) from e
    if len(body) > MAX_BYTES:
        raise InputError(f"{p}: {param} is more than the {MAX_BYTES} bytes a browser is sent", param=param)
    try:
        text = body.decode("utf-8")
    except UnicodeDecodeError as e:
        raise InputError(f"{p}: {param} is not a text (UTF-8) OBJ file", param=param) from e
    nv = tris = 0
    for ln, line in enumerate(text.splitlines(), 1):
        parts = line.split()
        if not parts:
            continue
        if parts[0] == "v":
            try:
                xyz = [float(x) for x in parts[1:4]]
            except ValueError:
                xyz = []
            if len(xyz) != 3 or not all(math.isfinite(x) for x in xyz):
                raise InputError(f"{p}:{ln}: {param}: a vertex needs three finite coordinates: {line.strip()[:80]!r}",
                                 param=param)
            nv += 1
        elif parts[0] == "f":
            if len(parts) < 4:
                raise InputError(f"{p}:{ln}: {param}: a face needs at least three vertices: {line.strip()[:80]!r}", param=param)
            for ref in parts[1:]:
                try:
                    k = int(ref.split("/", 1)[0])
                except ValueError:
                    k = 0
                if not (1 <= k <= nv or -nv <= k <= -1):
                    raise InputError(f"{p}:{ln}: {param}: face vertex {ref!r} does not name one of the {nv} vertices "
                                     "defined before it", param=param)
            tris += len(parts) - 3
    if tris == 0:
        raise InputError(f"{p}: {param} has no faces (an OBJ file with 'v' and 'f' lines is expected)", param=param)
    return ViewMesh(p.name, body, nv, tris)
