"""The base layer: what the probe and host applications share, importing nothing above it.

- :mod:`.errors` (``InputError``, ``LightprobeError``) and :mod:`.command` (exit codes);
- :mod:`.sphere` (the probe frame, directions, exact equirect solid angles, the one set of
  luminance weights) and :mod:`.healpix` (NESTED HEALPix, our own);
- the wire types hosts read: :mod:`.lightset` (the light-set type of CONVENTIONS.md),
  :mod:`.sh` (the SH basis, each engine's convention, the ``/sh`` body), :mod:`.sg` (SG lobes,
  the ``/sg`` body), :mod:`.q2wire` (the Q2-Tree wire format and node arithmetic), :mod:`.ktx2`
  (KTX2 cube maps), :mod:`.scene_files` (glTF / USD bundles);
- the contracts with hosts: :mod:`.mdns_txt` (DNS-SD TXT keys) and :mod:`.mqtt_topics` (topics
  and payloads);
- :mod:`.calibration` (the calibration file's model, the one response repair rule);
- :mod:`.imageio` (EXR / Radiance HDR), :mod:`.fsutil` (atomic writes), :mod:`.statelock` (the
  state directory's lock).

Importing this package imports none of its modules; at import they need numpy at most (OpenEXR
and cv2 only inside the image readers and writers), so ``import lightprobe.hostlink`` stays
cheap (``tests/test_layers.py`` holds it to that).
"""
