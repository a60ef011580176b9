"""``lightprobe sample MAP.(exr|hdr) --method M --count N --out LIGHTS.json``.

Reads an equirect radiance map (W = 2H, CONVENTIONS.md), samples it with one of the registered
samplers and writes the light-set JSON atomically. Exit 0 on success, 2 on bad input (unreadable
file, non-equirect aspect, count < 1, unknown or unavailable method) with a one-line message
naming the file or parameter, 1 on other failures.
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
from pathlib import Path

from lightprobe.core.errors import InputError

__all__ = ["main"]

METHODS = ("pharr", "hemigon", "q2tree", "median-cut")


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="lightprobe sample",
                                description="Sample an equirect HDR map into directional lights "
                                            "(light-set JSON per CONVENTIONS.md).")
    p.add_argument("map", type=Path, help="equirect radiance map, .exr or .hdr, width = 2 x height")
    p.add_argument("--method", choices=METHODS, default="pharr", help="sampler (default pharr)")
    p.add_argument("--count", type=int, required=True, help="number of lights N >= 1")
    p.add_argument("--out", type=Path, required=True, help="output light-set JSON file")
    p.add_argument("--unit", default="relative", help='radiance unit of the map (default "relative")')
    return p


def _write_json_atomic(path: Path, data: dict[str, object]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "w") as f:
            json.dump(data, f, indent=1)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def _run(args: argparse.Namespace) -> int:
    from lightprobe.core.imageio import read_hdr_image
    from lightprobe.device.sampling.registry import make_sampler

    if args.count < 1:
        raise InputError(f"--count must be >= 1, got {args.count}", param="--count")
    image = read_hdr_image(args.map)
    h, w = image.shape[:2]
    if w != 2 * h:
        raise InputError(f"{args.map}: not an equirect map (width {w} != 2 x height {h})",
                         param=str(args.map))
    try:
        sampler = make_sampler(args.method)
    except ImportError as e:
        raise InputError(f"--method {args.method} is not available in this build ({e})",
                         param="--method") from e
    lights = sampler.sample(image, args.count)
    lights.unit = args.unit
    _write_json_atomic(args.out, lights.to_json())
    print(f"{args.out}: {len(lights)} lights ({args.method})")
    return 0


def main(argv: list[str]) -> int:
    from lightprobe.core.command import run_command

    args = _parser().parse_args(argv)
    return run_command(_run, args)
