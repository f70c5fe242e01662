"""`python -m wrenorm sweep SPEC.toml --out DIR`: every cell of the spec as one Ray task.

DIR holds
    spec.toml            the spec as given
    sweep-state.json     the cells, the inputs' content hashes and, per finished cell, its status, error, host
                         and times (what --resume reads)
    cells/<cell>/        each cell's run folder, exactly as the task's own command writes it
    logs/<cell>.log      what the cell printed
    sweep.json           everything: spec, start-up and cell timings, per-cell records, the table
    sweep.csv            the table, one row per cell (wrenorm.sweep.table)
    sweep.png            each fitted parameter against each varied axis, with the seed spread
    recording.rrd        the whole sweep in Rerun (`python -m wrenorm view DIR`)

Ray: an embedded local Ray by default (nothing to start by hand; --cpus caps it), or --address to join a running
cluster (`ray start --head` prints the address). A cell holds --cpus-per-cell CPUs (Warp's CPU launch threads are
set to match) or, with --device cuda, --gpus-per-cell GPUs. Ray's own output goes to its log files, not to the
terminal; its start-up is timed apart from the cells.
"""
from __future__ import annotations

import contextlib
import json
import os
import sys
import threading
import time
from pathlib import Path

from wrenorm.errors import InputError, warn
from wrenorm.options import add_number
from wrenorm.results import write_atomic, write_json

from . import table
from .cell import TOKEN_FILE, _now, result_file

STATE_FILE = "sweep-state.json"
SCHEMA = "wrenorm.sweep/1"
WARM_CONFIGS = 8  # distinct option sets whose kernels the driver builds before any worker starts


def add_arguments(p) -> None:
    p.add_argument("spec", type=Path, metavar="SPEC.toml", help="the sweep: task, options, axes, seeds (README)")
    p.add_argument("--out", type=Path, default=None, help="sweep folder (default runs/sweep-<system>-<time>)")
    p.add_argument("--address", default=None,
                   help="join this Ray cluster (host:port printed by `ray start --head`; 'auto' for the local one); "
                        "default: start an embedded local Ray")
    add_number(p, "--cpus", default=None, lo=1, hi=100000, integer=True,
               help="CPUs of the embedded local Ray (default: this machine's)")
    add_number(p, "--cpus-per-cell", default=1, lo=1, hi=1024, integer=True,
               help="CPUs each cell holds; Warp's CPU launch threads match it")
    p.add_argument("--device", choices=["cpu", "cuda"], default="cpu", help="cuda: each cell holds --gpus-per-cell")
    add_number(p, "--gpus-per-cell", default=1.0, lo=0.0, lo_open=True, hi=64.0,
               help="GPUs each cell holds with --device cuda (a fraction shares one GPU between cells)")
    add_number(p, "--max-retries", default=0, lo=0, hi=100, integer=True,
               help="Ray retries of a cell whose worker or node was lost (0: record it as failed)")
    p.add_argument("--resume", action="store_true", help="run only the cells the interrupted sweep in --out lacks")
    p.add_argument("--retry-failed", action="store_true", help="resume, and run the failed cells again too")
    p.add_argument("--force", action="store_true", help="clear a non-empty --out folder that wrenorm wrote")
    p.add_argument("--quiet", action="store_true", help="no progress output")
    p.add_argument("--no-record", action="store_true", help="skip the sweep's Rerun recording")


# --- state ------------------------------------------------------------------------------------------------------

def _cells_identity(spec) -> list:
    return [[c.id, list(c.argv)] for c in spec.cells]


def _load_state(out: Path, spec) -> dict:
    f = out / STATE_FILE
    try:
        state = json.loads(f.read_text())
    except (OSError, ValueError) as e:
        raise InputError(str(f), STATE_FILE, f"cannot be read: {e}") from None
    records = state.get("records") if isinstance(state, dict) else None
    if not isinstance(records, dict) or not all(isinstance(r, dict) for r in records.values()):
        # a list, a null or a record that is a string had ended in a traceback (review of stop 54)
        raise InputError(str(f), "records", "not a sweep's state (an object of cell records): edited, or not "
                                            "wrenorm's; start anew with --force")
    if state.get("cells") != _cells_identity(spec):
        raise InputError(str(f), "cells", "the spec expands to other cells than the interrupted sweep's; resume with "
                                          "the same spec (DIR/spec.toml is a copy), or start anew with --force")
    # the same command lines may read other bytes: a file edited in place, or a relative path from another folder
    if not isinstance(state.get("inputs"), dict):  # saved before sweeps kept their inputs' hashes (stop 45)
        if spec.hashes:
            warn(f"{f}: inputs: the interrupted sweep did not record its inputs' content; resuming without checking "
                 f"{', '.join(sorted(spec.hashes))}")
        return state
    old = state["inputs"]
    for name in sorted(set(old) | set(spec.hashes)):
        if old.get(name) != spec.hashes.get(name):
            then = f"sha256 {old[name][:12]}" if old.get(name) else "not recorded"
            now = f"sha256 {spec.hashes[name][:12]}" if spec.hashes.get(name) else "not read"
            raise InputError(str(f), "inputs", f"{name} is not what the interrupted sweep read (content {then}, now "
                                               f"{now}); resume with the same inputs from the same folder, or start "
                                               "anew with --force")
    return state


def _save_state(out: Path, spec, records: dict) -> None:
    write_json(out / STATE_FILE, {"schema": "wrenorm.sweep-state/1", "task": spec.task,
                                  "cells": _cells_identity(spec), "inputs": spec.hashes, "records": records})


def _result_problem(verb: str, result) -> str | None:
    """Why the table could not read this as a finished cell's result (None: it can): its command's schema (a
    command whose result has none, `select`, is taken as it is), and per fit run or flow point the parameters with
    their fitted values and the loss."""
    if not isinstance(result, dict):
        return "is not a JSON object"
    schema = {"fit": "wrenorm.result/", "flow": "wrenorm.flow/"}.get(verb, f"wrenorm.{verb}/")
    if (verb in ("fit", "flow") or "schema" in result) and not str(result.get("schema", "")).startswith(schema):
        return f"schema is {result.get('schema')!r}, not {schema}*"
    if verb not in ("fit", "flow"):
        return None
    parts = result.get("runs", [result]) if verb == "fit" else result.get("points")
    if not isinstance(parts, list) or not parts:
        return "has no " + ("runs" if verb == "fit" else "points")
    for part in parts:
        params = part.get("parameters") if isinstance(part, dict) else None
        if not isinstance(params, dict) or not params:
            return "has no parameters"
        if not all(isinstance(p, dict) and "fitted" in p for p in params.values()):
            return "has a parameter without its fitted value"
        if not isinstance(part.get("loss"), dict):
            return "has no loss"
    return None


def _read_result(out: Path, verb: str, cell_id: str, say_why: bool) -> dict | None:
    """A finished cell's result, or None (the cell runs again: said on stderr where say_why)."""
    path = out / "cells" / cell_id / result_file(verb)
    try:
        result = json.loads(path.read_text())
        problem = _result_problem(verb, result)
    except FileNotFoundError:
        # a cell recorded as done whose result is gone (its folder deleted or moved) runs again, and says so
        problem = "recorded as done but missing"
    except (OSError, ValueError) as e:
        problem = f"cannot be read: {e}"
    if problem and say_why:
        warn(f"{path}: {problem}; running cell {cell_id} again")
    return None if problem else result


def _todo(out: Path, spec, records: dict, results: dict, retry_failed: bool) -> list:
    """The cells still to run; finished ones' results read back from their folders."""
    todo = []
    for cell in spec.cells:
        rec = records.get(cell.id)
        status = (rec or {}).get("status")
        if status == "failed" and not retry_failed:
            continue
        if status == "done" or (rec is None and spec.verb == "fit"):
            # done, or a fit that finished after the last state write (its result.json is written last, atomically)
            result = _read_result(out, spec.verb, cell.id, say_why=status == "done")
            if result is not None:
                results[cell.id] = result
                if rec is None:
                    records[cell.id] = {"status": "done", "error": None, "recovered_from": "result.json"}
                continue
        records.pop(cell.id, None)
        todo.append(cell)
    return todo


# --- Ray --------------------------------------------------------------------------------------------------------

def _import_ray(address: str | None = None):
    os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")  # nothing leaves this machine
    if address and "RAY_AUTH_MODE" not in os.environ and _token_available():
        # `ray start` (Ray >= 2.59) authenticates with a token; a driver joining it must say so, before Ray loads
        os.environ["RAY_AUTH_MODE"] = "token"
    os.environ.setdefault("RAY_DEDUP_LOGS", "0")
    os.environ.setdefault("RAY_ACCEL_ENV_VAR_OVERRIDE_ON_ZERO", "0")
    try:
        import ray
    except ImportError:
        raise InputError("sweep", "ray", "not installed: pip install 'wrenorm[sweep]'") from None
    return ray


def _start_ray(ray, args) -> dict:
    import logging

    kw = dict(include_dashboard=False, log_to_driver=False, logging_level=logging.ERROR, configure_logging=True)
    try:
        if args.address:
            ray.init(address=args.address, **kw)
        else:
            # "local": always a fresh embedded Ray, never one that `ray start` left running on this machine
            ray.init(address="local", num_cpus=args.cpus or os.cpu_count() or 1, **kw)
    except (ConnectionError, RuntimeError, ValueError) as e:
        where = "--address" if args.address else "ray"
        raise InputError(where, args.address or "local", f"cannot start or join Ray: {str(e).splitlines()[0]}") \
            from None
    from wrenorm.interrupt import take_sigterm

    take_sigterm()  # ray.init put its own SIGTERM handler (sys.exit) in place of ours: no resume line, exit 15
    res = ray.cluster_resources()
    return {"address": args.address or "local", "version": ray.__version__, "nodes": len(ray.nodes()),
            "cpus": float(res.get("CPU", 0)), "gpus": float(res.get("GPU", 0))}


@contextlib.contextmanager
def _ray_output_to(log: Path):
    """While Ray runs, whatever its C++ core and Python internals write to stderr goes to `log`; the sweep's own
    lines go to the terminal through the stream this yields."""
    sys.stderr.flush()
    saved = os.dup(2)
    terminal = os.fdopen(os.dup(saved), "w", buffering=1)
    with open(log, "ab") as f:
        os.dup2(f.fileno(), 2)
        try:
            yield terminal
        finally:
            sys.stderr.flush()
            os.dup2(saved, 2)
            os.close(saved)
            terminal.close()


def _check_address(address: str) -> None:
    """Something must answer at host:port before Ray is asked to join it (Ray itself retries for minutes)."""
    import socket

    if address == "auto":
        return
    text = address.split("://", 1)[-1]
    host, _, port = text.rpartition(":")
    if not host or not port.isdigit():
        raise InputError("--address", address, "expected host:port (as `ray start --head` prints it) or 'auto'")
    try:
        socket.create_connection((host, int(port)), timeout=5).close()
    except OSError as e:
        raise InputError("--address", address, f"nothing answers there ({e.strerror or e}): is `ray start --head` "
                                               "running on that machine?") from None


def _token_available() -> bool:
    return bool(os.environ.get("RAY_AUTH_TOKEN") or os.environ.get("RAY_AUTH_TOKEN_PATH")
                or (Path.home() / ".ray" / "auth_token").is_file())


def _check_local(args) -> None:
    """What the embedded local Ray will have is known before it starts: a cell it cannot hold is refused before
    --out is made (a cluster's resources are known only once joined: _run checks those)."""
    from wrenorm.cli import _device

    cpus = args.cpus or os.cpu_count() or 1
    if args.cpus_per_cell > cpus:
        have = f"--cpus {cpus}" if args.cpus else f"{cpus}, this machine's"
        raise InputError("--cpus-per-cell", args.cpus_per_cell,
                         f"a cell cannot hold more CPUs than the local Ray has ({have})")
    if args.device == "cuda":
        _device(args.device)  # no CUDA device here: one line naming --device


def _slots(info: dict, args) -> int:
    slots = int(info["cpus"] // args.cpus_per_cell)
    if args.device == "cuda":
        slots = min(slots, int(info["gpus"] // args.gpus_per_cell + 1e-9))
    return slots


def _warm_configs(spec) -> list:
    """Distinct option sets (seeds aside), first WARM_CONFIGS of them."""
    seen = []
    for c in spec.cells:
        words = list(c.argv[:-2])  # without --seed S
        if words not in seen:
            seen.append(words)
    return [[*w, "--seed", "0"] for w in seen[:WARM_CONFIGS]]


# --- the command --------------------------------------------------------------------------------------------------

def cmd_sweep(args) -> int:
    from wrenorm.cli import content_hashes
    from wrenorm.runfolder import hold_folder, prepare_out

    from .spec import load

    spec = load(args.spec)  # every cell checked: a bad spec ends here, before Ray starts
    spec.hashes = content_hashes(spec.inputs)  # once, at the start: what --resume must find again
    ray = _import_ray(args.address)
    if args.address:
        _check_address(args.address)
    else:
        _check_local(args)
    resume = args.resume or args.retry_failed
    out = args.out or Path("runs") / f"sweep-{spec.system}-{time.strftime('%Y%m%d-%H%M%S')}"
    records, results = {}, {}
    if resume and args.force:  # checked before the folder is taken: prepare_out says why
        prepare_out(out, resume=True, force=True)
    if resume and not Path(out).exists():
        prepare_out(out, resume=True, state=STATE_FILE, command="sweep")  # says there is nothing to resume
    hold_folder(out)
    if resume:
        out = prepare_out(out, resume=True, state=STATE_FILE, command="sweep")
        records = _load_state(out, spec).get("records", {})
    else:
        out = prepare_out(out, force=args.force, inputs=[args.spec, *spec.inputs], command=f"sweep {spec.task}")
        write_atomic(out / "spec.toml", spec.text)
    todo = _todo(out, spec, records, results, args.retry_failed)
    _save_state(out, spec, records)
    token = f"{os.getpid()}-{time.time_ns()}"
    write_atomic(out / TOKEN_FILE, token + "\n")
    (out / "cells").mkdir(exist_ok=True)
    (out / "logs").mkdir(exist_ok=True)
    if not args.quiet:
        print(f"wrenorm sweep {spec.task}: {len(spec.cells)} cells ({len(todo)} to run), writing {out}",
              file=sys.stderr, flush=True)

    timing = {"started": _now()}
    t_start = time.perf_counter()
    sweep = {"out": out, "spec": spec, "records": records, "results": results, "timing": timing, "ray": None,
             "args": args}
    interrupted = False
    try:
        if todo:
            with _ray_output_to(out / "ray.log") as terminal:
                say = (lambda text: None) if args.quiet else (lambda text: print(text, file=terminal, flush=True))
                try:
                    _run(ray, args, spec, out, todo, token, sweep, say, terminal)
                except KeyboardInterrupt:  # Ctrl-C or SIGTERM (wrenorm.interrupt)
                    # stderr is ray.log here, and Ray's shut-down outlasts the interrupt's one-second grace, whose
                    # line would go there too: say it on the terminal first
                    from wrenorm.interrupt import resume_hint

                    print(f"\nwrenorm: interrupted{resume_hint(args)}", file=terminal, flush=True)
                    interrupted = True
                finally:
                    if ray.is_initialized():
                        t = time.perf_counter()
                        ray.shutdown()
                        timing["ray_shutdown_s"] = time.perf_counter() - t
    finally:
        timing["total_s"] = time.perf_counter() - t_start
        _write_tables(sweep)
    if interrupted:
        from wrenorm.interrupt import exit_code

        return exit_code()
    _finish(sweep)
    return 0 if all(records.get(c.id, {}).get("status") == "done" for c in spec.cells) else 3


def _run(ray, args, spec, out: Path, todo: list, token: str, sweep: dict, say, terminal) -> None:
    from . import cell as cellmod
    from .progress import Progress

    timing, records, results = sweep["timing"], sweep["records"], sweep["results"]
    # start Ray while the driver builds the kernels the cells need (so that workers never race to compile them)
    # (the first option set always; further ones only while Ray is still starting)
    warm_info = {"configs": 0}
    ray_up = threading.Event()

    def warm_driver():
        t = time.perf_counter()
        for k, words in enumerate(_warm_configs(spec)):
            if k and ray_up.is_set():
                break
            cellmod.warm(words, args.cpus_per_cell, args.device, capture=False)  # a thread: never swap sys.stderr
            warm_info["configs"] = k + 1
        warm_info["seconds"] = time.perf_counter() - t

    where = f"joining {args.address}" if args.address else f"starting a local Ray ({args.cpus or os.cpu_count()} CPUs)"
    say(f"{where} and building the cells' kernels ...")
    warmer = threading.Thread(target=warm_driver, daemon=True)
    t0 = time.perf_counter()
    warmer.start()
    try:
        info = _start_ray(ray, args)
        timing["ray_start_s"] = time.perf_counter() - t0
    finally:
        ray_up.set()
        warmer.join()
    timing["driver_warm_s"], timing["driver_warm_configs"] = warm_info.get("seconds"), warm_info["configs"]
    sweep["ray"] = info
    slots = _slots(info, args)
    if slots < 1:
        need = f"{args.gpus_per_cell:g} GPU" if args.device == "cuda" else f"{args.cpus_per_cell} CPUs"
        flag = "--gpus-per-cell" if args.device == "cuda" else "--cpus-per-cell"
        raise InputError("--address" if args.address else flag,
                         args.gpus_per_cell if args.device == "cuda" else args.cpus_per_cell,
                         f"the Ray cluster ({info['cpus']:g} CPUs, {info['gpus']:g} GPUs) cannot hold a cell "
                         f"({need} each)")
    gpus = args.gpus_per_cell if args.device == "cuda" else 0
    opts = dict(num_cpus=args.cpus_per_cell, num_gpus=gpus)
    # every worker imports wrenorm and loads the kernels once, before the first cell (start-up, not cell time)
    t1 = time.perf_counter()
    warm = ray.remote(cellmod.warm).options(**opts, max_retries=0)
    first = _warm_configs(spec)[0]
    workers = ray.get([warm.remote(first, args.cpus_per_cell, args.device) for _ in range(min(slots, len(todo)))])
    timing["workers_warm_s"] = time.perf_counter() - t1
    timing["workers"] = sorted({f"{w['host']}:{w['pid']}" for w in workers})
    timing["startup_s"] = time.perf_counter() - t0
    say(f"Ray {info['version']} ({'local' if not args.address else args.address}, {info['cpus']:g} CPUs, "
        f"{info['gpus']:g} GPUs; {slots} cells at a time): started in {timing['ray_start_s']:.1f} s, "
        f"kernels and {len(workers)} workers warmed in {timing['startup_s'] - timing['ray_start_s']:.1f} s")

    task = ray.remote(cellmod.run_cell).options(**opts, max_retries=args.max_retries, retry_exceptions=False)
    t2 = time.perf_counter()
    here = os.getcwd()
    pending = {task.remote(list(c.argv), str(out.resolve()), c.id, token, args.cpus_per_cell, args.device,
                           None, here): c for c in todo}
    done_before = sum(1 for r in records.values() if r.get("status") == "done")
    failed_before = sum(1 for r in records.values() if r.get("status") == "failed")
    progress = Progress(len(spec.cells), label=f"sweep {spec.task}", quiet=args.quiet, stream=terminal)
    progress.update(done_before, min(len(pending), slots), failed_before, force=True)
    last_table = time.perf_counter()
    try:
        while pending:
            ready, _ = ray.wait(list(pending), num_returns=len(pending), timeout=0.25)
            for ref in ready:
                c = pending.pop(ref)
                try:
                    res = ray.get(ref)
                except Exception as e:  # the worker or its node was lost (ray.exceptions.RayError and kin)
                    first_line = (str(e).strip().splitlines() or [""])[0][:300]
                    res = {"rc": None, "error": f"worker lost ({type(e).__name__}): {first_line}", "result": None,
                           "log": str(e), "files": None, "host": None, "started": None, "finished": _now(),
                           "cell_seconds": None}
                if res["rc"] == 130:  # the cell was interrupted (Ctrl-C reaches the workers too): still to run
                    continue
                _record(out, spec, c, res, records, results)
                if res["rc"] != 0:
                    progress.note(f"cell {c.id} failed: {records[c.id]['error']}")
            done = sum(1 for r in records.values() if r.get("status") == "done")
            failed = sum(1 for r in records.values() if r.get("status") == "failed")
            progress.update(done, min(len(pending), slots), failed)
            if ready and time.perf_counter() - last_table > 2.0:  # the table grows as cells finish
                _write_tables(sweep)
                last_table = time.perf_counter()
        progress.close()
    except BaseException as e:
        if isinstance(e, KeyboardInterrupt):
            # the table first: cancelling and Ray's shut-down can outlast the interrupt's one-second grace, and the
            # table was written at most every 2 s, so the cells done since would be missing from it until --resume
            _write_tables(sweep)
        for ref in pending:
            ray.cancel(ref, force=True)
        raise
    timing["cells_s"] = time.perf_counter() - t2
    timing["slots"] = slots


def _record(out: Path, spec, c, res: dict, records: dict, results: dict) -> None:
    folder = out / "cells" / c.id
    for rel, data in (res.get("files") or {}).items():  # the worker did not see DIR: its files came back
        write_atomic(folder / rel, data)
    if res.get("log"):
        write_atomic(out / "logs" / f"{c.id}.log", res["log"])
    wall = (res.get("result") or {}).get("wall_seconds")
    records[c.id] = {"status": "done" if res["rc"] == 0 else "failed", "error": res.get("error"), "rc": res["rc"],
                     "host": res.get("host"), "started": res.get("started"), "finished": res.get("finished"),
                     "cell_seconds": res.get("cell_seconds"), "wall_seconds": wall,
                     "setup_seconds": res.get("setup_seconds"), "pid": res.get("pid"), "unix": res.get("unix"),
                     "resumed": bool(res.get("resumed"))}
    if res["rc"] == 0:
        results[c.id] = res.get("result")
    else:
        results.pop(c.id, None)
    _save_state(out, spec, records)


def _overhead(records: dict) -> dict | None:
    """What a cell costs beyond its command's own wall_seconds, and how much of that is the command's own set-up
    (options, problem building: what `fit` does too before its clock starts) rather than the sweep's or Ray's."""
    rs = [r for r in records.values() if r.get("cell_seconds") is not None and r.get("wall_seconds") is not None
          and not r.get("resumed")]  # a resumed cell's command timed part of its run
    if not rs:
        return None
    beyond = [r["cell_seconds"] - r["wall_seconds"] for r in rs]
    setup = [r.get("setup_seconds") or 0.0 for r in rs]
    rest = [b - s for b, s in zip(beyond, setup)]
    gaps = []  # between one cell's end and the next one's start on the same worker: Ray's dispatch
    by_worker: dict = {}
    for r in records.values():
        if r.get("unix") and r.get("pid") is not None:
            by_worker.setdefault((r.get("host"), r["pid"]), []).append(r["unix"])
    for spans in by_worker.values():
        spans.sort()
        gaps += [b[0] - a[1] for a, b in zip(spans, spans[1:])]
    def mean(xs):
        return sum(xs) / len(xs) if xs else None

    return {"mean_s": mean(beyond), "max_s": max(beyond), "cells": len(rs),
            "setup_mean_s": mean(setup), "beyond_setup_mean_s": mean(rest), "beyond_setup_max_s": max(rest),
            "dispatch_gap_mean_s": mean(gaps), "dispatch_gap_max_s": max(gaps) if gaps else None,
            "meaning": "mean_s / max_s: a cell's time in its worker (cell_seconds) minus its command's own "
                       "wall_seconds; setup_mean_s: of that, the command's option checks and problem building "
                       "before its run folder exists (a separate `fit` spends it too, outside wall_seconds); "
                       "beyond_setup: the rest (the sweep's own work in the worker); dispatch_gap: from one cell's "
                       "end to the next one's start on the same worker (Ray). Ray's start-up and the worker "
                       "warm-up are timed apart (timing)"}


def _write_tables(sweep: dict) -> None:
    out, spec, records, results = sweep["out"], sweep["spec"], sweep["records"], sweep["results"]
    rows = table.build(spec, records, results)
    counts = {s: sum(1 for r in records.values() if r.get("status") == s) for s in ("done", "failed")}
    counts["pending"] = len(spec.cells) - counts["done"] - counts["failed"]
    cells = []
    for c in spec.cells:
        rec = records.get(c.id, {})
        cells.append({"id": c.id, "axes": c.axes, "seed": c.seed, "status": rec.get("status", "pending"),
                      "error": rec.get("error"), "folder": f"cells/{c.id}",
                      "command": c.command(out / "cells" / c.id), **{k: rec.get(k) for k in table.VOLATILE}})
    write_json(out / "sweep.json", {
        "schema": SCHEMA, "task": spec.task, "description": spec.description,
        "spec": {"file": str(spec.path), "options": spec.options, "axes": spec.axes, "seeds": spec.seeds},
        "counts": counts, "summary": table.summary(spec, records, results), "ray": sweep["ray"],
        "timing": sweep["timing"], "cell_overhead": _overhead(records),
        "cells": cells, "columns": table.columns(spec, rows), "table": rows,
        "volatile_columns": list(table.VOLATILE)})
    table.write_csv(out / "sweep.csv", spec, rows)


def _finish(sweep: dict) -> None:
    out, spec, records, timing, args = sweep["out"], sweep["spec"], sweep["records"], sweep["timing"], sweep["args"]
    rows = table.build(spec, records, sweep["results"])
    names, part = table.plotted(spec, {k: v for k, v in sweep["results"].items()
                                       if records.get(k, {}).get("status") == "done"})
    plotted = False
    try:
        from wrenorm.viz.sweep_plot import plot_sweep

        plotted = plot_sweep(out / "sweep.png", spec, rows, names, part)
    except ImportError:  # matplotlib missing: the plot is a convenience, never fatal
        pass
    if not args.no_record:
        from wrenorm.viz.sweep_plot import record_sweep

        record_sweep(out / "recording.rrd", spec, rows, names, part)
    failed = [c for c in spec.cells if records.get(c.id, {}).get("status") == "failed"]
    done = sum(1 for c in spec.cells if records.get(c.id, {}).get("status") == "done")
    print(f"\nsweep {spec.task}: {done}/{len(spec.cells)} cells done, {len(failed)} failed")
    for c in failed:
        print(f"  {c.id}: {records[c.id].get('error')}")
    for line in table.summary(spec, records, sweep["results"]):
        print(f"  {line}")
    warned = list(dict.fromkeys(r["cell"] for r in rows if r.get("warnings")))
    if warned:
        print(f"  {len(warned)} done cell{'s' if len(warned) > 1 else ''} with warnings ({', '.join(warned[:8])}"
              f"{', ...' if len(warned) > 8 else ''}): see the `warnings` column of sweep.csv")
    if "ray_start_s" in timing:
        ov = _overhead({k: records[k] for k in records})
        print(f"Ray start-up {timing['ray_start_s']:.1f} s (+ warm-up {timing['startup_s'] - timing['ray_start_s']:.1f}"
              f" s), cells {timing.get('cells_s', 0):.1f} s on {timing.get('slots')} slots"
              + (f"; per cell {ov['mean_s']:.2f} s (max {ov['max_s']:.2f} s) beyond the command's own wall_seconds, "
                 f"{ov['setup_mean_s']:.2f} s of it the command's set-up" if ov else ""))
    print(f"table: {out / 'sweep.csv'}" + (f"  plot: {out / 'sweep.png'}" if plotted else "")
          + ("" if args.no_record else f"  view: python -m wrenorm view {out}"))
