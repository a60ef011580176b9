"""The ``lightprobe`` command line: a thin dispatcher to each command's own module.

A command that drives one package lives beside it (``cameras``: ``drivers``, ``fuse``:
``device.hdr``, ``sample``: ``device.sampling``, ``discover`` and ``relight``: ``hostlink``,
``bench``: ``bench``); the commands that wire a whole probe together (``serve``, ``token``,
``run-pipeline``, ``calibrate``) live in this package, the top of the stack, with the one
bootstrap that builds cameras, calibrations and pipelines for them (:mod:`.bootstrap`). Each
exposes ``main(argv) -> int``; importing this module imports none of them, so ``lightprobe
--help`` is instant and a broken optional backend cannot break unrelated commands. Exit codes:
:mod:`device.core.command`.
"""

from __future__ import annotations

import argparse
import importlib
import sys

__all__ = ["COMMANDS", "main"]

# command -> (module, one-line help). The module's main(argv) parses its own options.
COMMANDS: dict[str, tuple[str, str]] = {
    "serve": ("device.cli.serve", "run the probe service"),
    "token": ("device.cli.token", "print the API bearer token"),
    "warm-kernels": ("device.cli.kernels", "compile the service's numba kernels (run once at install)"),
    "fuse": ("device.hdr.cli", "fuse an exposure stack into a linear HDR image"),
    "sample": ("device.sampling.cli", "sample an equirect map into a light set"),
    "export": ("device.formats.cli", "write a map as a host engine's lighting (SH, cube map, glTF, USD)"),
    "run-pipeline": ("device.cli.run_pipeline", "run the capture pipeline on a camera and print per-frame stats"),
    "calibrate": ("device.cli.calibrate", "calibration routines (fisheye, response, photometric, ...)"),
    "cameras": ("drivers.cli", "list attached cameras and their capabilities"),
    "discover": ("hostlink.cli", "list probes on the LAN"),
    "relight": ("hostlink.relight.cli", "relight a 3D scene with a probe's lights"),
    "room": ("hostlink.room.cli", "recover a photographed room's reflectance and render it under other lights"),
    "bench": ("bench.cli", "run a benchmark, write JSON and PNG plots"),
}


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
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
    module_name, _ = COMMANDS[ns.command]
    try:
        module = importlib.import_module(module_name)
    except ModuleNotFoundError as e:
        if e.name and module_name.startswith(e.name):
            print(f"lightprobe: command {ns.command!r} is not available in this build", file=sys.stderr)
            return 1
        raise
    return int(module.main(argv[1:]) or 0)

