"""Live relighting: re-render whenever a probe publishes a new light set.

The light sets come from :meth:`hostlink.ProbeClient.subscribe` (``WS /api/v1/stream`` with
reconnect and backoff), so a probe that restarts or a network dropout resumes by itself; a stale
re-delivery of the last set (the client's signal that the stream dropped) is not re-rendered.
"""

from __future__ import annotations

import asyncio
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

from lightprobe.core.errors import InputError
from lightprobe.hostlink.relight.cuts.render import Relighter
from lightprobe.hostlink.relight.raster import write_image

__all__ = ["live_loop", "run_live"]


async def run_live(src: str, token: str | None, rl: Relighter, out: Path, frames: int, quiet: bool,
                   on_frame: Callable[[Any, Any], None] | None = None) -> int:
    """Re-render ``out`` for every light set of the probe at ``src`` (``http://host:port``);
    ``on_frame(light_set, image)`` is called after each write; stops after ``frames`` renders
    (0 = until cancelled)."""
    from lightprobe.hostlink.client import ProbeAuthError, ProbeClient

    done = 0
    async with ProbeClient(src, token=token) as client:
        try:
            async for ls in client.subscribe():
                if ls.stale:
                    continue  # the stream dropped: the client reconnects, the image stands
                rl.set_lightset(ls)
                img, _ = await asyncio.to_thread(rl.render)  # numba work off the loop
                await asyncio.to_thread(write_image, out, img)
                if on_frame is not None:
                    on_frame(ls, img)
                done += 1
                if not quiet:
                    print(f"relight: frame {ls.frame} -> {out}", file=sys.stderr)
                if frames and done >= frames:
                    break
        except ProbeAuthError as e:
            raise InputError(f"{src}: {e}", param="--token") from None
    return 0


def live_loop(src: str, token: str | None, rl: Relighter, out: Path, frames: int, quiet: bool) -> int:
    return asyncio.run(run_live(src, token, rl, out, frames, quiet))
