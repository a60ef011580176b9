"""``lightprobe warm-kernels``: compile every numba kernel the service runs, at install time.

numba compiles a kernel the first time it is called and caches the machine code beside the
source (``__pycache__``). A probe must not compile at start or at request time (the first
``GET /api/v1/q2tree`` would take seconds), so the install runs this command once: it starts
the real service in-process on the simulator (not paced), lets the pipeline run through a
metering sweep and a few cycles, asks every endpoint that computes (each sampler's on-demand
lights, the Q2-Tree, the map as EXR and Radiance HDR, the previews) and stops. Everything those paths call is then in the cache.

Under the systemd unit the package is read-only and numba needs a writable cache
(``NUMBA_CACHE_DIR`` in the state directory): :func:`seed_cache` copies the install's compiled
kernels there before numba loads (numba files a source directory's kernels under
``<cache>/<dirname>_<sha1 of its absolute path>``, and checks each against its source file's
timestamp and size, so a copy is valid exactly while the installed sources are the ones it was
compiled from; a stale one is simply recompiled).
"""

from __future__ import annotations

import argparse
import hashlib
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

__all__ = ["main", "seed_cache", "shipped_kernel_dirs"]

ROOT = Path(__file__).resolve().parents[1]  # the repository, or lightprobe/ in a wheel
PACKAGES = ("core", "device", "drivers", "sim", "calibration", "hostlink")


def shipped_kernel_dirs(root: Path = ROOT) -> list[Path]:
    """Source directories with compiled kernels in their ``__pycache__``."""
    out = []
    for pkg in PACKAGES:
        base = root / pkg
        if not base.is_dir():
            continue
        for cache in base.rglob("__pycache__"):
            if any(cache.glob("*.nbi")):
                out.append(cache.parent)
    return sorted(out)


def seed_cache(cache_dir: str | os.PathLike[str], root: Path = ROOT) -> int:
    """Copy the install's compiled kernels into ``cache_dir`` (numba's ``NUMBA_CACHE_DIR``
    layout) where missing or older; returns the number of files copied. Each file is written to
    a temporary name and renamed, so a concurrent start never reads half a file."""
    copied = 0
    target_root = Path(cache_dir)
    for src_dir in shipped_kernel_dirs(root):
        sub = f"{src_dir.name}_{hashlib.sha1(str(src_dir.resolve()).encode()).hexdigest()}"
        target = target_root / sub
        for f in (src_dir / "__pycache__").iterdir():
            if f.suffix not in (".nbi", ".nbc"):
                continue
            dst = target / f.name
            try:
                if dst.exists() and dst.stat().st_mtime >= f.stat().st_mtime:
                    continue
                target.mkdir(parents=True, exist_ok=True)
                tmp = dst.with_name(f".{dst.name}.{os.getpid()}.tmp")
                shutil.copy2(f, tmp)
                os.replace(tmp, dst)
                copied += 1
            except OSError:
                continue  # a cache is an optimisation: numba compiles what it cannot load
    return copied


async def _exercise(frames: int) -> dict[str, object]:
    import aiohttp
    from aiohttp import web

    from lightprobe.device.bootstrap import pipeline_factory
    from lightprobe.device.sampling.registry import SAMPLERS
    from lightprobe.device.service.app import create_app
    from lightprobe.device.service.config import ServiceConfig
    from lightprobe.drivers.discovery import open_camera

    token = "warm-kernels-token-0123456789abcdef"
    with tempfile.TemporaryDirectory(prefix="lp-warm-") as tmp:
        state = Path(tmp)
        cfg = ServiceConfig(path=state / "config.toml").with_patch({"mdns": {"enabled": False}})
        app = create_app(cfg, lambda: open_camera("sim", scene="flashlight", cache_dir=state / "cache",
                                                  realtime=False),
                         pipeline_factory(state, "warmkernels01"), token=token, probe_id="warmkernels01", port=0)
        runner = web.AppRunner(app, shutdown_timeout=0.5, access_log=None)
        await runner.setup()
        site = web.TCPSite(runner, "127.0.0.1", 0)
        await site.start()
        port = site._server.sockets[0].getsockname()[1]  # type: ignore[union-attr]
        url = f"http://127.0.0.1:{port}/api/v1"
        hdr = {"Authorization": f"Bearer {token}"}
        asked = 0
        try:
            async with aiohttp.ClientSession(headers=hdr) as c:
                async with c.ws_connect(url + "/stream") as ws:
                    for _ in range(frames):
                        await ws.receive(timeout=300)
                paths = ["/status", "/lights", "/q2tree", "/preview.jpg", "/preview.jpg?view=equirect",
                         "/probe.exr", "/probe.hdr", "/sh", "/sg", "/cubemap.ktx2", "/environment.gltf"]
                paths += [f"/lights?method={m}&count=64" for m in sorted(SAMPLERS)]
                for path in paths:
                    async with c.get(url + path) as r:
                        await r.read()
                        asked += 1
        finally:
            await runner.cleanup()
    return {"frames": frames, "requests": asked}


def main(argv: list[str] | None = None) -> int:
    import asyncio

    p = argparse.ArgumentParser(prog="lightprobe warm-kernels", description=__doc__.split("\n\n")[0])
    p.add_argument("--frames", type=int, default=40, help="frames to run the pipeline (default 40)")
    p.add_argument("--into", type=Path, default=None,
                   help="also copy the compiled kernels into this NUMBA_CACHE_DIR (e.g. a unit's)")
    a = p.parse_args(argv)
    if os.environ.get("NUMBA_CACHE_DIR"):
        print("lightprobe warm-kernels: unset NUMBA_CACHE_DIR: the kernels belong beside the sources",
              file=sys.stderr)
        return 2
    from lightprobe.device.threads import ThreadingLayerError, require_threadsafe, select

    select()
    try:  # an install without a thread-safe layer fails here, saying why, not with an abort later
        require_threadsafe()  # (and compiles the check's own kernel, which serve runs at start)
    except ThreadingLayerError as e:
        print(f"lightprobe warm-kernels: error: {e}", file=sys.stderr)
        return 2
    t0 = time.monotonic()
    res = asyncio.run(_exercise(a.frames))
    n = len(shipped_kernel_dirs())
    msg = f"lightprobe: compiled kernels in {n} source directories ({res['requests']} requests, "
    msg += f"{time.monotonic() - t0:.0f} s)"
    if a.into is not None:
        msg += f"; copied {seed_cache(a.into)} files into {a.into}"
    print(msg)
    return 0


if __name__ == "__main__":
    sys.exit(main())
