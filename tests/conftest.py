import os

os.environ.setdefault("RERUN_ANALYTICS", "0")

import warp as wp  # noqa: E402

wp.config.log_level = wp.LOG_ERROR
