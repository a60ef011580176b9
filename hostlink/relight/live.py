"""Live relighting: re-render when a probe publishes a new light set on ``/api/v1/stream``."""

from __future__ import annotations

import asyncio
import json
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit, urlunsplit

from device.errors import InputError
from hostlink.relight.render import Relighter

__all__ = ["live_loop", "run_live", "stream_url"]


def stream_url(src: str) -> str:
    """ws(s)://host:port/api/v1/stream for a probe URL given as http(s)://host:port[/...]."""
    u = urlsplit(src)
    scheme = "wss" if u.scheme == "https" else "ws"
    return urlunsplit((scheme, u.netloc, "/api/v1/stream", "", ""))


async def run_live(src: str, token: str | None, rl: Relighter, out: Path, frames: int, quiet: bool,
                   on_frame: Callable[[Any, Any], None] | None = None) -> int:
    """Re-render ``out`` for every light set on the probe's stream; ``on_frame(light_set, image)``
    is called after each write; stops after ``frames`` renders (0 = when the stream closes)."""
    import aiohttp

    from device.sampling.base import LightSet
    from hostlink.relight.cli import write_image

    headers = {"Authorization": f"Bearer {token}"} if token else {}
    done = 0
    async with aiohttp.ClientSession() as s, s.ws_connect(stream_url(src), headers=headers, heartbeat=30) as ws:
        async for msg in ws:
            if msg.type != aiohttp.WSMsgType.TEXT:
                if msg.type in (aiohttp.WSMsgType.CLOSED, aiohttp.WSMsgType.ERROR):
                    break
                continue
            try:
                ls = LightSet.from_json(json.loads(msg.data))
            except (ValueError, KeyError, TypeError, InputError):
                continue                                         # not a light set: ignore
            rl.set_lightset(ls)
            img, _ = await asyncio.to_thread(rl.render)          # numba work off the loop
            await asyncio.to_thread(write_image, out, img)
            if on_frame is not None:
                on_frame(ls, img)
            done += 1
            if not quiet:
                print(f"relight: frame {ls.frame} -> {out}", file=sys.stderr)
            if frames and done >= frames:
                break
    return 0


def live_loop(src: str, token: str | None, rl: Relighter, out: Path, frames: int, quiet: bool) -> int:
    import aiohttp

    try:
        return asyncio.run(run_live(src, token, rl, out, frames, quiet))
    except aiohttp.ClientError as e:
        raise InputError(f"{src}: live stream failed ({e})", param="--lights") from None
