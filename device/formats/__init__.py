"""What host engines consume, derived from the probe's map: order-2 SH in each engine's
convention (:mod:`.sh`), the primary light (:mod:`.primary`), GGX-prefiltered cubemaps
(:mod:`.cubemap`, :mod:`.ktx2`) and scene files (:mod:`.scene`: glTF 2.0 and USD).

Layering: reads the map a frame publishes (``device.core``, ``device.sampling.peaks``); nothing
below the publication stage imports it.
"""
