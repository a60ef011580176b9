"""The SG relighting's settings: the cone layout and the ray and table budgets the method's
description (:mod:`.relighter`) argues for."""

from __future__ import annotations

import math

__all__ = ["CONE_HALF", "DIFFUSE_CONES", "DIFFUSE_GRID", "LAM_CONE", "PEAK0", "PEAK_RAYS", "RADIANCE_GRID", "RAYS_PER_CONE", "RAYS_PER_PEAK", "RECT_RAYS", "REFLECTION", "RESIDUAL_RAYS", "THIN_PEAK_VOXELS", "ZONAL_SAMPLES"]

DIFFUSE_CONES = 20         # the residual's cones, cosine-distributed over the hemisphere


CONE_HALF = math.acos(1.0 - 1.0 / DIFFUSE_CONES)   # equal caps: together the hemisphere's solid angle


LAM_CONE = math.log(2.0) / (1.0 - math.cos(CONE_HALF))          # paper eq. 5-6 inverted


REFLECTION = DIFFUSE_CONES       # the cone layout: diffuse cones, the reflection cone, the peaks


PEAK0 = DIFFUSE_CONES + 1


RECT_RAYS = 32             # rays per cone against the rectangles (exact occluders, not voxels)


RADIANCE_GRID = 17         # cube-face side of the residual radiance table (ray weights)


DIFFUSE_GRID = 13          # cube-face side of the diffuse tables (smooth kernels: ~7 deg texels)


ZONAL_SAMPLES = 1025


RAYS_PER_CONE = 16         # rays uniform within the reflection cone, with rays


RESIDUAL_RAYS = 112        # cosine-distributed rays for the residual's visibility, with rays


RAYS_PER_PEAK = 32


THIN_PEAK_VOXELS = 2.0     # peaks narrower than this across the grid: one shadow ray each


PEAK_RAYS = 8              # rays per broader peak, with voxels (drawn from the lobe)
