"""User-facing errors: every bad input names its source, the field and the problem."""
import sys

WARNING_PREFIX = "wrenorm: warning: "  # a sweep cell's log is read back by it (wrenorm.sweep.cell)


def warn(message: str) -> None:
    """Say a flag on the data (a file left out, an uncertain event, a suspect frame rate) on stderr, as it arises;
    the result files keep the same text."""
    print(f"{WARNING_PREFIX}{message}", file=sys.stderr, flush=True)


class InputError(Exception):
    """Bad user input. The CLI prints it and exits with code 2, never a traceback."""

    def __init__(self, source: str, field: str, problem: str):
        self.source, self.field, self.problem = str(source), str(field), str(problem)
        super().__init__(f"{self.source}: {self.field}: {self.problem}")


class AllCandidatesFailed(RuntimeError):
    """Every candidate of a generation blew up: the search has nothing to learn from."""
