"""Ctrl-C (and SIGTERM) that always works: the first one raises KeyboardInterrupt as usual and starts a one-second
watchdog; if the interrupt was swallowed (Python drops exceptions raised inside a finalizer, which Warp and numpy run
at any time) or the work does not reach a point where it can stop, the watchdog ends the process with exit code
128 + the signal (130, 143). State written so far is complete: every write is atomic (temp file + rename)."""
from __future__ import annotations

import os
import signal
import sys
import threading

GRACE_S = 1.0
SIGNALS = (signal.SIGINT, signal.SIGTERM)  # Ctrl-C, and a job scheduler's or `timeout`'s polite stop
_state = {"hint": "", "signal": signal.SIGINT}


def exit_code() -> int:
    """128 + the signal that stopped the run (130 for Ctrl-C, 143 for SIGTERM), as a shell reports it."""
    return 128 + int(_state["signal"])


def _watchdog():
    try:
        sys.stderr.write(f"\nwrenorm: interrupted{_state['hint']}\n")
        sys.stderr.flush()
    finally:
        os._exit(exit_code())


def _handler(signum, frame):
    _state["signal"] = signum
    timer = threading.Timer(GRACE_S, _watchdog)
    timer.daemon = True
    timer.start()
    for s in SIGNALS:
        signal.signal(s, lambda *a: _watchdog())  # a second one ends it at once
    raise KeyboardInterrupt


def install(hint: str = ""):
    """Route SIGINT and SIGTERM through the watchdog (main thread only; elsewhere Python's default stays).
    Returns the handlers it replaced, for `restore`."""
    _state["hint"], _state["signal"] = hint, signal.SIGINT
    if threading.current_thread() is threading.main_thread():
        return {s: signal.signal(s, _handler) for s in SIGNALS}
    return None


def take_sigterm() -> None:
    """SIGTERM back to the watchdog after a library (Ray's init) replaced the handler `install` set."""
    if threading.current_thread() is threading.main_thread() and signal.getsignal(signal.SIGINT) is _handler:
        signal.signal(signal.SIGTERM, _handler)


def restore(previous) -> None:
    if previous is not None and threading.current_thread() is threading.main_thread():
        for s, handler in previous.items():
            signal.signal(s, handler)


def resume_hint(args) -> str:
    """What to do after an interrupt: --resume where the command has it; `select` and `sensitivity` had been told to
    resume, which they cannot, and the folder then refused a plain rerun (review of stop 54)."""
    out = getattr(args, "out", None)
    if args is not None and not hasattr(args, "resume"):
        return f"; this command does not resume: run it again with --force --out {out}" if out else ""
    argv = [a for a in getattr(args, "_argv", None) or [] if a != "--force"]
    if out and argv and "--out" in argv:  # the whole command: a flow or a sweep (its spec) resumes only with its own
        # options, and a flow told "--resume --out DIR" alone had refused with every resolution listed (stop 54)
        import shlex

        return f"; continue with: python -m wrenorm {shlex.join(argv + ([] if '--resume' in argv else ['--resume']))}"
    return f"; continue with --resume --out {out}" if out else "; continue with --resume --out <folder>"
