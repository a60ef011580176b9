"""Host relighting with visibility cuts (Iwasaki et al.): SVC / VCF precomputation with Embree,
height-coded cuts, counter-based multi-cut traversal, dynamic lights, BRDFs, views and moving
(translated and rotated) rigid objects. Importing this package does nothing; see ``cli.py`` for
the command.

Modules: ``directions`` (2^15 directions, depth-15 tree), ``cuts`` (selection, coding, products,
interpolation), ``scene`` (scene JSON, OBJ), ``precompute`` (SVC, VCF, disk cache), ``lighting``
(per-cluster light integrals: prefix sums and the per-node table), ``kernels`` (numba shading:
BRDFs, static SVC shading, counter-based dynamic shading, brute force), ``occlusion`` (shadows
of movable objects from their VCFs), ``raster`` (ID buffer, image resolve, tone map), ``render``
(run-time state and caches), ``reference`` (brute force), ``live`` (WebSocket re-rendering),
``cli``.
"""
