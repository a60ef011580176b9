"""The ``lightprobe`` command line, the top of the stack: one module per command in this package.

Each command's module parses its own options and imports what it runs (inside its functions, so
``lightprobe --help`` stays instant and a broken optional backend cannot break unrelated
commands); the commands that wire a whole probe together (``serve``, ``run-pipeline``,
``calibrate``) share one bootstrap that builds cameras, calibrations and pipelines
(:mod:`.bootstrap`). Each exposes ``main(argv) -> int``. Exit codes: :mod:`lightprobe.core.command`.
"""

from __future__ import annotations

import argparse
import sys
from types import ModuleType

from . import (
    bench,
    calibrate,
    cameras,
    discover,
    export,
    fuse,
    record,
    relight,
    room,
    run_pipeline,
    sample,
    serve,
    token,
    warm_kernels,
)

__all__ = ["COMMANDS", "main"]

# command -> (module, one-line help). The module's main(argv) parses its own options.
COMMANDS: dict[str, tuple[ModuleType, str]] = {
    "serve": (serve, "run the probe service"),
    "token": (token, "print the API bearer token"),
    "warm-kernels": (warm_kernels, "compile the service's numba kernels (run once at install)"),
    "fuse": (fuse, "fuse an exposure stack into a linear HDR image"),
    "sample": (sample, "sample an equirect map into a light set"),
    "export": (export, "write a map as a host engine's lighting (SH, cube map, glTF, USD)"),
    "run-pipeline": (run_pipeline, "run the capture pipeline on a camera and print per-frame stats"),
    "record": (record, "record a camera's frames (or a real bracket) to replay with --camera replay:FILE"),
    "calibrate": (calibrate, "calibration routines (fisheye, response, photometric, ...)"),
    "cameras": (cameras, "list attached cameras and their capabilities"),
    "discover": (discover, "list probes on the LAN"),
    "relight": (relight, "relight a 3D scene with a probe's lights"),
    "room": (room, "recover a photographed room's reflectance and render it under other lights"),
    "bench": (bench, "run a benchmark, write JSON and PNG plots"),
}


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    from lightprobe.device.threads import select

    select()  # a thread-safe numba threading layer, before anything imports numba
    parser = argparse.ArgumentParser(
        prog="lightprobe",
        description="Live HDR light probe: capture, fuse, project and sample lighting.",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog="commands:\n" + "\n".join(f"  {k:<13} {v[1]}" for k, v in COMMANDS.items())
        + "\n\nRun 'lightprobe COMMAND --help' for a command's options.",
    )
    parser.add_argument("command", choices=sorted(COMMANDS), metavar="COMMAND")
    parser.add_argument("args", nargs=argparse.REMAINDER)
    ns = parser.parse_args(argv[:1])
    module, _ = COMMANDS[ns.command]
    try:
        return int(module.main(argv[1:]) or 0)
    except ModuleNotFoundError as e:
        if e.name and e.name.split(".")[0] != "lightprobe":  # an optional dependency of this command
            print(f"lightprobe: command {ns.command!r} needs {e.name}, which is not installed "
                  f"(pip install 'lightprobe[probe]', or [relight] for relight and room)", file=sys.stderr)
            return 1
        raise
