"""``lightprobe room recover DIR``, ``lightprobe room render DIR --edit EDITS.json --out IMAGE`` and
``lightprobe room lights DIR --sg PROBE... --out captures/NAME.json``.

``recover`` writes ``DIR/reflectance.exr``, ``DIR/confidence.exr``, ``DIR/shading_source.exr``
(which pixel's geometry shades each pixel, :meth:`lightprobe.hostlink.relight.room.room.Room._snap`) and
``DIR/alignment.json`` (with ``--align``, the objects' offsets :meth:`lightprobe.hostlink.relight.room.room.Room.align`
found; ``{}`` without) atomically and prints what it used; ``render`` reads them (or recovers first), takes the lights of ``EDITS.json`` (the
captures' format: ``{"lights": [{"position", "radius", "rgb"}]}``, the whole edited set: change
a power, add or drop a light; ``"objects"``: virtual meshes to insert; ``"remove"``: room.obj
groups to take out; see :func:`lightprobe.hostlink.relight.room.room.load_edits`) and writes the room under them (``.exr`` linear, ``.png``
tone-mapped). ``lights`` places the lamps the probes see (their ``GET /api/v1/sg`` bodies, files
or URLs, with their poses) in ``room.obj`` and writes them in the captures' format
(:mod:`lightprobe.hostlink.relight.room.probes`). Bad input exits 2 naming the file.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

__all__ = ["main"]


def _room(d: Path, offsets: dict | None = None):  # type: ignore[no-untyped-def]
    from lightprobe.hostlink.relight.room.room import Room

    return Room(d, offsets=offsets)


def _read_alignment(d: Path) -> dict:
    """The objects' offsets ``recover --align`` found (``DIR/alignment.json``), {} without one."""
    import json

    from lightprobe.core.errors import InputError

    p = d / "alignment.json"
    if not p.is_file():
        return {}
    try:
        doc = json.loads(p.read_text())
    except (OSError, ValueError) as e:
        raise InputError(f"{p}: not a readable JSON file ({e})", param=str(p)) from e
    offsets = doc.get("offsets") if isinstance(doc, dict) else None
    if not isinstance(offsets, dict) or not all(
            isinstance(v, list) and len(v) == 3 and all(isinstance(x, (int, float)) for x in v) for v in offsets.values()):
        raise InputError(f"{p}: 'offsets' must map room.obj group names to [x, y, z]", param=str(p))
    return {str(k): [float(x) for x in v] for k, v in offsets.items()}


def _recover(a: argparse.Namespace) -> int:
    import json

    import numpy as np

    from lightprobe.core.fsutil import atomic_write
    from lightprobe.core.imageio import write_exr
    from lightprobe.hostlink.relight.room.room import Room

    t0 = time.perf_counter()
    room = Room.aligned(a.dir) if a.align else _room(a.dir)
    img = room.recover(filters=not a.no_filters, indirect=a.indirect)
    # always written: a render must use the model the reflectance was recovered with
    atomic_write(a.dir / "alignment.json", json.dumps(
        {"version": 1, "offsets": {k: list(v) for k, v in room.offsets.items()},
         "misfit_before_after": list(room.align_misfit) if room.align_misfit else None}, indent=1).encode())
    write_exr(a.dir / "reflectance.exr", img, {"lightprobe": "room reflectance"})
    conf = room.confidence_image()
    write_exr(a.dir / "confidence.exr", conf[..., None].repeat(3, axis=2), {"lightprobe": "room confidence"})
    write_exr(a.dir / "shading_source.exr", room.source_image(),
              {"lightprobe": "room shading source (row, column of the pixel whose geometry shades each pixel)"})
    if not a.quiet:
        print(f"room: {len(room.captures)} captures, {int(room.cover.sum())} pixels, {len(room.f)} patches, "
              + (f"objects moved {', '.join(f'{k} {1e3 * float(np.linalg.norm(v)):.1f} mm' for k, v in room.offsets.items()) or 'none'}"
                 f" (misfit {room.align_misfit[0]:.4g} -> {room.align_misfit[1]:.4g}), " if room.align_misfit else "")
              + f"{room.snapped} pixels shaded by a neighbour's geometry (the model is off there), "
              f"{time.perf_counter() - t0:.1f} s; wrote {a.dir / 'reflectance.exr'}, {a.dir / 'confidence.exr'}, "
              f"{a.dir / 'shading_source.exr'}",
              file=sys.stderr)
    return 0


def _render(a: argparse.Namespace) -> int:
    from lightprobe.core.errors import InputError
    from lightprobe.core.imageio import read_hdr_image
    from lightprobe.hostlink.relight.raster import write_image
    from lightprobe.hostlink.relight.room.io import load_edits

    out = Path(a.out)
    if out.suffix.lower() not in (".png", ".exr"):
        raise InputError(f"{out}: --out must end in .png or .exr", param="--out")
    lights, objects, remove = load_edits(a.edit)
    t0 = time.perf_counter()
    room = _room(a.dir, _read_alignment(a.dir))
    refl = a.dir / "reflectance.exr"
    if refl.is_file() and (a.dir / "confidence.exr").is_file():
        src = a.dir / "shading_source.exr"
        room.use_reflectance(read_hdr_image(refl), read_hdr_image(a.dir / "confidence.exr")[..., 0],
                             read_hdr_image(src) if src.is_file() else None)
    else:
        room.recover()
    img = room.render(lights, a.edit, objects, remove)
    write_image(out, img, mask=room.render_cover)
    if not a.quiet:
        print(f"room: wrote {out} ({len(lights)} lights, {len(objects)} objects, {len(remove)} groups removed, "
              f"{time.perf_counter() - t0:.1f} s)", file=sys.stderr)
    return 0


def _lights(a: argparse.Namespace) -> int:
    import json

    from lightprobe.core.fsutil import atomic_write
    from lightprobe.hostlink.relight.room.probes import lights_from_probes

    found = lights_from_probes(a.dir, a.sg)
    doc = {"lights": [{"position": list(f.light.position), "radius": f.light.radius, "rgb": list(f.light.rgb)}
                      for f in found]}
    out = Path(a.out)
    atomic_write(out, (json.dumps(doc, indent=1) + "\n").encode())
    if not a.quiet:
        for f in found:
            x, y, z = f.light.position
            print(f"room: lamp at ({x:.3f}, {y:.3f}, {z:.3f}) m, radius {f.light.radius:.3f} m, power "
                  f"{', '.join(f'{c:.4g}' for c in f.light.rgb)}: {f.method} from probes {f.probes}"
                  + (f", rays {1000 * f.gap:.1f} mm apart" if f.method == "triangulated" else ""), file=sys.stderr)
        print(f"room: wrote {out} ({len(found)} lamps from {len(a.sg)} probes)", file=sys.stderr)
    return 0


def main(argv: list[str]) -> int:
    from lightprobe.core.command import run_command

    p = argparse.ArgumentParser(prog="lightprobe room", description=__doc__.split("\n\n")[0])
    sub = p.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("recover", help="recover reflectance.exr and confidence.exr from the captures")
    r.add_argument("dir", type=Path, help="room folder: room.obj, camera.json, captures/NAME.exr + NAME.json")
    r.add_argument("--no-filters", action="store_true",
                   help="plain confidence-weighted merge (no confidence filter, outlier test, smoothing or refill)")
    r.add_argument("--indirect", choices=("radiosity", "ambient", "none"), default="radiosity",
                   help="indirect light: a radiosity solve over the patches (default), one ambient estimate "
                        "from each capture's mean colour, or none")
    r.add_argument("--align", action="store_true",
                   help="first move the room's objects sideways (up to 2%% of the room) to where the captures "
                        "put them; written to alignment.json, which render uses")
    r.add_argument("--quiet", action="store_true")
    e = sub.add_parser("render", help="render the room under the lights of EDITS.json")
    e.add_argument("dir", type=Path)
    e.add_argument("--edit", type=Path, required=True, help="EDITS.json: {\"lights\": [...], \"objects\": [...], \"remove\": [...]}: lights, virtual meshes, groups removed")
    e.add_argument("--out", required=True, help="IMAGE.exr (linear) or IMAGE.png (tone-mapped)")
    e.add_argument("--quiet", action="store_true")
    lt = sub.add_parser("lights", help="the lamps the probes see, placed in the room: a captures/NAME.json")
    lt.add_argument("dir", type=Path, help="room folder (its room.obj)")
    lt.add_argument("--sg", action="append", required=True,
                    help="a probe's GET /api/v1/sg body with its pose (a file), or the probe's URL; once per probe")
    lt.add_argument("--out", required=True, help="the lights JSON to write (e.g. DIR/captures/NAME.json)")
    lt.add_argument("--quiet", action="store_true")
    a = p.parse_args(argv)
    return run_command({"recover": _recover, "render": _render, "lights": _lights}[a.cmd], a)


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
