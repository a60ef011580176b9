"""Relighting the real room (Loscos et al. 1999): reflectance from photographs of the room under
known lights, then the room rendered under other lights. See :mod:`hostlink.room.room`; the
command is ``lightprobe room``. Importing this package does nothing.
"""
