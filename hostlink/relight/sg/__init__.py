"""Relighting with spherical Gaussians (Michiels, Put, Bekaert 2015): no precompute, so meshes may
move or deform every frame. Importing this package does nothing.

Modules: :mod:`.relighter` (:class:`~.relighter.SGRelighter`, the front: lighting, objects,
shading, rendering; the method's choices in its docstring), :mod:`.visibility` (voxels,
rectangles and rays for the cones and peaks), :mod:`.tables` (kernels over the sphere and the
lighting's direction tables), :mod:`.settings` (the cone layout, ray and table budgets),
:mod:`.kernels` (the numba kernels).
"""
