"""hostlink: find lightprobe units, follow their lights, merge several probes for host renderers.

The public, typed surface (everything else is internal)::

    from hostlink import Discovery, ProbeClient, MergedStream, merge_q2trees

- :class:`Discovery` (``hostlink.discovery``): mDNS browsing of ``_lightprobe._tcp`` keyed by the
  TXT ``id``, plus manual ``host:port`` addresses.
- :class:`ProbeClient` (``hostlink.client``): status, light sets, HDR map, Q2-Tree, WebSocket
  subscription with reconnect/backoff; typed errors :class:`ProbeError` and subclasses.
- :mod:`hostlink.merge`: Nikodym et al. 2013 Algorithm 2 (:func:`merge_q2trees`), index
  interpolation (:func:`merge_indexed`), distance weights (:func:`probe_weights`),
  :func:`merge_probes` with failed probes dropping out.
- :mod:`device.core.q2wire`: the compact binary Q2-Tree encoding (:func:`encode_q2tree`,
  :func:`decode_q2tree`, :class:`Q2DecodeError`).
- :class:`MergedStream` (``hostlink.stream``): a live merged stream over several probes.

Importing ``hostlink`` is cheap: names resolve lazily on first use (PEP 562).
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from device.core.q2wire import Q2DecodeError, Q2Tree, decode_q2tree, encode_q2tree
    from hostlink.client import (
        ProbeAuthError,
        ProbeClient,
        ProbeError,
        ProbeProtocolError,
        ProbeRequestError,
        ProbeUnavailable,
    )
    from hostlink.discovery import Discovery, ProbeEvent, ProbeInfo
    from hostlink.merge import (
        MergeError,
        ProbeInput,
        merge_indexed,
        merge_probes,
        merge_q2trees,
        probe_weights,
    )
    from hostlink.stream import MergedStream

_EXPORTS = {
    "Discovery": "hostlink.discovery",
    "ProbeEvent": "hostlink.discovery",
    "ProbeInfo": "hostlink.discovery",
    "ProbeAuthError": "hostlink.client",
    "ProbeClient": "hostlink.client",
    "ProbeError": "hostlink.client",
    "ProbeProtocolError": "hostlink.client",
    "ProbeRequestError": "hostlink.client",
    "ProbeUnavailable": "hostlink.client",
    "MergeError": "hostlink.merge",
    "ProbeInput": "hostlink.merge",
    "merge_indexed": "hostlink.merge",
    "merge_probes": "hostlink.merge",
    "merge_q2trees": "hostlink.merge",
    "probe_weights": "hostlink.merge",
    "Q2DecodeError": "device.core.q2wire",
    "Q2Tree": "device.core.q2wire",
    "decode_q2tree": "device.core.q2wire",
    "encode_q2tree": "device.core.q2wire",
    "MergedStream": "hostlink.stream",
}

__all__ = [
    "Discovery",
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
        raise AttributeError(f"module 'hostlink' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
