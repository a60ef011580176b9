"""What host engines consume that is built from the map's pixels: GGX-prefiltered cube maps
(:mod:`.cubemap`, written as KTX2 by :mod:`device.core.ktx2`), glTF 2.0 and USD scene files
(:mod:`.scene`) and the ``lightprobe export`` command (:mod:`.cli`).

The per-frame lighting hosts read (order-2 SH in each engine's convention and the primary light:
:mod:`device.core.sh`, :mod:`device.core.primary`, :mod:`device.core.environment`) lives in the
base layer, because hosts compute the same from offline maps (``hostlink.formats``).
"""
