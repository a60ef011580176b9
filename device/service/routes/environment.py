"""Host formats of the live lighting (``lightprobe.device.formats``), under ``/api/v1``:

- ``GET sh?convention=canonical|threejs|webxr|filament|unity``: order-2 SH (all light and
  ambient) plus the primary light, JSON (``lightprobe.device.formats.sh_primary``), for the latest frame;
- ``GET cubemap.ktx2?size=N&levels=M``: the GGX-prefiltered cube map (RGBA16F KTX2), and
  ``GET cubemap/{px,nx,py,ny,pz,nz}.exr?mip=m`` its faces as float32 EXR;
- ``GET environment.gltf`` (+ ``environment/*.png``) and ``GET environment.usda`` (+ the latlong
  EXR files beside it): scene files with the probe's pose applied;
- ``GET /view``: a live three.js view lit by all of it, made with the three.js host module;
- ``GET /js/lightprobe-three.js`` (+ ``.d.ts``) and ``GET /js/three.module.min.js``: that module
  (``hostlink/threejs``, the host library's, which the probe serves so a page on the LAN imports
  it from the unit) and the three.js it was tested with, open to every origin (code, no data).

The SH and primary light are computed when asked, once per frame (``Runner.environment``). Cubemaps and
scene files are built on request in a worker thread and kept until the *lighting* changes (keyed
by a digest of the map, not by frame: a static room is filtered once). The map's pixels are an
image of the room: everything here except ``sh`` needs the token unless
``service.public_images`` (``lightprobe.device.service.app.PRIVATE_PREFIXES``).
"""

from __future__ import annotations

import asyncio
import hashlib
import json
from pathlib import Path
from typing import Any

import numpy as np
from aiohttp import web

from lightprobe.core.errors import InputError
from lightprobe.core.sh import CONVENTIONS
from lightprobe.device.service.errors import ApiError
from lightprobe.device.service.payloads import sg_payload
from lightprobe.device.service.routes.probe import check_query, static_handler
from lightprobe.device.service.state import STATE, VIEW_MESH, ServiceState

__all__ = ["HOST_JS", "add_routes"]

# the three.js host module (hostlink/threejs): beside this package in the repository and the
# wheel alike (lightprobe/device/service/routes -> lightprobe/hostlink/threejs); a file the probe
# serves, not code it imports
HOST_JS = Path(__file__).resolve().parents[3] / "hostlink" / "threejs"

API = "/api/v1"
MAX_SIZE = 128
_CACHE_ENTRIES = 8
_FILTERS = 3


def _int(request: web.Request, name: str, lo: int, hi: int, default: int, *, power_of_two: bool = False) -> int:
    raw = request.query.get(name)
    if raw is None:
        return default
    what = f"{name} must be {'a power of two' if power_of_two else 'an integer'} in [{lo}, {hi}]"
    try:
        v = int(raw)
    except ValueError:
        raise InputError(f"{what}, got {raw[:40]!r}", param=name) from None
    if not lo <= v <= hi or (power_of_two and v & (v - 1)):
        raise InputError(f"{what}, got {v}", param=name)
    return v


async def _latest(st: ServiceState) -> tuple[Any, Any]:
    r = st.runner.result
    env = await st.runner.environment() if r is not None else None
    if r is None or env is None:
        raise ApiError(503, "no frame yet: the pipeline is starting or the camera is reconnecting",
                       param="camera", headers={"Retry-After": "1"})
    return r, env


def _digest(equirect: np.ndarray) -> str:
    return hashlib.blake2b(np.ascontiguousarray(equirect).tobytes(), digest_size=16).hexdigest()


class _LightingCache:
    """Products of the map kept until the lighting changes: ``{(kind, params): (digest, value)}``."""

    def __init__(self) -> None:
        self.items: dict[tuple[Any, ...], tuple[str, Any]] = {}
        self.filters: dict[tuple[int, int], Any] = {}
        self.locks: dict[tuple[Any, ...], asyncio.Lock] = {}
        self.builds = 0

    async def get(self, key: tuple[Any, ...], digest: str, build: Any) -> Any:
        """The value for ``key`` at this lighting; built once however many requests ask at once."""
        async with self.locks.setdefault(key, asyncio.Lock()):
            hit = self.items.get(key)
            if hit is not None and hit[0] == digest:
                return hit[1]
            value = await asyncio.to_thread(build)
            self.builds += 1
            if len(self.items) >= _CACHE_ENTRIES:
                self.items.pop(next(iter(self.items)))
            self.items[key] = (digest, value)
            return value

    def filter(self, size: int, levels: int) -> Any:
        """A cube-map filter for the size and mip count (its tables kept for the last few asked)."""
        from lightprobe.device.formats.cubemap import CubemapFilter

        f = self.filters.pop((size, levels), None)
        if f is None:
            f = CubemapFilter(size, levels)
            while len(self.filters) >= _FILTERS:
                self.filters.pop(next(iter(self.filters)))
        self.filters[(size, levels)] = f  # most recently used last
        return f


CACHE: web.AppKey[_LightingCache] = web.AppKey("lighting_cache", _LightingCache)


def _cube_params(request: web.Request) -> tuple[int, int]:
    """``size`` (a power of two) and ``levels`` (default down to 4 x 4; more than the chain holds
    gives the whole chain)."""
    size = _int(request, "size", 1, MAX_SIZE, 64, power_of_two=True)
    max_levels = size.bit_length()
    default_levels = max(1, min(max_levels, size.bit_length() - 2)) if size >= 4 else max_levels
    return size, min(_int(request, "levels", 1, 16, default_levels), max_levels)


async def _map_digest(st: ServiceState, r: Any) -> str:
    key = f"digest:{int(r.frame)}"
    hit = st.runner.cache.get(key)
    if hit is not None:
        return hit[1].decode()
    d = await asyncio.to_thread(_digest, r.equirect)
    st.runner.cache[key] = (int(r.frame), d.encode())
    return d


async def sh(request: web.Request) -> web.Response:
    st = request.app[STATE]
    check_query(request, {"convention"})
    conv = request.query.get("convention", "canonical")
    if conv not in CONVENTIONS:
        raise InputError(f"convention must be one of {', '.join(CONVENTIONS)}, got {conv[:40]!r}",
                         param="convention")
    _, env = await _latest(st)
    body = env.to_json(conv)
    body["stale"] = st.runner.stale
    return web.json_response(body)


async def sg(request: web.Request) -> web.Response:
    st = request.app[STATE]
    check_query(request, set())
    await _latest(st)
    data = await sg_payload(st)
    if data is None:
        raise ApiError(503, "no frame yet", param="camera", headers={"Retry-After": "1"})
    return web.Response(body=data, content_type="application/json")


async def cubemap_ktx2(request: web.Request) -> web.Response:
    st = request.app[STATE]
    check_query(request, {"size", "levels"})
    size, levels = _cube_params(request)
    r, env = await _latest(st)
    cache = request.app[CACHE]
    digest = await _map_digest(st, r)
    flt = cache.filter(size, levels)

    data = await cache.get(("ktx2", size, levels), digest, lambda: flt.filter(r.equirect).ktx2(env.unit))
    return web.Response(body=data, content_type="image/ktx2",
                        headers={"Content-Disposition": 'inline; filename="cubemap.ktx2"',
                                 "X-Lightprobe-Frame": str(int(r.frame))})


async def cubemap_face(request: web.Request) -> web.Response:
    from lightprobe.core.imageio import exr_bytes
    from lightprobe.device.formats.cubemap import FACE_NAMES  # numba: kept off the start-up path

    st = request.app[STATE]
    check_query(request, {"size", "levels", "mip"})
    face = request.match_info["face"]
    if face not in FACE_NAMES:
        raise ApiError(404, f"no face {face[:8]!r}: faces are {', '.join(FACE_NAMES)}", param="face")
    size, levels = _cube_params(request)
    mip = _int(request, "mip", 0, 15, 0)
    if mip >= levels:
        raise ApiError(404, f"no mip {mip}: this chain has {levels} (0 .. {levels - 1})", param="mip")
    r, env = await _latest(st)
    cache = request.app[CACHE]
    digest = await _map_digest(st, r)
    flt = cache.filter(size, levels)
    cm = await cache.get(("cube", size, levels), digest, lambda: flt.filter(r.equirect))
    meta = {"unit": str(env.unit), "probe": st.probe_id, "frame": str(int(r.frame)), "face": face,
            "mip": str(mip), "roughness": f"{cm.roughness[mip]:g}",
            "cube_convention": "OpenGL/KTX face table, probe frame +y up, row 0 at top"}
    data = await asyncio.to_thread(exr_bytes, cm.mips[mip][FACE_NAMES.index(face)], meta)
    return web.Response(body=data, content_type="image/x-exr")


async def _scene(request: web.Request) -> tuple[dict[str, Any], dict[str, bytes], str]:
    """The glTF document and images, and the USD text, of the latest lighting (cached)."""
    from lightprobe.device.formats.primary import ambient_map
    from lightprobe.device.formats.scene import gltf_environment, usd_environment

    st = request.app[STATE]
    r, env = await _latest(st)
    cache = request.app[CACHE]
    digest = await _map_digest(st, r)
    flt = cache.filter(64, 5)  # 64 down to 4, as the cube-map endpoint's default

    def build() -> tuple[dict[str, Any], dict[str, bytes], str]:
        from lightprobe.core.imageio import exr_bytes

        amb = ambient_map(r.equirect, env.primary)
        cm = flt.filter(amb)
        doc, files = gltf_environment(env, cm)
        meta = {"unit": str(env.unit), "probe": st.probe_id, "frame": str(int(r.frame)),
                "layout": "latlong (OpenEXR / UsdLux): the probe frame's equirect"}
        files["environment_latlong.exr"] = exr_bytes(np.asarray(r.equirect, np.float32), meta)
        files["environment_ambient_latlong.exr"] = exr_bytes(amb, meta)
        return doc, files, usd_environment(env)

    return await cache.get(("scene",), digest, build)  # type: ignore[no-any-return]


def _with_token(doc: dict[str, Any], request: web.Request) -> dict[str, Any]:
    """Image URIs that carry the request's ``access_token`` (a loader fetching them relative to
    the document cannot add a header)."""
    tok = request.query.get("access_token")
    if not tok:
        return doc
    from urllib.parse import quote

    doc = json.loads(json.dumps(doc))
    for im in doc.get("images", []):
        im["uri"] = f"{im['uri']}?access_token={quote(tok)}"
    return doc


async def environment_gltf(request: web.Request) -> web.Response:
    check_query(request, set())
    doc, _, _ = await _scene(request)
    return web.Response(body=json.dumps(_with_token(doc, request)).encode(), content_type="model/gltf+json")


async def environment_file(request: web.Request) -> web.Response:
    check_query(request, set())
    name = request.match_info["name"]
    _, files, _ = await _scene(request)
    key = f"environment/{name}"
    if key not in files:
        raise ApiError(404, f"no environment image {name[:60]!r}", param="name")
    return web.Response(body=files[key], content_type="image/png")


async def environment_usda(request: web.Request) -> web.Response:
    check_query(request, set())
    _, _, text = await _scene(request)
    return web.Response(text=text, content_type="model/vnd.usda",
                        headers={"Content-Disposition": 'inline; filename="environment.usda"'})


def _latlong(name: str) -> Any:
    async def handler(request: web.Request) -> web.Response:
        check_query(request, set())
        _, files, _ = await _scene(request)
        return web.Response(body=files[name], content_type="image/x-exr")

    return handler


async def view_mesh(request: web.Request) -> web.Response:
    """The OBJ file of ``[view] mesh`` for ``/view`` (404 when none is configured: the page then
    shows its torus knot)."""
    check_query(request, set())
    mesh = request.app[VIEW_MESH]
    if mesh is None:
        raise ApiError(404, "no view mesh configured ([view] mesh or lightprobe serve --view-mesh)",
                       param="view.mesh")
    return web.Response(body=mesh.body, content_type="model/obj",
                        headers={"Content-Disposition": f'inline; filename="{mesh.name}"',
                                 "X-Mesh-Triangles": str(mesh.triangles)})


def _module_file(path: Path) -> Any:
    ctype = "text/javascript" if path.suffix == ".js" else "application/typescript"
    present = path.is_file()  # shipped with the package: looked for once

    async def handler(request: web.Request) -> web.StreamResponse:
        if not present:
            raise web.HTTPNotFound()
        # any page may import it (module scripts are fetched with CORS); no credentials, no data
        return web.FileResponse(path, headers={"Content-Type": ctype, "Access-Control-Allow-Origin": "*",
                                               "Cache-Control": "no-cache"})

    return handler


def add_routes(app: web.Application, static_dir: Path) -> None:
    app[CACHE] = _LightingCache()
    r = app.router
    r.add_get(f"{API}/sh", sh)
    r.add_get(f"{API}/sg", sg)
    r.add_get(f"{API}/cubemap.ktx2", cubemap_ktx2)
    r.add_get(f"{API}/cubemap/{{face}}.exr", cubemap_face)
    r.add_get(f"{API}/environment.gltf", environment_gltf)
    r.add_get(f"{API}/environment/{{name}}", environment_file)
    r.add_get(f"{API}/environment.usda", environment_usda)
    for name in ("environment_latlong.exr", "environment_ambient_latlong.exr"):
        r.add_get(f"{API}/{name}", _latlong(name))
    r.add_get("/view", static_handler(static_dir, "view.html"))
    js = {"lightprobe-three.js": HOST_JS / "lightprobe-three.js", "lightprobe-three.d.ts": HOST_JS / "lightprobe-three.d.ts",
          "three.module.min.js": static_dir / "vendor" / "three.module.min.js"}
    for name, path in js.items():
        r.add_get(f"/js/{name}", _module_file(path))
    r.add_get("/view/mesh.obj", view_mesh)  # its files: routes.probe.STATIC_FILES
