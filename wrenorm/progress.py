"""Progress of long work: a tqdm bar on a terminal; on anything else (CI, a log file) a plain line every few
seconds and at the end; nothing with --quiet. One interface for fits, flows, correction trials, reference
generation and sweeps:

    with Progress(total=60, what="rope gen", quiet=args.quiet) as bar:
        for g in range(60):
            ...
            bar.update(best=f"{loss:.3g}", blowups=n)
"""
from __future__ import annotations

import sys
import time

LINE_EVERY_S = 5.0  # plain-line mode: at most one line this often (and always the last one)


def _fmt_s(s: float) -> str:
    return f"{s:.0f}s" if s < 120 else f"{s / 60:.1f}min"


class Progress:
    def __init__(self, total: int | None, what: str, quiet: bool = False, unit: str = "", stream=None,
                 done: int = 0, every: float = LINE_EVERY_S):
        self.total, self.what, self.quiet, self.unit = total, what, quiet, unit
        self.stream = stream or sys.stderr
        self.every = every
        self.n = done
        self.t0 = time.perf_counter()
        self._last_line = -1e9
        self._fields: dict = {}
        self._bar = None
        if not quiet and getattr(self.stream, "isatty", lambda: False)():
            from tqdm import tqdm

            self._bar = tqdm(total=total, desc=what, unit=unit or "it", file=self.stream, dynamic_ncols=True,
                             leave=True, initial=done)

    def set_total(self, total: int) -> None:
        """For work whose size is known only once it starts (a simulator's frame count)."""
        if total != self.total:
            self.total = total
            if self._bar is not None:
                self._bar.total = total
                self._bar.refresh()

    def update(self, n: int = 1, force: bool = False, **fields) -> None:
        """n more done; `fields` shown beside the count; force: a plain line now (e.g. at a failure)."""
        self.n += n
        self._fields.update(fields)
        if self.quiet:
            return
        if self._bar is not None:
            self._bar.update(n)
            if fields:
                self._bar.set_postfix({k: v for k, v in self._fields.items()}, refresh=False)
            return
        now = time.perf_counter()
        if force or now - self._last_line >= self.every or (self.total is not None and self.n >= self.total):
            self._line(now)

    def _line(self, now: float) -> None:
        self._last_line = now
        elapsed = now - self.t0
        of = f"/{self.total}" if self.total else ""
        eta = ""
        if self.total and 0 < self.n < self.total:
            eta = f", about {_fmt_s(elapsed / self.n * (self.total - self.n))} left"
        fields = "  ".join(f"{k} {v}" for k, v in self._fields.items())
        self.stream.write(f"[{self.what}] {self.n}{of}{' ' + self.unit if self.unit else ''}  {fields}  "
                          f"{_fmt_s(elapsed)}{eta}\n")
        self.stream.flush()

    def note(self, message: str) -> None:
        """A one-off line that does not break the bar."""
        if self.quiet:
            return
        if self._bar is not None:
            self._bar.write(message, file=self.stream)
        else:
            self.stream.write(message + "\n")
            self.stream.flush()

    def close(self) -> None:
        if self._bar is not None:
            self._bar.close()
            self._bar = None
        elif not self.quiet and self.n and time.perf_counter() - self._last_line > 0.5:
            self._line(time.perf_counter())

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
        return False
