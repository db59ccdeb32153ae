"""This machine as benchmark figures name it: its CPU model and the cores this process may use."""
from __future__ import annotations

import os
import platform
from pathlib import Path


def cpu_model(unknown: str = "unknown") -> str:
    """The CPU's model name (/proc/cpuinfo), else what platform knows, else ``unknown``."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or unknown


def usable_cores() -> int:
    """The cores this process may run on (its affinity where the OS tells it), at least 1."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:
        return max(1, os.cpu_count() or 1)
