"""lightprobe.hostlink: find lightprobe units, follow their lights, merge several probes for host renderers.

The public, typed surface (everything else is internal)::

    from lightprobe.hostlink import Discovery, ProbeClient, MergedStream, merge_q2trees

- :class:`Discovery` (``lightprobe.hostlink.discovery``): mDNS browsing of ``_lightprobe._tcp`` keyed by the
  TXT ``id``, plus manual ``host:port`` addresses.
- :class:`ProbeClient` (``lightprobe.hostlink.client``): status, light sets, HDR map, Q2-Tree, WebSocket
  subscription with reconnect/backoff; typed errors :class:`ProbeError` and subclasses.
- :mod:`lightprobe.hostlink.merge`: Nikodym et al. 2013 Algorithm 2 (:func:`merge_q2trees`), index
  interpolation (:func:`merge_indexed`), distance weights (:func:`probe_weights`),
  :func:`merge_probes` with failed probes dropping out.
- :mod:`lightprobe.core.q2wire`: the compact binary Q2-Tree encoding (:func:`encode_q2tree`,
  :func:`decode_q2tree`, :class:`Q2DecodeError`).
- :class:`MergedStream` (``lightprobe.hostlink.stream``): a live merged stream over several probes.
- The host formats' types (from the base layer): :class:`SHLighting` (``GET /sh``),
  :class:`CubeMap` (a decoded ``cubemap.ktx2``), :class:`EnvironmentFiles` (glTF / USD bundles).

Importing ``lightprobe.hostlink`` is cheap: names resolve lazily on first use (PEP 562).
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from lightprobe.core.ktx2 import CubeMap
    from lightprobe.core.q2wire import Q2DecodeError, Q2Tree, decode_q2tree, encode_q2tree
    from lightprobe.core.scene_files import EnvironmentFiles
    from lightprobe.core.sh import SHLighting
    from lightprobe.hostlink.client import (
        ProbeAuthError,
        ProbeClient,
        ProbeError,
        ProbeProtocolError,
        ProbeRequestError,
        ProbeUnavailable,
    )
    from lightprobe.hostlink.discovery import Discovery, ProbeEvent, ProbeInfo
    from lightprobe.hostlink.merge import (
        MergeError,
        ProbeInput,
        merge_indexed,
        merge_probes,
        merge_q2trees,
        probe_weights,
    )
    from lightprobe.hostlink.stream import MergedStream

_EXPORTS = {
    "Discovery": "lightprobe.hostlink.discovery",
    "ProbeEvent": "lightprobe.hostlink.discovery",
    "ProbeInfo": "lightprobe.hostlink.discovery",
    "ProbeAuthError": "lightprobe.hostlink.client",
    "ProbeClient": "lightprobe.hostlink.client",
    "ProbeError": "lightprobe.hostlink.client",
    "ProbeProtocolError": "lightprobe.hostlink.client",
    "ProbeRequestError": "lightprobe.hostlink.client",
    "ProbeUnavailable": "lightprobe.hostlink.client",
    "MergeError": "lightprobe.hostlink.merge",
    "ProbeInput": "lightprobe.hostlink.merge",
    "merge_indexed": "lightprobe.hostlink.merge",
    "merge_probes": "lightprobe.hostlink.merge",
    "merge_q2trees": "lightprobe.hostlink.merge",
    "probe_weights": "lightprobe.hostlink.merge",
    "Q2DecodeError": "lightprobe.core.q2wire",
    "Q2Tree": "lightprobe.core.q2wire",
    "decode_q2tree": "lightprobe.core.q2wire",
    "encode_q2tree": "lightprobe.core.q2wire",
    "MergedStream": "lightprobe.hostlink.stream",
    "SHLighting": "lightprobe.core.sh",
    "CubeMap": "lightprobe.core.ktx2",
    "EnvironmentFiles": "lightprobe.core.scene_files",
}

__all__ = [
    "CubeMap",
    "Discovery",
    "EnvironmentFiles",
    "MergeError",
    "MergedStream",
    "ProbeAuthError",
    "ProbeClient",
    "ProbeError",
    "ProbeEvent",
    "ProbeInfo",
    "ProbeInput",
    "ProbeProtocolError",
    "ProbeRequestError",
    "ProbeUnavailable",
    "Q2DecodeError",
    "Q2Tree",
    "SHLighting",
    "decode_q2tree",
    "encode_q2tree",
    "merge_indexed",
    "merge_probes",
    "merge_q2trees",
    "probe_weights",
]


def __getattr__(name: str) -> Any:
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module 'lightprobe.hostlink' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
