"""Relighting with spherical Gaussians (Michiels, Put, Bekaert 2015): no precompute, so meshes may
move or deform every frame. Importing this package does nothing.

:class:`~.relighter.SGRelighter` (:mod:`.relighter`: the lighting, shading and rendering; the
method's choices in its docstring) extends :class:`~.visibility.SGVisibility` (cones through
voxels and rectangles, or rays; the peaks' shadow rays), which extends
:class:`~.objects.SGScene` (materials, objects, poses, shapes, the voxel grid). Beside them:
:mod:`.tables` (kernels over the sphere, the lighting's direction tables), :mod:`.settings`
(the cone layout, ray and table budgets), :mod:`.kernels` (numba).
"""
