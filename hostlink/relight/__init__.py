"""Host relighting with visibility cuts (Iwasaki et al.): SVC / VCF precomputation with Embree,
height-coded cuts, counter-based multi-cut traversal, dynamic lights, BRDFs, views and moving
(translated) rigid objects. Importing this package does nothing; see ``cli.py`` for the command.

Modules: ``directions`` (2^15 directions, depth-15 tree), ``cuts`` (selection, coding, products,
interpolation), ``scene`` (scene JSON, OBJ), ``precompute`` (SVC, VCF, disk cache), ``lighting``
(per-cluster light integrals), ``kernels`` (numba shading), ``render`` (run-time state, rasteriser),
``reference`` (brute force), ``live`` (WebSocket re-rendering), ``cli``.
"""
