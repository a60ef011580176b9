"""``GET /api/v1/q2tree``: the compact Q2-Tree of the probe's latest map, for host-side merging.

The tree is built fresh on the latest frame's published map (``Q2TreeSampler`` with zero hysteresis and
jitter placement, so it is a function of the map alone and the host can reproduce the lights
from the leaves), with ``count`` lights (query, default ``pipeline.light_count``). The body is
the binary encoding of :mod:`lightprobe.core.q2wire` (``application/x-lightprobe-q2tree``); the frame,
probe id, unit and timestamp travel in ``X-Lightprobe-*`` headers. Encoded once per frame and
count (the runner clears its cache on every new frame); the tree is built in a worker thread.

Wire it with ``add_routes(app)`` after :func:`lightprobe.device.service.routes.probe.add_routes`.
"""

from __future__ import annotations

import asyncio
from typing import Any

import numpy as np
from aiohttp import web

from lightprobe.core.errors import InputError
from lightprobe.device.service.errors import ApiError
from lightprobe.device.service.state import STATE

__all__ = ["CONTENT_TYPE", "add_routes", "q2tree_bytes", "q2tree_handler"]

CONTENT_TYPE = "application/x-lightprobe-q2tree"
MAX_COUNT = 4096
ROUTE = "/api/v1/q2tree"


def q2tree_bytes(result: Any, count: int, nside_max: int = 256) -> bytes:
    """Encoding of the Q2-Tree with ``count`` lights over ``result.equirect`` (blocking: run in
    a thread): the map the light sets and ``probe.exr`` publish (the upper hemisphere), so the
    leaves sum to the served map's integral; the tree's finest level is ``min(auto nside,
    nside_max)``."""
    from lightprobe.core.q2wire import Q2Tree, encode_q2tree, nodes_to_uniq
    from lightprobe.device.sampling.base import sanitize_radiance
    from lightprobe.device.sampling.q2tree import Q2TreeSampler
    from lightprobe.device.sampling.q2tree._nodes import pyramid_from_equirect
    from lightprobe.device.sampling.q2tree.sampler import auto_nside

    clean, _ = sanitize_radiance(np.asarray(result.equirect))
    top = min(auto_nside(clean.shape[0]), nside_max)
    sampler = Q2TreeSampler(top, hysteresis=0.0, placement="jitter")
    sampler.sample(clean, count)
    pyr = pyramid_from_equirect(clean, top, False)
    level, index = sampler.to_nodes()
    uniq = nodes_to_uniq(level, index)
    return encode_q2tree(Q2Tree(uniq, pyr.rgb[uniq], pyr.max_level))


def _count(request: web.Request, default: int) -> int:
    raw = request.query.get("count")
    if raw is None:
        return default
    try:
        v = int(raw)
    except ValueError:
        raise InputError(f"count must be an integer in [1, {MAX_COUNT}], got {raw[:40]!r}",
                         param="count") from None
    if not 1 <= v <= MAX_COUNT:
        raise InputError(f"count must be an integer in [1, {MAX_COUNT}], got {v}", param="count")
    return v


async def q2tree_handler(request: web.Request) -> web.Response:
    """``GET /api/v1/q2tree[?count=N]``: the binary Q2-Tree encoding of the latest map."""
    st = request.app[STATE]
    for k in request.query:
        if k not in ("count", "access_token", "t"):
            raise InputError(f"unknown query parameter {k[:40]!r}", param=k[:40])
    count = _count(request, int(st.config.get("pipeline", "light_count")))
    r = st.runner.result
    if r is None:
        raise ApiError(503, "no frame yet: the pipeline is starting or the camera is reconnecting",
                       param="camera", headers={"Retry-After": "1"})
    frame = int(getattr(r, "frame", 0))
    key = f"q2tree:{count}"
    hit = st.runner.cache.get(key)
    if hit is not None and hit[0] == frame:
        data = hit[1]
    else:
        data = await asyncio.to_thread(q2tree_bytes, r, count)
        st.runner.cache[key] = (frame, data)
    headers = {"X-Lightprobe-Frame": str(frame), "X-Lightprobe-Probe": st.probe_id,
               "X-Lightprobe-Unit": str(getattr(r, "unit", "relative")),
               "X-Lightprobe-Timestamp": repr(float(getattr(r, "timestamp", 0.0))),
               **({} if getattr(r, "captured", None) is None
                  else {"X-Lightprobe-Captured": repr(float(r.captured))}),
               "X-Lightprobe-Stale": "true" if st.runner.stale else "false"}
    return web.Response(body=data, content_type=CONTENT_TYPE, headers=headers)


def add_routes(app: web.Application) -> None:
    """Register ``GET /api/v1/q2tree`` on the service app (idempotent: a second call is a no-op)."""
    if any(r.canonical == ROUTE for r in app.router.resources()):
        return
    app.router.add_get(ROUTE, q2tree_handler)
