import os

os.environ.setdefault("RERUN_ANALYTICS", "0")
# Detected events are cached by file content (tasks/rope/reference/events.py); tests keep theirs apart from the
# user's cache so a stale entry can never hide a detector change.
if "WRENORM_CACHE" not in os.environ:
    import tempfile

    os.environ["WRENORM_CACHE"] = tempfile.mkdtemp(prefix="wrenorm-test-cache-")

import warp as wp  # noqa: E402

wp.config.log_level = wp.LOG_ERROR
