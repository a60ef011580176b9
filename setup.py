"""The package map: every top-level folder of the repository is one subpackage of ``lightprobe``.

The folders stay where the product put them (``core/``, ``device/``, ``drivers/``, ...); the
wheel holds them as ``lightprobe/core/``, ``lightprobe/device/``, ... (``lightprobe`` itself is a namespace: it
has no module of its own). Everything else is in ``pyproject.toml``.
"""

from setuptools import find_packages, setup

# bottom to top (tests/test_layers.py holds the rules between them)
FOLDERS = ("core", "drivers", "calibration", "device", "sim", "hostlink", "bench", "cli")

setup(
    packages=[f"lightprobe.{p}" for p in find_packages(include=[f"{f}*" for f in FOLDERS])
              if p.split(".")[0] in FOLDERS],
    package_dir={f"lightprobe.{f}": f for f in FOLDERS},
)
