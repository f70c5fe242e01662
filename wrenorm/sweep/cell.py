"""What one Ray task does: run the task's own command (wrenorm.cli.main, the code path of `fit`, `flow`, ...) into
the cell's run folder, and say how it went. Never raises: a failing cell is a result like any other.

A cell killed before it finished (a killed driver, a lost worker) left its run folder behind: its command continues
it with `--resume` (a fit's search log, a correction's stored real trials), which repeats the uninterrupted run, and
runs it afresh only where the resume is refused (killed before it saved a state, or a state it refuses: exit 2, before
any work). A resumed run that fails otherwise is the cell's result, as the same run afresh would be.

The cell's folder is DIR/cells/<cell> when the worker sees DIR (same machine or a shared file system, recognised by
the token the driver wrote in DIR/.wrenorm-sweep); otherwise the cell runs in a local temporary folder and its files
travel back with the result, for the driver to write into DIR/cells/<cell>.
"""
from __future__ import annotations

import contextlib
import io
import json
import os
import shutil
import socket
import tempfile
import time
import traceback
from pathlib import Path

from wrenorm.errors import WARNING_PREFIX
from wrenorm.runfolder import MARKER as RUN_MARKER

TOKEN_FILE = ".wrenorm-sweep"
RESUME_REFUSED = "wrenorm sweep: the killed cell's run could not be resumed; it ran afresh"
RESULT_FILES = {"fit": "result.json", "flow": "flow.json"}  # any other command: <verb>.json (correct.json)
WARNINGS_KEPT = 5  # a failed cell's last warnings that its recorded error carries


def result_file(verb: str) -> str:
    return RESULT_FILES.get(verb, f"{verb}.json")


def _now() -> str:
    """Local wall time to the millisecond (a cell's and a sweep's start and finish)."""
    return time.strftime("%Y-%m-%dT%H:%M:%S", time.localtime()) + f".{int(time.time() * 1000) % 1000:03d}"


def _shared(sweep_dir: str, token: str) -> bool:
    try:
        return (Path(sweep_dir) / TOKEN_FILE).read_text().strip() == token
    except OSError:
        return False


def _threads(cpus: int) -> None:
    """Warp's CPU launches split over WRENORM_THREADS threads (kernels/launch.py): one per CPU the cell holds."""
    os.environ["WRENORM_THREADS"] = str(max(1, int(cpus)))


def _error_line(log: str, rc: int) -> str:
    """The cell's error as sweep.csv records it: its command's last error line, after the warnings printed before
    it (the last WARNINGS_KEPT). Those name the file left out and why, where the error may only say "warnings
    above": the log they are in is not what a reader of the table sees."""
    lines = [ln.strip() for ln in log.splitlines() if ln.strip()]
    for prefix, keep in (("wrenorm: error: ", ""), ("wrenorm: fit failed: ", "fit failed: ")):
        hit = [i for i, ln in enumerate(lines) if ln.startswith(prefix)]
        if hit:
            warnings = [ln[len("wrenorm: "):] for ln in lines[:hit[-1]] if ln.startswith(WARNING_PREFIX)]
            more = len(warnings) - WARNINGS_KEPT
            return "; ".join([keep + lines[hit[-1]][len(prefix):], *warnings[-WARNINGS_KEPT:],
                              *([f"{more} earlier warnings in the cell's log"] if more > 0 else [])])
    return lines[-1] if lines else f"exit code {rc}"


def run_cell(argv: list, sweep_dir: str, cell_id: str, token: str, cpus: int = 1, device: str = "cpu",
             ship: bool | None = None, cwd: str | None = None) -> dict:
    """Run one cell. `ship` forces (True) or forbids (False) sending the files back; None: only when the worker
    does not see the sweep's folder. cwd: the folder the sweep was started from, where relative paths in the spec
    point (entered when this machine has it)."""
    t0, unix0 = time.perf_counter(), time.time()
    started = _now()
    _threads(cpus)
    if cwd and os.path.isdir(cwd):
        os.chdir(cwd)
    ship = (not _shared(sweep_dir, token)) if ship is None else ship
    tmp = tempfile.mkdtemp(prefix=f"wrenorm-cell-{cell_id}-") if ship else None
    out = Path(tmp) / cell_id if ship else Path(sweep_dir) / "cells" / cell_id
    words = [*argv, "--out", str(out), "--quiet"] + (["--device", device] if device != "cpu" else [])
    resumed = (out / RUN_MARKER).is_file()  # a cell killed before it finished (the folder is the sweep's own)
    rc, log = _command(words + ["--resume"]) if resumed else (None, "")
    if rc is None or rc == 2:  # a resume refused (exit 2, before any work): no state to continue, or one it refuses
        if resumed:
            log, resumed = f"{RESUME_REFUSED} ({_error_line(log, rc)})\n", False
        if out.exists():
            shutil.rmtree(out)
        rc, fresh = _command(words)
        log += fresh
    verb = argv[0]
    try:  # the command checks its options and builds its problem before it makes its run folder
        setup = None if resumed else (out / RUN_MARKER).stat().st_mtime - unix0
    except OSError:
        setup = None
    result = None
    path = out / result_file(verb)
    if rc == 0 and path.exists():
        result = json.loads(path.read_text())
    files = None
    if ship:
        files = {str(p.relative_to(out)): p.read_bytes() for p in sorted(out.rglob("*")) if p.is_file()}
        shutil.rmtree(tmp, ignore_errors=True)
    return {"cell": cell_id, "rc": rc, "error": None if rc == 0 else _error_line(log, rc), "result": result,
            "log": log, "files": files, "host": socket.gethostname(), "pid": os.getpid(), "started": started,
            "finished": _now(), "cell_seconds": time.perf_counter() - t0, "setup_seconds": setup,
            "unix": [unix0, time.time()], "resumed": resumed}


def _command(words: list) -> tuple[int, str]:
    """wrenorm.cli.main(words) in this process: its exit code and all it printed."""
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf), contextlib.redirect_stderr(buf):
        try:
            from wrenorm.cli import main

            rc = int(main(words))
        except BaseException as e:  # a bug, not bad input: keep the traceback in the cell's log
            traceback.print_exc()
            rc = 130 if isinstance(e, KeyboardInterrupt) else 1
    return rc, buf.getvalue()


def warm(argv: list, cpus: int = 1, device: str = "cpu", capture: bool = True) -> dict:
    """Import everything a cell uses and build (or load from Warp's kernel cache) the kernels of this cell's
    options, so the cells that follow pay neither. Run in the driver before any worker (so that workers do not
    race to compile the same module) and once in every worker. capture: swallow what it prints (never in a
    thread beside others: sys.stdout and sys.stderr are the whole process's)."""
    t0 = time.perf_counter()
    _threads(cpus)
    info = {"host": socket.gethostname(), "pid": os.getpid()}
    quiet = (contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO())) if capture else ()
    with contextlib.ExitStack() as stack:
        for q in quiet:
            stack.enter_context(q)
        try:
            _warm(list(argv), device)
        except Exception as e:  # the cell itself will report it properly
            info["error"] = f"{type(e).__name__}: {e}"
    info["seconds"] = time.perf_counter() - t0
    return info


def _warm(argv: list, device: str) -> None:
    import warp as wp

    wp.config.log_level = wp.LOG_ERROR
    from wrenorm import cli
    from wrenorm.system import resolve, systems

    with contextlib.suppress(ImportError):  # what writing a result uses: plots and recordings
        import wrenorm.viz.plots  # noqa: F401
        import wrenorm.viz.record  # noqa: F401
        from wrenorm.viz.plots import _figure

        _figure()
    if argv[0] not in ("fit", "flow"):  # other commands: the imports above are all we know how to warm
        return
    import numpy as np

    args = cli.build_parser(argv).parse_args([*argv, "--out", "warm", "--device", device])
    system = systems()[args.system]
    build = system.build if args.command == "fit" else system.flow.build

    problems = resolve(build)(args, cli._device(args.device))
    for p in problems[:1]:
        p.errors(np.asarray(p.space.measured)[None], p.train)
