"""Sampler registry: ``make_sampler(name, **params)`` builds any sampler by its CLI name.

Modules are imported lazily so that importing the registry costs nothing and a sampler under
construction (``q2tree``) cannot break the others.
"""

from __future__ import annotations

import importlib
from typing import Any

from .base import Sampler

__all__ = ["SAMPLERS", "available_samplers", "make_sampler"]

# CLI name -> (module, class name)
SAMPLERS: dict[str, tuple[str, str]] = {
    "pharr": ("device.sampling.pharr", "PharrSampler"),
    "hemigon": ("device.sampling.hemigon", "HemigonSampler"),
    "median-cut": ("device.sampling.median_cut", "MedianCutSampler"),
    "q2tree": ("device.sampling.q2tree", "Q2TreeSampler"),
}


def _load(name: str) -> type:
    if name not in SAMPLERS:
        raise KeyError(f"unknown sampler {name!r} (known: {', '.join(sorted(SAMPLERS))})")
    module_name, cls_name = SAMPLERS[name]
    module = importlib.import_module(module_name)
    return getattr(module, cls_name)  # type: ignore[no-any-return]


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
