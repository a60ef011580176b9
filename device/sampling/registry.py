"""Sampler registry: ``make_sampler(name, **params)`` builds any sampler by its CLI name.

Modules are imported lazily so that importing the registry costs nothing and a sampler under
construction (``q2tree``) cannot break the others.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from .base import Sampler

__all__ = ["SAMPLERS", "available_samplers", "make_sampler"]

def _pharr() -> type:
    from .pharr import PharrSampler

    return PharrSampler


def _hemigon() -> type:
    from .hemigon import HemigonSampler

    return HemigonSampler


def _median_cut() -> type:
    from .median_cut import MedianCutSampler

    return MedianCutSampler


def _q2tree() -> type:
    from .q2tree import Q2TreeSampler

    return Q2TreeSampler


# CLI name -> the sampler's class, imported when first asked for
SAMPLERS: dict[str, Callable[[], type]] = {
    "pharr": _pharr,
    "hemigon": _hemigon,
    "median-cut": _median_cut,
    "q2tree": _q2tree,
}


def _load(name: str) -> type:
    if name not in SAMPLERS:
        raise KeyError(f"unknown sampler {name!r} (known: {', '.join(sorted(SAMPLERS))})")
    return SAMPLERS[name]()


def available_samplers() -> list[str]:
    """Names whose module imports and defines the class (q2tree may not exist yet)."""
    out = []
    for name in SAMPLERS:
        try:
            _load(name)
        except (ImportError, AttributeError):
            continue
        out.append(name)
    return out


def make_sampler(name: str, **params: Any) -> Sampler:
    """A new sampler ``name`` (``pharr``, ``hemigon``, ``median-cut``, ``q2tree``) with ``params``.

    Raises ``KeyError`` for an unknown name, ``ImportError`` when its module is not available.
    """
    cls = _load(name)
    return cls(**params)  # type: ignore[no-any-return]
