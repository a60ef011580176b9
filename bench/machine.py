"""The machine a benchmark ran on, as every result file records it (CPU model, cores, Python, date)."""

from __future__ import annotations

import platform
import time
from pathlib import Path

__all__ = ['machine_info']


def machine_info() -> dict[str, object]:
    import os

    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return {"cpu": cpu, "cores": os.cpu_count(), "python": platform.python_version(),
            "machine": platform.machine(), "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())}

