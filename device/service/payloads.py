"""Per-frame bodies the API serves in more than one place (``GET`` and the stream), encoded
once per frame and kept in the runner's per-frame cache: the SH body per convention and the
SG lobes (fitted on demand, one fit per frame however many clients ask)."""

from __future__ import annotations

import asyncio
import json

import numpy as np

from lightprobe.device.service.state import ServiceState

__all__ = ["sg_body", "sg_payload", "sh_payload"]


async def sh_payload(st: ServiceState, conv: str) -> bytes | None:
    """The latest frame's SH body in ``conv``, encoded once per frame and convention."""
    env = await st.runner.environment()
    if env is None:
        return None
    key = f"sh:{conv}"
    hit = st.runner.cache.get(key)
    if hit is not None and hit[0] == int(env.frame):
        return hit[1]
    body = env.to_json(conv)
    body["stale"] = st.runner.stale
    data = json.dumps(body, separators=(",", ":")).encode()
    st.runner.cache[key] = (int(env.frame), data)
    return data


def sg_body(st: ServiceState) -> bytes | None:
    """The latest frame's SG lobes as JSON bytes (blocking: run in a thread), or ``None``."""
    from lightprobe.device.formats.sgfit import fit_sg

    r = st.runner.result
    if r is None:
        return None
    sg = fit_sg(np.asarray(r.equirect), probe=st.probe_id, frame=int(r.frame), timestamp=float(r.timestamp),
                unit=str(getattr(r, "unit", "relative")), captured=getattr(r, "captured", None))
    body = sg.to_json()
    body["stale"] = st.runner.stale
    if getattr(r.lights, "pose", None):      # as beside a light set: hosts place the lobes in the room
        body["pose"] = r.lights.pose
    return json.dumps(body, separators=(",", ":")).encode()


async def sg_payload(st: ServiceState) -> bytes | None:
    """:func:`sg_body`, fitted once per frame (shared by ``GET /sg`` and the stream)."""
    r = st.runner.result
    if r is None:
        return None
    frame = int(r.frame)
    hit = st.runner.cache.get("sg")
    if hit is not None and hit[0] == frame:
        return hit[1]
    lock = st.runner.cache_locks.setdefault("sg", asyncio.Lock())
    async with lock:  # one fit per frame however many clients ask
        hit = st.runner.cache.get("sg")
        if hit is not None and hit[0] == frame:
            return hit[1]
        data = await asyncio.to_thread(sg_body, st)
        if data is not None:
            st.runner.cache["sg"] = (frame, data)
        return data
