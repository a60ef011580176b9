"""``lightprobe relight SCENE --lights (URL|MAP.exr|MAP.hdr|LIGHTS.json) --out IMAGE [--method cuts|sg]``.

``--method sg`` (:mod:`lightprobe.hostlink.relight.sg.relighter`) needs no precompute; its ``--lights`` is a map, an SG
JSON (``GET /api/v1/sg``'s body) or a probe URL, whose ``/api/v1/sg`` it fetches.

URL forms: ``http://host:port`` (fetches ``/api/v1/lights``), or a full URL ending in
``probe.exr`` / ``probe.hdr`` / ``lights``. ``--live`` keeps a WebSocket on ``/api/v1/stream``
open and re-renders ``--out`` whenever a light set arrives (``--frames N`` stops after N).
``--token`` (or the URL's ``access_token``) is sent as a bearer token. ``--move NAME=dx,dy,dz``
and ``--rotate NAME=rx,ry,rz`` (XYZ Euler degrees, about the object's VCF centre) pose movable
objects relative to their precompute pose.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from lightprobe.core.errors import InputError

__all__ = ["load_lights", "main"]


def _lightset_from_json(doc: Any, where: str):  # type: ignore[no-untyped-def]
    from lightprobe.core.lightset import LightSet

    try:
        return LightSet.from_json(doc)
    except (KeyError, TypeError, ValueError, InputError) as e:
        raise InputError(f"{where}: not a light-set JSON ({e})", param="--lights") from None


def _read_json(p: Path) -> Any:
    """A ``--lights`` JSON file; unreadable or invalid JSON is an InputError naming it (and the line)."""
    try:
        return json.loads(p.read_text())
    except OSError as e:
        raise InputError(f"{p}: cannot read ({e.strerror})", param="--lights") from None
    except json.JSONDecodeError as e:
        raise InputError(f"{p}:{e.lineno}: invalid JSON ({e.msg})", param="--lights") from None


def _fetch(url: str, token: str | None) -> tuple[bytes, str]:
    import asyncio

    import aiohttp

    async def get() -> tuple[bytes, str]:
        headers = {"Authorization": f"Bearer {token}"} if token else {}
        async with aiohttp.ClientSession(timeout=aiohttp.ClientTimeout(total=30)) as s, \
                s.get(url, headers=headers) as r:
            if r.status != 200:
                raise InputError(f"{url}: HTTP {r.status}", param="--lights")
            return await r.read(), r.headers.get("Content-Type", "")

    try:
        return asyncio.run(get())
    except aiohttp.ClientError as e:
        raise InputError(f"{url}: cannot fetch ({e})", param="--lights") from None


def _fetch_json(url: str, token: str | None) -> Any:
    """A probe's JSON answer; a body that is not JSON is an InputError naming the URL."""
    body, ctype = _fetch(url, token)
    try:
        return json.loads(body)
    except json.JSONDecodeError:
        raise InputError(f"{url}: response is not JSON ({ctype})", param="--lights") from None


def _lights_url(src: str) -> str:
    base = src.rstrip("/")
    if base.endswith(("probe.exr", "probe.hdr", "/lights")):
        return base
    return base + "/api/v1/lights" if "/api/v1" not in base else base + "/lights"


def load_lights(src: str, token: str | None = None) -> tuple[str, Any]:
    """-> ("map", equirect float32) or ("lights", LightSet)."""
    from lightprobe.core.imageio import read_hdr_image

    if src.startswith(("http://", "https://")):
        url = _lights_url(src)
        if url.endswith((".exr", ".hdr")):
            body, _ctype = _fetch(url, token)
            with tempfile.NamedTemporaryFile(suffix=url[-4:]) as f:
                f.write(body)
                f.flush()
                return "map", read_hdr_image(f.name)
        return "lights", _lightset_from_json(_fetch_json(url, token), url)
    p = Path(src)
    if p.suffix.lower() == ".json":
        return "lights", _lightset_from_json(_read_json(p), str(p))
    if p.suffix.lower() not in (".exr", ".hdr"):
        raise InputError(f"{p}: --lights must be a URL, .exr, .hdr or .json", param="--lights")
    return "map", read_hdr_image(p)


def _parse_move(items: list[str], flag: str = "--move", form: str = "NAME=dx,dy,dz") -> list[tuple[str, np.ndarray]]:
    out = []
    for it in items:
        name, _, vec = it.partition("=")
        try:
            v = np.array([float(x) for x in vec.split(",")])
        except ValueError:
            v = np.zeros(0)
        if v.shape != (3,) or not np.isfinite(v).all():
            raise InputError(f"{flag} {it!r}: expected {form}", param=flag)
        out.append((name, v))
    return out


def _sg_lights(src: str, token: str | None) -> tuple[str, Any]:
    """-> ("map", equirect) or ("sg", SGLighting): a map, an SG JSON file, or a probe URL
    (its ``/api/v1/sg``)."""
    from lightprobe.core.sg import SGLighting

    def parse(doc: Any, where: str) -> SGLighting:
        try:
            return SGLighting.from_json(doc)
        except InputError as e:
            raise InputError(f"{where}: {e}", param="--lights") from None

    if src.startswith(("http://", "https://")):
        base = src.rstrip("/")
        if base.endswith(("probe.exr", "probe.hdr")):
            return load_lights(src, token)
        url = base if base.endswith("/sg") else (base + "/sg" if "/api/v1" in base else base + "/api/v1/sg")
        return "sg", parse(_fetch_json(url, token), url)
    p = Path(src)
    if p.suffix.lower() == ".json":
        return "sg", parse(_read_json(p), str(p))
    return load_lights(src, token)


def _run_sg(a: argparse.Namespace, out: Path) -> int:
    """``--method sg``: spherical Gaussians, per-pixel, no precompute (lightprobe.hostlink.relight.sg.relighter)."""
    from lightprobe.hostlink.relight.raster import write_image
    from lightprobe.hostlink.relight.scene import load_scene
    from lightprobe.hostlink.relight.sg.relighter import SGRelighter

    if a.live:
        raise InputError("--live re-renders with the cuts only: drop --method sg", param="--live")
    scene = load_scene(a.scene)
    kind, lights = _sg_lights(a.lights, a.token)
    t0 = time.perf_counter()
    rl = SGRelighter(scene, visibility=a.visibility, voxels=a.voxels)
    names = [o.name for o in scene.objects]
    moves = dict(_parse_move(a.move))
    turns = dict(_parse_move(a.rotate, "--rotate", "NAME=rx,ry,rz (degrees)"))
    for flag, d in (("--move", moves), ("--rotate", turns)):
        for name in d:
            if name not in names:
                raise InputError(f"{flag}: {name!r} is not an object of {a.scene}", param=flag)
    if a.frame is not None:
        rl.set_frame(a.frame)
    for name in set(moves) | set(turns):
        rl.move(name, moves.get(name, np.zeros(3)), turns.get(name))
    rl.set_equirect(lights) if kind == "map" else rl.set_sg(lights)
    img, stats = rl.render(background=lights if kind == "map" else None)
    write_image(out, img, mask=None)
    if not a.quiet:
        print(f"relight: wrote {out} (sg, {a.visibility} visibility, {len(rl.sg or [])} lobes, "
              f"{int(stats['pixels'])} pixels, {time.perf_counter() - t0:.3f} s, no precompute)", file=sys.stderr)
    return 0


def _run(a: argparse.Namespace) -> int:
    from lightprobe.hostlink.relight.cuts.precompute import precompute
    from lightprobe.hostlink.relight.cuts.render import Relighter
    from lightprobe.hostlink.relight.scene import load_scene

    out = Path(a.out)
    if out.suffix.lower() not in (".png", ".exr"):
        raise InputError(f"{out}: --out must end in .png or .exr", param="--out")
    if a.method == "sg":
        return _run_sg(a, out)
    scene = load_scene(a.scene)
    kind, lights = load_lights(a.lights, a.token)
    from lightprobe.hostlink.relight.cuts.cluster import resolve

    pre = precompute(scene, tau=a.tau, spheres=a.spheres, grid=a.grid, cache_dir=a.cache,
                     progress=not a.quiet, cluster=resolve(a.precompute_on))
    rl = Relighter(scene, pre)
    moves = dict(_parse_move(a.move))
    turns = dict(_parse_move(a.rotate, "--rotate", "NAME=rx,ry,rz (degrees)"))
    names = [o.name for o in scene.objects]
    for flag, d in (("--move", moves), ("--rotate", turns)):
        for name in d:
            if name not in names or not scene.objects[names.index(name)].movable:
                raise InputError(f"{flag}: {name!r} is not a movable object of {a.scene}", param=flag)
    for name in set(moves) | set(turns):
        rl.move(name, moves.get(name, np.zeros(3)), turns.get(name))
    bg = lights if kind == "map" else None
    rl.set_equirect(lights) if kind == "map" else rl.set_lightset(lights)
    t0 = time.perf_counter()
    img, stats = rl.render(background=bg)
    from lightprobe.hostlink.relight.raster import write_image

    write_image(out, img, mask=None)
    if not a.quiet:
        print(f"relight: wrote {out} ({time.perf_counter() - t0:.3f} s, "
              f"{int(stats['visible_vertices'])} visible vertices)", file=sys.stderr)
    if a.live:
        if not a.lights.startswith(("http://", "https://")):
            raise InputError("--live needs a probe URL for --lights", param="--live")
        from lightprobe.hostlink.relight.cuts.live import live_loop

        return live_loop(a.lights, a.token, rl, out, a.frames, a.quiet)
    return 0


def main(argv: list[str]) -> int:
    from lightprobe.core.command import run_command
    from lightprobe.hostlink.relight.cuts.precompute import DEFAULT_TAU

    p = argparse.ArgumentParser(prog="lightprobe relight",
                                description="Relight a scene (JSON scene file) with a probe's lights using "
                                            "self-visibility cuts and visibility cut fields, or spherical "
                                            "Gaussians (--method sg).")
    p.add_argument("scene", help="scene JSON file (meshes, materials, ground, camera)")
    p.add_argument("--lights", required=True,
                   help="probe URL (http://host:port), MAP.exr / MAP.hdr, or LIGHTS.json")
    p.add_argument("--out", required=True, help="output image, .png (tone-mapped) or .exr (linear)")
    p.add_argument("--method", choices=("cuts", "sg"), default="cuts",
                   help="cuts: visibility cuts (precomputed, cached; rigid motion); sg: spherical "
                        "Gaussians with cone-traced visibility (no precompute; any object may move "
                        "or deform; lambert and phong materials; --lights a map, an SG JSON or a "
                        "probe URL, whose /api/v1/sg it reads)")
    p.add_argument("--visibility", choices=("voxels", "rays"), default="voxels",
                   help="with --method sg: voxel cone tracing (default) or Embree rays per cone")
    p.add_argument("--frame", type=int, default=None, metavar="K",
                   help="with --method sg: deforming objects (their 'frames' in the scene file) take shape K")
    p.add_argument("--voxels", type=int, default=128, help="with --method sg: voxel grid side (power of two, default 128)")
    p.add_argument("--tau", type=float, default=DEFAULT_TAU, help=f"SVC cut threshold (default {DEFAULT_TAU})")
    p.add_argument("--spheres", type=int, default=32, help="VCF spheres per movable object (default 32)")
    p.add_argument("--grid", type=int, default=32, help="VCF points per cube face side (default 32)")
    p.add_argument("--cache", type=Path, default=None, help="precompute cache dir (default ~/.cache/lightprobe/relight)")
    p.add_argument("--precompute-on", default=None, metavar="tcp://HOST:8786|local",
                   help="run the precompute's chunks on a Dask cluster: a scheduler address, or "
                        "'local' for one worker process per core (default: $DASK_SCHEDULER_ADDRESS, "
                        "else in this process); finished chunks are cached, so a rerun redoes only "
                        "the missing ones")
    p.add_argument("--move", action="append", default=[], metavar="NAME=dx,dy,dz",
                   help="translate a movable object before rendering (repeatable)")
    p.add_argument("--rotate", action="append", default=[], metavar="NAME=rx,ry,rz",
                   help="rotate a movable object about its VCF centre by XYZ Euler angles in degrees "
                        "(applied before --move's translation; repeatable)")
    p.add_argument("--token", default=None, help="bearer token for the probe's API")
    p.add_argument("--live", action="store_true", help="re-render whenever the probe's lights change")
    p.add_argument("--frames", type=int, default=0, help="with --live: stop after N updates (0 = forever)")
    p.add_argument("--quiet", action="store_true", help="no progress bar or messages")
    a = p.parse_args(argv)
    return run_command(_run, a)


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
