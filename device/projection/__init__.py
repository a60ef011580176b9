"""Fisheye radiance image -> hemisphere polar map, full equirect map and NESTED HEALPix map.

Tables are built once from a :class:`lightprobe.core.calibration.Calibration`; a frame is then one sparse
matrix-vector product per map (float32, three channels, numba CSR kernel).

Conservative (area-correct) remapping
-------------------------------------
Every valid fisheye pixel ``i`` (camera polar angle of its centre <= ``fov_deg / 2 -
ring_margin_deg``, and inside the calibration's clean-circle ``mask`` when present) is split into
``s x s`` subpixels (``subdiv``, 4). The subpixel corners are unprojected through the KB4 model
(``FisheyeModel``) and rotated to the probe frame with ``lightprobe.core.sphere.CAMERA_TO_PROBE``; a
subpixel's solid angle is that of its spherical quadrilateral (two triangles, Van Oosterom &
Strackee 1983, eq. (VOS)). It is binned into output pixels with a 5-point rule (1/2 at its centre,
1/8 at each corner; the corners make thin slivers of overlap get an entry)::

    W[j, i] = solid angle of the subpixels of i that fall into output pixel j       (O)

so the columns of ``W`` sum to the fisheye pixel solid angles ``Omega_i`` exactly. Output pixels
that receive nothing although their centre is seen (tiny polar-cap pixels near the zenith) get a
*gather* row: bilinear weights at the pixel centre times ``Omega_j`` (hole-free fallback).

The point quadrature leaves row sums a few percent off ``Omega_j``. ``W`` is therefore balanced
(over-relaxed iterative proportional fitting, :func:`tables._balance`) so that every *interior*
output pixel (all of it inside the valid region) gets row sum ``Omega_j`` to ~1e-4 while every
column keeps its total exactly: each fisheye pixel's energy (radiance x solid angle) is handed out
once, also through the gather rows. Rows on the rim are free; their row sum ``A_j`` is the
covered solid angle and ``coverage_j = min(A_j / Omega_j, 1)`` (interior: 1).

Per frame, ``L_j = sum_i W[j, i] g_i L_i / A_j`` (eq. (P), ``A_j`` = the balanced row sum), with
the gain ``g_i = scale / V_i`` folding in 1/vignetting and the photometric scale. A constant image
gives an exactly constant map where seen; a partly covered pixel holds the mean radiance of its
seen part; and ``sum_j Omega_j coverage_j L_j = sum_i Omega_i g_i L_i`` (energy, eq. (E)) to the
balancing residual (``Projector.balance_residual``, ~1e-4).

Invalid pixels (``valid`` mask False, NaN or Inf) are dropped per frame and each output pixel is
renormalised over its valid contributions (a second kernel that runs only when needed); an output
pixel with no valid contribution is 0. Outputs are never NaN.

Lower hemisphere of the equirect map (``lower=``): the lens sees a thin band below the horizon
(fov ~185 deg); partly covered pixels are blended ``c L_seen + (1 - c) L_fill`` with

* ``"zero"`` (default): ``L_fill = 0`` (the map's integral is exactly the energy seen);
* ``"mirror"``: ``L_fill(theta, phi) = ground_albedo x L(pi - theta, phi)`` (upper hemisphere
  reflected by a grey ground);
* ``"mean-horizon"``: ``L_fill`` = mean radiance of the lowest fully covered band
  (``horizon_band_deg`` high), the same for every azimuth.

The calibration's pose is not applied: all maps are in the probe frame. Building the tables takes
seconds (VGA: ~5-10 s on the 2-core box, more under load); they are memoised per calibration id
and geometry parameters (``cache=True``), read-only and shared.

Layout: ``geometry`` (unprojection, subpixels, grids), ``tables`` (eq. O, gather, balancing,
eq. P), ``kernels`` (numba CSR x RGB), ``projector`` (:class:`Projector`, :class:`ProbeMaps`).

Dtype policy: geometry and table construction in float64; tables, images and maps float32;
per-pixel accumulation in the kernels is float64.

References
----------
Van Oosterom, A. & Strackee, J. 1983, "The solid angle of a plane triangle", IEEE Trans. Biomed.
Eng. 30(2), eq. (VOS): tan(Omega/2) = |a.(b x c)| / (1 + a.b + b.c + c.a).
Jones, P. 1999, "First- and second-order conservative remapping schemes for grids in spherical
coordinates", Mon. Wea. Rev. 127 (first-order conservative remapping, eq. (O)).
Bishop, Fienberg & Holland 1975, "Discrete Multivariate Analysis" (iterative proportional fitting).
"""

from __future__ import annotations

from .geometry import (
    fisheye_pixel_directions,
    fisheye_pixel_solid_angles,
    fisheye_valid_mask,
    spherical_triangle_solid_angle,
)
from .projector import LOWER_POLICIES, LowerPolicy, ProbeMaps, Projector
from .tables import sample_sharing

__all__ = [
    "LOWER_POLICIES",
    "LowerPolicy",
    "ProbeMaps",
    "Projector",
    "fisheye_pixel_directions",
    "fisheye_pixel_solid_angles",
    "fisheye_valid_mask",
    "sample_sharing",
    "spherical_triangle_solid_angle",
]
