"""The producers of the host formats, computed alike by the probe (the routes, the stream) and
by a host from an offline map (``lightprobe export``, host relighting): order-2 SH and the primary
light (:mod:`.sh_primary`, :mod:`.primary`, on :mod:`.bright_regions`), the SG fit
(:mod:`.sgfit`), GGX-prefiltered cube maps (:mod:`.cubemap`) and glTF 2.0 / USD scene files
(:mod:`.scene`). Their conventions and wire types are the base layer's (:mod:`lightprobe.core.sh`,
:mod:`lightprobe.core.sg`, :mod:`lightprobe.core.ktx2`, :mod:`lightprobe.core.scene_files`).
This package imports only the base layer.
"""
