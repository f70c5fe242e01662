"""Warp initialised for a command line: quiet unless asked.

Warp's native library prints "Warp CUDA warning: Could not find or load the NVIDIA CUDA driver" with fprintf on
every machine without a GPU, whatever Python's logging says, so no error could ever be one line. The line is
dropped unless CUDA was asked for (where it explains a failure) or --verbose; everything else the library writes
while it starts is passed through.
"""
from __future__ import annotations

import contextlib
import ctypes
import os
import sys
import tempfile

NO_DRIVER = "Warp CUDA warning: Could not find or load the NVIDIA CUDA driver."


@contextlib.contextmanager
def _native_stderr_without(drop: tuple[str, ...]):
    """fd 2 goes to a temporary file for the block, then every line but `drop` is written back: this catches what
    the native library writes with fprintf, which Python's stderr never sees."""
    try:
        sys.stderr.flush()
        saved = os.dup(2)
        tmp = tempfile.TemporaryFile()
    except (OSError, ValueError, AttributeError):  # no fd 2 or no temporary folder: run unfiltered
        yield
        return
    with tmp:
        os.dup2(tmp.fileno(), 2)
        try:
            yield
        finally:
            with contextlib.suppress(Exception):
                ctypes.CDLL(None).fflush(None)
            os.dup2(saved, 2)
            os.close(saved)
            tmp.seek(0)
            rest = "".join(line for line in tmp.read().decode("utf-8", "replace").splitlines(True)
                           if not line.startswith(drop))
            if rest:
                sys.stderr.write(rest)
                sys.stderr.flush()


_STATE = {"initialised": False}


def init_warp(device: str = "cpu", verbose: bool = False):
    """wp.init() with Warp's banner and module-load lines only when verbose, and the missing-driver line only when
    CUDA was asked for or verbose. Warp initialises once per process; later calls change nothing."""
    import warp as wp

    if _STATE["initialised"]:  # a later call (a command asking for its device) keeps the first call's verbosity
        return wp
    _STATE["initialised"] = True
    wp.config.log_level = wp.LOG_INFO if verbose else wp.LOG_WARNING
    wp.config.verbose = bool(verbose)
    if verbose or str(device).startswith("cuda"):
        wp.init()
    else:
        with _native_stderr_without((NO_DRIVER,)):
            wp.init()
    return wp
