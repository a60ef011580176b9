"""``lightprobe export MAP.(exr|hdr) --format gltf|usd|sh|ktx2 --out PATH``: host formats of an
offline equirect map, exactly as the live probe serves them (``lightprobe.device.formats``).

- ``sh``: the ``GET /api/v1/sh`` JSON, ``--convention canonical|threejs|webxr|filament|unity``;
- ``ktx2``: the GGX cube map (``--size`` default 64, ``--levels``);
- ``gltf``: ``OUT.gltf`` plus its images in ``OUT_dir/environment/`` beside it;
- ``usd``: ``OUT.usda`` plus the two latlong EXR files beside it.
``--pose POSE.json`` (``{"rotation": 3x3, "position": [3]}``, CONVENTIONS.md) places the probe;
``--unit`` names the map's unit. Files are written atomically. Exit 0 on success, 2 on bad input
(a one-line message naming the file or parameter), 1 on other failures.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import numpy as np

from lightprobe.core.errors import InputError

__all__ = ["main"]

FORMATS = ("gltf", "usd", "sh", "ktx2")


def _parser() -> argparse.ArgumentParser:
    from lightprobe.core.sh import CONVENTIONS

    p = argparse.ArgumentParser(prog="lightprobe export",
                                description="Write an equirect HDR map as a host engine's lighting: "
                                            "SH + primary light, GGX cube map, glTF or USD.")
    p.add_argument("map", type=Path, help="equirect radiance map, .exr or .hdr, width = 2 x height")
    p.add_argument("--format", choices=FORMATS, required=True, help="what to write")
    p.add_argument("--out", type=Path, required=True, help="output file (.json, .ktx2, .gltf, .usda)")
    p.add_argument("--convention", choices=CONVENTIONS, default="canonical", help="SH convention (sh only)")
    p.add_argument("--size", type=int, default=64, help="cube map face size, a power of two (default 64)")
    p.add_argument("--levels", type=int, default=None, help="cube map mips (default: down to 4 x 4)")
    p.add_argument("--pose", type=Path, default=None, help="probe pose JSON (rotation 3x3, position)")
    p.add_argument("--unit", default="relative", help='radiance unit of the map (default "relative")')
    return p


def _pose(path: Path | None) -> dict[str, Any] | None:
    if path is None:
        return None
    try:
        d = json.loads(path.read_text())
        r = np.asarray(d["rotation"], np.float64).reshape(3, 3)
        t = np.asarray(d.get("position", [0, 0, 0]), np.float64).reshape(3)
    except (OSError, ValueError, KeyError, TypeError) as e:
        raise InputError(f"{path}: not a pose (rotation 3x3, position [3]): {e}", param="--pose") from None
    if not np.allclose(r @ r.T, np.eye(3), atol=1e-6) or np.linalg.det(r) < 0:
        raise InputError(f"{path}: rotation is not a proper rotation matrix", param="--pose")
    return {"rotation": r.tolist(), "position": t.tolist()}


def _run(args: argparse.Namespace) -> int:
    from lightprobe.core.fsutil import atomic_write
    from lightprobe.core.imageio import exr_bytes, read_hdr_image
    from lightprobe.device.formats.cubemap import CubemapFilter
    from lightprobe.device.formats.primary import ambient_map
    from lightprobe.device.formats.scene import gltf_bytes, gltf_environment, usd_environment
    from lightprobe.device.formats.sh_primary import EnvironmentEstimator

    image = read_hdr_image(args.map)
    h, w = image.shape[:2]
    if w != 2 * h or h % 2:
        raise InputError(f"{args.map}: not an equirect map (width {w} != 2 x height {h})", param=str(args.map))
    flt = CubemapFilter(args.size, args.levels)  # validates --size / --levels before any work
    env = EnvironmentEstimator().estimate(image, unit=args.unit, probe=args.map.stem, pose=_pose(args.pose))
    out: Path = args.out
    if args.format == "sh":
        atomic_write(out, json.dumps(env.to_json(args.convention), indent=1).encode())
    elif args.format == "ktx2":
        atomic_write(out, flt.filter(image).ktx2(args.unit))
    elif args.format == "gltf":
        cm = flt.filter(ambient_map(image, env.primary))
        image_dir = f"{out.stem}_files"
        doc, files = gltf_environment(env, cm, image_dir=image_dir)
        for uri, data in files.items():
            (out.parent / uri).parent.mkdir(parents=True, exist_ok=True)
            atomic_write(out.parent / uri, data)
        atomic_write(out, gltf_bytes(doc))
    else:
        dome, amb = f"{out.stem}_latlong.exr", f"{out.stem}_ambient_latlong.exr"
        meta = {"unit": args.unit, "layout": "latlong (OpenEXR / UsdLux)"}
        atomic_write(out.parent / dome, exr_bytes(np.asarray(image, np.float32), meta))
        atomic_write(out.parent / amb, exr_bytes(ambient_map(image, env.primary), meta))
        atomic_write(out, usd_environment(env, dome, amb).encode())
    prim = env.primary
    print(f"{out}: {args.format}" + (f", primary light {np.round(prim.direction, 4).tolist()} "
                                     f"({100 * prim.energy_fraction:.1f}% of the light)" if prim else ", no primary light"))
    return 0


def main(argv: list[str]) -> int:
    from lightprobe.core.command import run_command

    args = _parser().parse_args(argv)
    return run_command(_run, args)
