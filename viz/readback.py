"""Read a recording back (for tests and checks): which entities does it hold?"""
from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path


def entity_paths(rrd: str | Path) -> set[str]:
    """Entity paths of every chunk in `rrd`, via the rerun CLI shipped with rerun-sdk."""
    env = dict(os.environ, RERUN_ANALYTICS="0")
    out = subprocess.run([sys.executable, "-m", "rerun", "rrd", "print", str(rrd)], capture_output=True, text=True,
                         env=env, check=True, timeout=120).stdout
    return {m.replace("\\", "") for m in re.findall(r" - (/\S+) - data columns", out)}
