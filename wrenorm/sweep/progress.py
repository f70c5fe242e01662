"""A sweep's progress on the one progress display of every command (wrenorm.progress: a tqdm bar on a terminal,
a plain line every `every` seconds otherwise, nothing when quiet): cells done, running and failed; a failure is
shown at once."""
from __future__ import annotations

from wrenorm.progress import Progress as Display


class Progress:
    def __init__(self, total: int, label: str = "sweep", quiet: bool = False, stream=None, every: float = 10.0,
                 slots: int = 1):
        self.display = Display(int(total), label, quiet, unit="cells", stream=stream, every=every)
        self.failed = 0

    def update(self, done: int, running: int, failed: int, force: bool = False) -> None:
        failed_now = failed > self.failed
        self.failed = failed
        self.display.update(done + failed - self.display.n, force=force or failed_now, done=done, running=running,
                            failed=failed)

    def note(self, text: str) -> None:
        self.display.note(text)

    def close(self) -> None:
        self.display.close()
