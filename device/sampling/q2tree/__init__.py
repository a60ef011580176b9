"""Spherical Q2-Tree sampler (Wan, Wong, Leung 2005) with incremental split-merge.

``Q2TreeSampler`` is the public class (``make_sampler("q2tree", ...)``); ``nodes_to_uniq`` /
``uniq_to_nodes`` convert between (level, NESTED index) leaf arrays and light ids (HEALPix NUNIQ); they are
defined with the wire format in :mod:`lightprobe.core.q2wire`.
"""

from lightprobe.core.q2wire import nodes_to_uniq, uniq_to_nodes

from .sampler import MAX_NSIDE, Q2TreeSampler, auto_nside

__all__ = ["MAX_NSIDE", "Q2TreeSampler", "auto_nside", "nodes_to_uniq", "uniq_to_nodes"]
