"""Relighting the real room (Loscos et al. 1999): reflectance from photographs of the room under
known lights, then the room rendered under other lights. Importing this package does nothing;
the command is ``lightprobe room``.

Modules along the method's steps: :mod:`.io` (the room folder's files), :mod:`.item_buffer`
(patches, the camera's raster of them, footprints), :mod:`.radiosity` (direct light and the
radiosity solve), :mod:`.recovery` (reflectance and its filters), :mod:`.alignment` (snapping,
objects moved where the captures put them), :mod:`.rendering` (the room under other lights,
virtual objects, removals); :mod:`.room` (:class:`~.room.Room`, the front: what it does and
leaves out), :mod:`.settings`, :mod:`.kernels` (numba), :mod:`.probes` (lamps placed from the
probes' SG peaks).
"""
