"""The base layer: what the probe and host applications share, importing nothing above it.

- :mod:`.errors` (``InputError``, ``LightprobeError``) and :mod:`.command` (exit codes);
- :mod:`.sphere` (the probe frame, directions, exact equirect solid angles, the one set of
  luminance weights) and :mod:`.healpix` (NESTED HEALPix, our own);
- :mod:`.lightset` (the light-set type of CONVENTIONS.md) and :mod:`.q2wire` (the Q2-Tree wire
  format and node arithmetic);
- :mod:`.calibration` (the calibration file's model, the one response repair rule);
- :mod:`.imageio` (EXR / Radiance HDR) and :mod:`.fsutil` (atomic writes).

Importing this package imports none of its modules; they need numpy at most (cv2 only inside
the Radiance ``.hdr`` reader), so ``import hostlink`` stays cheap.
"""
