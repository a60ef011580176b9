"""``lightprobe discover [--timeout S] [--json]``: list the probes on the LAN.

Browses ``_lightprobe._tcp.local.`` for ``--timeout`` seconds (and polls any ``--address``
HOST:PORT given for networks mDNS does not cross), then prints one line per probe, or with
``--json`` one object ``{"version": 1, "probes": [{"id", "name", "host", "port", "url", "path",
"version", "model", "sampler", "source", "service_name"}]}``. Exit 0 (also when none is found),
2 on bad arguments, 1 when discovery cannot run (no usable network interface).
"""

from __future__ import annotations

import argparse
import asyncio
import json
import sys

__all__ = ["build_parser", "main"]


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="lightprobe discover",
        description="List lightprobe units found by mDNS (_lightprobe._tcp) and manual addresses.")
    p.add_argument("--timeout", type=float, default=3.0, metavar="S",
                   help="seconds to listen before printing (default 3)")
    p.add_argument("--json", action="store_true", help="print JSON instead of a table")
    p.add_argument("--interface", action="append", default=[], metavar="ADDR",
                   help="IPv4 address of an interface to browse on (repeatable; default all)")
    p.add_argument("--address", action="append", default=[], metavar="HOST:PORT",
                   help="also query a probe at this address (repeatable; for VLANs)")
    p.add_argument("--token", default=None, help="bearer token for probes that require one")
    return p


async def _discover(a: argparse.Namespace) -> list[dict[str, object]]:
    from lightprobe.hostlink.discovery import Discovery

    disc = Discovery(interfaces=a.interface or None, manual=a.address,
                     manual_poll_s=max(a.timeout / 2, 0.5), token=a.token)
    await disc.start()
    try:
        await asyncio.sleep(a.timeout)
        return [p.to_json() for p in disc.snapshot()]
    finally:
        await disc.close()


def _run(argv: list[str]) -> int:
    from lightprobe.core.errors import InputError

    a = build_parser().parse_args(argv)
    if not 0 < a.timeout <= 3600:
        raise InputError(f"--timeout must be in (0, 3600] seconds, got {a.timeout}",
                         param="--timeout")
    try:
        probes = asyncio.run(_discover(a))
    except InputError:
        raise
    except OSError as e:
        print(f"lightprobe: error: cannot browse mDNS: {e}", file=sys.stderr)
        return 1
    if a.json:
        print(json.dumps({"version": 1, "probes": probes}, indent=2))
    elif not probes:
        print("no probes found")
    else:
        for p in probes:
            print(f"{p['name'] or '-':24} {p['id']:14} {p['url']:28} {p['model']} "
                  f"{p['version']} sampler={p['sampler']} ({p['source']})")
    return 0


def main(argv: list[str]) -> int:
    from lightprobe.core.command import run_command

    return run_command(_run, argv)
