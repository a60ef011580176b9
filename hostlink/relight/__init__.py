"""Host relighting: 3D scenes lit by the probes' lights, one subpackage per method over a
shared part. Importing this package does nothing; the commands are ``lightprobe relight`` and
``lightprobe room`` (:mod:`lightprobe.cli.relight`, :mod:`lightprobe.cli.room`).

Shared: :mod:`.scene` (scene JSON, OBJ, cameras, materials), :mod:`.raster` (ID buffer, image
resolve, tone map, image files), :mod:`.rays` (Embree scenes of meshes, occlusion queries, ray
offsets).

Methods:

- :mod:`.cuts`: visibility cuts (Iwasaki et al.), precomputed per scene, rigid objects that move
  and turn;
- :mod:`.sg`: spherical Gaussians (Michiels et al. 2015), no precompute, meshes that deform;
- :mod:`.room`: the real, photographed room (Loscos et al. 1999), its reflectance recovered and
  rendered under other lights.
"""
