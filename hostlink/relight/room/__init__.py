"""Relighting the real room (Loscos et al. 1999): reflectance from photographs of the room under
known lights, then the room rendered under other lights. Importing this package does nothing;
the command is ``lightprobe room``.

:class:`~.room.Room` is the front (:mod:`.room`: what the method does and leaves out); it is
built of the method's steps, each a class that extends the one before: :mod:`.model`
(``RoomModel``: patches, the item buffer, each lamp's direct light), :mod:`.radiosity`
(``RoomRadiosity``: form factors, the radiosity solve), :mod:`.recovery` (``RoomRecovery``:
reflectance, its filters, the pixels' snapping), then :mod:`.alignment` (``RoomAlignment``:
objects moved where the captures put them) and :mod:`.rendering` (``RoomRendering``: the room
under other lights, virtual objects, removals). Beside them: :mod:`.io` (the room folder's
files), :mod:`.item_buffer` (patches, rasters, footprints, fills), :mod:`.settings`,
:mod:`.kernels` (numba), :mod:`.probes` (lamps placed from the probes' SG peaks).
"""
