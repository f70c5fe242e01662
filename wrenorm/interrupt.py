"""Ctrl-C that always works: the first one raises KeyboardInterrupt as usual and starts a one-second watchdog;
if the interrupt was swallowed (Python drops exceptions raised inside a finalizer, which Warp and numpy run at
any time) or the work does not reach a point where it can stop, the watchdog ends the process with exit code
130. State written so far is complete: every write is atomic (temp file + rename)."""
from __future__ import annotations

import os
import signal
import sys
import threading

EXIT_CODE = 130
GRACE_S = 1.0
_state = {"hint": ""}


def _watchdog():
    try:
        sys.stderr.write(f"\nwrenorm: interrupted{_state['hint']}\n")
        sys.stderr.flush()
    finally:
        os._exit(EXIT_CODE)


def _handler(signum, frame):
    timer = threading.Timer(GRACE_S, _watchdog)
    timer.daemon = True
    timer.start()
    signal.signal(signal.SIGINT, lambda *a: _watchdog())  # a second Ctrl-C ends it at once
    raise KeyboardInterrupt


def install(hint: str = ""):
    """Route SIGINT through the watchdog (main thread only; elsewhere Python's default stays). Returns the
    handler it replaced, for `restore`."""
    _state["hint"] = hint
    if threading.current_thread() is threading.main_thread():
        return signal.signal(signal.SIGINT, _handler)
    return None


def restore(previous) -> None:
    if previous is not None and threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGINT, previous)


def resume_hint(args) -> str:
    out = getattr(args, "out", None)
    return f"; continue with --resume --out {out}" if out else "; continue with --resume --out <folder>"
