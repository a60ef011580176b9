"""The simulated lightprobe: a fisheye camera with ground truth, implementing lightprobe.drivers.base.Camera.

Public API::

    from lightprobe.sim.camera import SimCamera          # the Camera (open/apply/capture, truth_calibration)
    from lightprobe.sim.scenarios import load_scene      # "room", "flashlight", "flicker", "switch",
                                              # "swing", "daylight", or any equirect path
    from lightprobe.sim.scene import Scene, DynamicLight # radiance over the sphere, area-correct lights
    from lightprobe.sim.lens import make_lens            # KB4 fisheye, vignetting, housing ring, render matrix
    from lightprobe.sim.optics import Kb4Lens, MOUNT     # its own lens, mounting and sphere conventions
    from lightprobe.sim.sensor import SensorModel        # shot/read noise, response curve, 8-bit / raw
    from lightprobe.sim.faults import FaultPlan          # camera.faults.inject("disconnect", duration_s=0.5)

Typical use::

    cam = SimCamera("flashlight", seed=1)
    async with cam:
        await cam.apply(Controls(exposure_s=1e-3))
        frame = await cam.capture()
    cal = cam.truth_calibration()             # fused value x cal.photometric.scale == radiance
    truth = cam.truth_radiance(cam.scene_time(frame.meta.timestamp_s))

The simulator is its own implementation: its lens, vignetting, mounting and response are written
from the documents (CONVENTIONS.md, NOTES.md), not imported from the probe, and its truth
calibration is those models written in the calibration file's schema
(``tests/test_independence.py``).

Importing this package does nothing (no files read, no threads).
"""
