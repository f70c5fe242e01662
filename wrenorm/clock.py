"""How long this process has been running: start-up costs are measured from the process's birth, not from when
wrenorm's code first ran (interpreter and imports count)."""
from __future__ import annotations

import os
import time

_IMPORTED = time.time()


def process_age() -> float:
    """Seconds since this process started (Linux /proc), else since this module was imported."""
    try:
        with open(f"/proc/{os.getpid()}/stat") as f:
            start_ticks = float(f.read().rsplit(")", 1)[1].split()[19])
        with open("/proc/uptime") as f:
            uptime = float(f.read().split()[0])
        return uptime - start_ticks / os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError, IndexError):
        return time.time() - _IMPORTED
