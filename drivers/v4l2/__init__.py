"""V4L2 backend: our own ctypes ioctl layer (no linuxpy: GPL), mmap streaming, settling rule.

``V4L2Camera`` is the camera; ``_structs`` holds the videodev2.h layouts for LP64 and ARM EABI
ILP32, ``_ioctl`` the transport seam, ``fake`` a simulated UVC webcam behind that seam for tests.
Importing this package does nothing.
"""

from .camera import V4L2Camera

__all__ = ["V4L2Camera"]
