"""The room relighting's settings: the choices the method's description (:mod:`.room`) names."""

from __future__ import annotations

__all__ = ["ALIGN_BOUND", "ALIGN_GAIN", "ALIGN_STEPS", "ALIGN_STEP_GAIN", "ALIGN_WIDTH", "DOUBT", "INDIRECT", "OUTLIER", "SNAP_CAP", "SNAP_GAIN", "SNAP_MIN", "SNAP_RADIUS", "SUBPIXEL"]

INDIRECT = ("radiosity", "ambient", "none")   # Room.recover's indirect terms


DOUBT = 0.5            # a pixel under this fraction of its surface's median confidence is blended with its surroundings


SNAP_RADIUS = 2        # a pixel may take the geometry of a pixel this many pixels away ...


SNAP_GAIN = 0.5        # ... whose shading explains its captures this much better (misfit ratio) ...


SNAP_MIN = 0.02        # ... when its own misfit is over this (relative, squared: 14% rms)


SNAP_CAP = 0.2         # a pixel's misfit counts at most this much in an alignment's score


ALIGN_WIDTH = 160      # an alignment scores its candidates at most this many pixels wide


ALIGN_BOUND = 0.02     # objects move at most this share of the room's largest extent (the paper's modelling error) ...


ALIGN_STEPS = (0.75, 0.375, 0.1875, 0.09375)   # ... in steps of these shares of that bound ...


ALIGN_STEP_GAIN = 0.01     # ... each kept when it lowers the captures' misfit by this share of the model's own ...


ALIGN_GAIN = 0.95      # ... and the whole alignment only when it ends below this share of it


OUTLIER = 0.3          # a capture's reflectance further than this fraction from the median is rejected


SUBPIXEL = 3           # s x s samples over a pixel whose footprint crosses an edge
