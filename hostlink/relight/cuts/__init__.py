"""Relighting with visibility cuts (Iwasaki et al.): SVC / VCF precomputation with Embree,
height-coded cuts, counter-based multi-cut traversal, dynamic lights, BRDFs, views and moving
(translated and rotated) rigid objects. Importing this package does nothing.

Modules: :mod:`.directions` (2^15 directions, depth-15 tree), :mod:`.coding` (cut selection,
coding, products, interpolation), :mod:`.precompute` (SVC, VCF, disk cache), :mod:`.cluster`
(the precompute's chunks on a Dask cluster), :mod:`.lighting` (per-cluster light integrals:
prefix sums and the per-node table), :mod:`.kernels` (numba shading: BRDFs, static SVC shading,
counter-based dynamic shading, brute force), :mod:`.occlusion` (shadows of movable objects from
their VCFs), :mod:`.render` (run-time state and caches), :mod:`.reference` (brute force),
:mod:`.live` (WebSocket re-rendering).
"""
