import os

os.environ.setdefault("RERUN_ANALYTICS", "0")
os.environ.setdefault("WARP_CACHE_PATH", os.path.join(os.path.expanduser("~"), ".cache", "warp"))

import warp as wp  # noqa: E402

wp.config.log_level = wp.LOG_ERROR
