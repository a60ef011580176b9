"""An aiohttp client for one probe's HTTP/WebSocket API (``/api/v1``, see CONVENTIONS.md).

:class:`ProbeClient` reads the status, light sets (``LightSet.from_json``), the HDR map (OpenEXR
through ``lightprobe.core.imageio``) and the Q2-Tree encoding (:mod:`lightprobe.core.q2wire`), and follows the
WebSocket stream with :meth:`ProbeClient.subscribe`: on a dropout the last light set is
re-delivered once marked ``stale``, then the client reconnects with exponential backoff
(``backoff_initial`` doubling up to ``backoff_max``, reset after a good connection).

Errors are typed: :class:`ProbeUnavailable` (cannot connect, timeout, 503), :class:`ProbeAuthError`
(401/403), :class:`ProbeRequestError` (other 4xx: the message names the parameter),
:class:`ProbeProtocolError` (a reply that is not what the API promises). All derive from
:class:`ProbeError`.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import json
import logging
import os
import tempfile
from collections.abc import AsyncIterator
from typing import TYPE_CHECKING, Any

import aiohttp
import numpy as np

from lightprobe.core.errors import InputError, LightprobeError
from lightprobe.core.lightset import LightSet
from lightprobe.core.q2wire import Q2DecodeError, Q2Tree, decode_q2tree

if TYPE_CHECKING:
    from lightprobe.core.ktx2 import CubeMap
    from lightprobe.core.scene_files import EnvironmentFiles
    from lightprobe.core.sg import SGLighting
    from lightprobe.core.sh import SHLighting

__all__ = [
    "ProbeAuthError",
    "ProbeClient",
    "ProbeError",
    "ProbeProtocolError",
    "ProbeRequestError",
    "ProbeUnavailable",
]

log = logging.getLogger(__name__)


class ProbeError(LightprobeError):
    """Base of the client's errors; ``url`` is the request that failed."""

    def __init__(self, message: str, url: str = "", status: int | None = None) -> None:
        super().__init__(message)
        self.url, self.status = url, status


class ProbeUnavailable(ProbeError):
    """The probe cannot be reached, timed out, or has no frame yet (503)."""


class ProbeAuthError(ProbeError):
    """The probe refused the request: missing or wrong bearer token (401/403)."""


class ProbeRequestError(ProbeError):
    """The probe rejected a parameter (4xx); the message is the probe's."""


class ProbeProtocolError(ProbeError):
    """The probe answered, but not with what the API promises (bad JSON, type, encoding)."""


def _api_url(url: str) -> str:
    url = url.rstrip("/")
    return url if url.endswith("/api/v1") else url + "/api/v1"


class ProbeClient:
    """Client of one probe at ``url`` (``http://host:port`` or ``.../api/v1``).

    Pass a ``session`` to share connections between probes (it is then not closed here).
    """

    def __init__(self, url: str, *, token: str | None = None,
                 session: aiohttp.ClientSession | None = None, timeout: float = 5.0,
                 backoff_initial: float = 0.25, backoff_max: float = 8.0) -> None:
        self.api = _api_url(url)
        self.token = token
        self.timeout = float(timeout)
        self.backoff_initial, self.backoff_max = float(backoff_initial), float(backoff_max)
        self._session = session
        self._own_session = session is None
        self.connected = False
        self.reconnects = 0

    # ---- lifecycle ------------------------------------------------------------------------------
    def _sess(self) -> aiohttp.ClientSession:
        if self._session is None or self._session.closed:
            self._session = aiohttp.ClientSession()
            self._own_session = True
        return self._session

    async def close(self) -> None:
        if self._own_session and self._session is not None:
            await self._session.close()
        self._session = None

    async def __aenter__(self) -> ProbeClient:
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    def _headers(self) -> dict[str, str]:
        return {"Authorization": f"Bearer {self.token}"} if self.token else {}

    # ---- requests -------------------------------------------------------------------------------
    async def _get(self, path: str, params: dict[str, str] | None = None
                   ) -> tuple[bytes, dict[str, str], str]:
        url = self.api + path
        try:
            async with self._sess().get(url, params=params, headers=self._headers(),
                                        timeout=aiohttp.ClientTimeout(total=self.timeout)) as r:
                body = await r.read()
                if r.status >= 400:
                    _raise_for(r.status, body, url)
                return body, dict(r.headers), r.content_type
        except (aiohttp.ClientConnectionError, TimeoutError, OSError) as e:
            raise ProbeUnavailable(f"{url}: {type(e).__name__}: {e}", url) from e

    async def _json(self, path: str, params: dict[str, str] | None = None) -> Any:
        body, _, _ = await self._get(path, params)
        try:
            return json.loads(body)
        except (ValueError, UnicodeDecodeError) as e:
            raise ProbeProtocolError(f"{self.api + path}: reply is not JSON: {e}",
                                     self.api + path) from e

    async def status(self) -> dict[str, Any]:
        """``GET /status`` (probe id, health, camera state, timings ...)."""
        d = await self._json("/status")
        if not isinstance(d, dict) or not isinstance(d.get("probe"), dict):
            raise ProbeProtocolError(f"{self.api}/status: not a status object", self.api + "/status")
        return d

    async def lights(self, method: str | None = None, count: int | None = None) -> LightSet:
        """``GET /lights`` (the published set, or a fresh one for ``method`` / ``count``)."""
        params = {k: str(v) for k, v in (("method", method), ("count", count)) if v is not None}
        return _lightset(await self._json("/lights", params or None), self.api + "/lights")

    async def hdr_map(self) -> tuple[np.ndarray, dict[str, str]]:
        """``GET /probe.exr`` (needs the token: a map is a picture of the room, unless the
        installer set ``service.public_images``): the latest equirect radiance map (float32 (H, 2H, 3)) and the
        probe's metadata headers."""
        body, headers, ctype = await self._get("/probe.exr")
        if ctype != "image/x-exr":
            raise ProbeProtocolError(f"{self.api}/probe.exr: content type {ctype!r}",
                                     self.api + "/probe.exr")
        return await asyncio.to_thread(_read_exr_bytes, body, self.api + "/probe.exr"), headers

    async def q2tree(self, count: int | None = None) -> Q2Tree:
        """``GET /q2tree``: the probe's Q2-Tree (decoded and checked), with ``meta`` holding
        probe, frame, unit, timestamp, captured (None when not sent) and stale from the reply
        headers."""
        params = {"count": str(count)} if count is not None else None
        body, headers, _ = await self._get("/q2tree", params)
        meta = {"probe": headers.get("X-Lightprobe-Probe", ""),
                "frame": int(headers.get("X-Lightprobe-Frame", "0") or 0),
                "unit": headers.get("X-Lightprobe-Unit", "relative"),
                "timestamp": float(headers.get("X-Lightprobe-Timestamp", "0") or 0),
                "captured": float(headers["X-Lightprobe-Captured"]) if headers.get("X-Lightprobe-Captured") else None,
                "stale": headers.get("X-Lightprobe-Stale") == "true"}
        try:
            return decode_q2tree(body, meta)
        except Q2DecodeError as e:
            raise ProbeProtocolError(f"{self.api}/q2tree: {e}", self.api + "/q2tree") from e

    # ---- host formats ---------------------------------------------------------------------------
    async def sh(self, convention: str = "canonical") -> SHLighting:
        """``GET /sh``: order-2 SH (all light, ambient) and the primary light in a host's
        convention (canonical, threejs, webxr, filament, unity)."""
        from lightprobe.core.sh import SHLighting

        d = await self._json("/sh", {"convention": convention})
        try:
            return SHLighting.from_json(d)
        except InputError as e:
            raise ProbeProtocolError(f"{self.api}/sh: {e}", self.api + "/sh") from e

    async def sg(self) -> SGLighting:
        """``GET /sg``: the lighting as spherical Gaussians (peak and residual lobes)."""
        from lightprobe.core.sg import SGLighting

        d = await self._json("/sg")
        try:
            return SGLighting.from_json(d)
        except InputError as e:
            raise ProbeProtocolError(f"{self.api}/sg: {e}", self.api + "/sg") from e

    async def cubemap(self, size: int = 64, levels: int | None = None) -> CubeMap:
        """``GET /cubemap.ktx2`` (needs the token unless ``service.public_images``): the
        GGX-prefiltered cube map, decoded."""
        from lightprobe.core.ktx2 import CubeMap, read_ktx2_cubemap

        params = {"size": str(size)} | ({"levels": str(levels)} if levels is not None else {})
        body, _, _ = await self._get("/cubemap.ktx2", params)
        try:
            mips, kv = read_ktx2_cubemap(body)
        except InputError as e:
            raise ProbeProtocolError(f"{self.api}/cubemap.ktx2: {e}", self.api + "/cubemap.ktx2") from e
        rough = [float(x) for x in str(kv.get("lightprobe.roughness", "")).split(",") if x]
        return CubeMap([m[..., :3].copy() for m in mips], rough, kv)

    async def environment(self, kind: str = "gltf") -> EnvironmentFiles:
        """``GET /environment.gltf`` or ``/environment.usda`` (needs the token unless
        ``service.public_images``) with every file it references (glTF images, USD textures)."""
        from lightprobe.core.scene_files import EnvironmentFiles

        if kind not in ("gltf", "usd"):
            raise InputError(f"kind must be 'gltf' or 'usd', got {kind!r}", param="kind")
        name = "environment.gltf" if kind == "gltf" else "environment.usda"
        body, _, _ = await self._get("/" + name)
        if kind == "gltf":
            try:
                refs = [im["uri"].split("?")[0] for im in json.loads(body).get("images", [])]
            except (ValueError, KeyError, TypeError, AttributeError) as e:
                raise ProbeProtocolError(f"{self.api}/{name}: not a glTF document: {e}", self.api + "/" + name) from e
        else:
            import re

            refs = re.findall(rb"@([^@]+)@", body)
            refs = [r.decode() for r in refs]
        files = {}
        for ref in refs:
            data, _, _ = await self._get("/" + ref)
            files[ref] = data
        return EnvironmentFiles(name, body, files)

    # ---- the stream -----------------------------------------------------------------------------
    async def subscribe(self, *, heartbeat: float = 5.0) -> AsyncIterator[LightSet]:
        """Light sets from ``WS /stream``, forever (cancel or ``break`` to stop).

        A dropout re-delivers the last set once with ``stale=True``, then reconnects with
        exponential backoff; auth errors are raised (retrying cannot fix them).
        """
        backoff = self.backoff_initial
        last: LightSet | None = None
        url = self.api + "/stream"
        while True:
            try:
                async with self._sess().ws_connect(url, headers=self._headers(), heartbeat=heartbeat,
                                                   timeout=aiohttp.ClientWSTimeout(ws_close=1.0),
                                                   max_msg_size=0) as ws:
                    self.connected = True
                    async for msg in ws:
                        if msg.type != aiohttp.WSMsgType.TEXT:
                            break
                        try:
                            last = _lightset(json.loads(msg.data), url)
                        except (ValueError, ProbeProtocolError) as e:
                            log.warning("%s: bad message skipped: %s", url, e)
                            continue
                        backoff = self.backoff_initial
                        yield last
            except aiohttp.WSServerHandshakeError as e:
                if e.status in (401, 403):
                    raise ProbeAuthError(f"{url}: {e.status} {e.message}", url, e.status) from e
                log.info("%s: handshake failed (%s)", url, e.status)
            except (aiohttp.ClientError, TimeoutError, OSError) as e:
                log.info("%s: connection lost: %s", url, e)
            self.connected = False
            if last is not None and not last.stale:
                last = dataclasses.replace(last, stale=True)
                yield last
            await asyncio.sleep(backoff)
            self.reconnects += 1
            backoff = min(backoff * 2.0, self.backoff_max)


def _raise_for(status: int, body: bytes, url: str) -> None:
    msg = body[:300].decode("utf-8", "replace")
    with contextlib.suppress(ValueError, UnicodeDecodeError, AttributeError):
        d = json.loads(body)
        msg = str(d.get("error") or d.get("message") or msg)
    if status in (401, 403):
        raise ProbeAuthError(f"{url}: {status}: {msg}", url, status)
    if status in (502, 503, 504):
        raise ProbeUnavailable(f"{url}: {status}: {msg}", url, status)
    if 400 <= status < 500:
        raise ProbeRequestError(f"{url}: {status}: {msg}", url, status)
    raise ProbeProtocolError(f"{url}: {status}: {msg}", url, status)


def _lightset(d: Any, url: str) -> LightSet:
    try:
        return LightSet.from_json(d)
    except (InputError, ValueError, TypeError) as e:
        raise ProbeProtocolError(f"{url}: not a light set: {e}", url) from e


def _read_exr_bytes(data: bytes, url: str) -> np.ndarray:
    from lightprobe.core.imageio import read_hdr_image

    fd, tmp = tempfile.mkstemp(suffix=".exr")
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
        return read_hdr_image(tmp)
    except InputError as e:
        raise ProbeProtocolError(f"{url}: not a readable EXR: {e}", url) from e
    finally:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
