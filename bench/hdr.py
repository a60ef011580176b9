"""``lightprobe bench hdr``: fusion accuracy and speed against OpenCV MergeDebevec."""

from device.hdr.benchmark import run

__all__ = ["run"]
