"""Progress over many units of work (a sweep's cells): done / running / failed, elapsed, estimate.

The interface is small on purpose (`update(done=, running=, failed=)`, `note(text)`, `close()`), so that the
single commands' progress display can stand behind it later. On a terminal the line is redrawn in place; when
stderr is not a terminal a plain line is printed every `every` seconds and at each failure; quiet prints nothing.
"""
from __future__ import annotations

import sys
import time


def _clock(seconds: float | None) -> str:
    if seconds is None:
        return "?"
    s = int(round(seconds))
    return f"{s // 3600}h{s % 3600 // 60:02d}m{s % 60:02d}s" if s >= 3600 else f"{s // 60}m{s % 60:02d}s"


class Progress:
    def __init__(self, total: int, label: str = "sweep", quiet: bool = False, stream=None, every: float = 10.0,
                 slots: int = 1):
        self.total, self.label, self.quiet = int(total), label, quiet
        self.stream = stream if stream is not None else sys.stderr
        self.tty = bool(getattr(self.stream, "isatty", lambda: False)())
        self.every = every if not self.tty else 0.2
        self.slots = max(1, int(slots))
        self.t0 = time.perf_counter()
        self.done = self.running = self.failed = 0
        self._last = -1e9
        self._width = 0

    def estimate(self) -> float | None:
        """Seconds left: the cells still to finish at the rate cells have finished so far (None before the first)."""
        finished = self.done + self.failed
        if finished == 0:
            return None
        elapsed = time.perf_counter() - self.t0
        return elapsed / finished * (self.total - finished)

    def line(self) -> str:
        elapsed = time.perf_counter() - self.t0
        return (f"{self.label}: {self.done}/{self.total} done, {self.running} running, {self.failed} failed, "
                f"elapsed {_clock(elapsed)}, about {_clock(self.estimate())} left")

    def update(self, done: int, running: int, failed: int, force: bool = False) -> None:
        failed_now = failed > self.failed
        self.done, self.running, self.failed = done, running, failed
        now = time.perf_counter()
        if self.quiet or not (force or failed_now or now - self._last >= self.every):
            return
        self._last = now
        self._write(self.line())

    def note(self, text: str) -> None:
        """A line of its own (a failed cell, a phase), never overwritten."""
        if self.quiet:
            return
        if self.tty and self._width:
            self.stream.write("\r" + " " * self._width + "\r")
            self._width = 0
        self.stream.write(text + "\n")
        self.stream.flush()

    def _write(self, text: str) -> None:
        if self.tty:
            pad = max(0, self._width - len(text))
            self.stream.write("\r" + text + " " * pad)
            self._width = len(text)
        else:
            self.stream.write(text + "\n")
        self.stream.flush()

    def close(self) -> None:
        if self.quiet:
            return
        self._write(self.line())
        if self.tty:
            self.stream.write("\n")
            self._width = 0
        self.stream.flush()
