"""Command line: `python -m wrenorm fit pd|rope|swimmer`, `view`, `reference rope`, `bench`,
`correct rope`, `sensitivity rope`.

Every user mistake (bad file, bad option value) ends with one line naming the file or option,
the field and the problem, and exit code 2 — never a traceback.
"""
from __future__ import annotations

import argparse
import importlib
import sys
import time
from pathlib import Path

from .errors import AllCandidatesFailed, InputError

TASKS = ("pd", "rope", "swimmer")


def _task_module(name: str):
    return importlib.import_module(f"wrenorm.tasks.{name}")


def _default_out(task: str) -> Path:
    return Path("runs") / f"{task}-{time.strftime('%Y%m%d-%H%M%S')}"


def _device(name: str) -> str:
    import warp as wp

    wp.config.quiet = True
    wp.init()
    if name.startswith("cuda") and not wp.is_cuda_available():
        raise InputError("--device", "device", "cuda requested but no CUDA device is available")
    return "cuda:0" if name.startswith("cuda") else "cpu"


def _positive_int(text: str) -> int:
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
    if v < 0:
        raise argparse.ArgumentTypeError(f"must be >= 0, got {v}")
    return v


def _parameter_set_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--free", nargs="+", default=[], metavar="NAME",
                   help="also fit these parameters (expand the set when the held-out verdict says 'expand')")
    p.add_argument("--freeze", nargs="+", default=[], metavar="NAME",
                   help="hold these parameters at their measured values")


def _apply_parameter_set(problems, args) -> None:
    """--free / --freeze: the paper's procedure starts from the smallest set and grows it when
    held-out conditions say the omitted physics was not absorbed."""
    free, freeze = list(getattr(args, "free", [])), list(getattr(args, "freeze", []))
    both = sorted(set(free) & set(freeze))
    if both:
        raise InputError("--free/--freeze", ",".join(both), "named both free and frozen")
    if not (free or freeze):
        return
    changes = {n: {"frozen": False} for n in free} | {n: {"frozen": True} for n in freeze}
    for pb in problems:
        try:
            pb.space = pb.space.with_changes(**changes)
        except InputError as e:
            raise InputError("--free/--freeze", e.field, e.problem) from None
        if not pb.space.free:
            raise InputError("--freeze", ",".join(freeze), f"leaves no free parameter of {pb.space.names}")


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="wrenorm", description=__doc__.splitlines()[0])
    sub = p.add_subparsers(dest="command", required=True)
    fit = sub.add_parser("fit", help="fit a system's effective parameters")
    fit_sub = fit.add_subparsers(dest="task", required=True)
    for task in TASKS:
        tp = fit_sub.add_parser(task, help=f"fit the {task} system")
        tp.add_argument("--out", type=Path, default=None, help="run folder (default runs/<task>-<time>)")
        tp.add_argument("--seed", type=_positive_int, default=0)
        tp.add_argument("--device", choices=["cpu", "cuda"], default="cpu")
        tp.add_argument("--resume", action="store_true", help="continue the interrupted fit in --out")
        tp.add_argument("--force", action="store_true", help="overwrite a non-empty --out folder")
        tp.add_argument("--quiet", action="store_true", help="no progress lines")
        tp.add_argument("--no-record", action="store_true", help="skip the Rerun recording")
        _parameter_set_arguments(tp)
        try:
            _task_module(task).add_arguments(tp)
        except ModuleNotFoundError:
            tp.set_defaults(_missing=True)
    flow = sub.add_parser("flow", help="effective parameters as functions of resolution, with uncertainty")
    flow_sub = flow.add_subparsers(dest="task", required=True)
    for task in TASKS:
        fp = flow_sub.add_parser(task, help=f"resolution flow of the {task} system")
        fp.add_argument("--resolutions", type=float, nargs="+", default=None,
                        help="pd: f_sim [Hz]; rope: segment counts (--axis dt: steps [s]); "
                             "swimmer: time steps [s] (--axis bodies: tail bodies)")
        fp.add_argument("--out", type=Path, default=None)
        _parameter_set_arguments(fp)
        fp.add_argument("--seed", type=_positive_int, default=0)
        fp.add_argument("--device", choices=["cpu", "cuda"], default="cpu")
        fp.add_argument("--force", action="store_true")
        fp.add_argument("--quiet", action="store_true")
        fp.add_argument("--no-record", action="store_true")
        fp.add_argument("--restarts", type=int, default=4, help="seeded CMA-ES searches side by side")
        fp.add_argument("--resume", action="store_true",
                        help="continue the interrupted flow in --out after its last finished resolution")
        fp.add_argument("--generations", type=int, default=None)
        try:
            mod = _task_module(task)
            if hasattr(mod, "add_flow_arguments"):
                mod.add_flow_arguments(fp)
        except ModuleNotFoundError:
            pass
    view = sub.add_parser("view", help="open a run's recording in the Rerun viewer")
    view.add_argument("run", type=Path)
    ref = sub.add_parser("reference", help="generate a reference")
    ref_sub = ref.add_subparsers(dest="system", required=True)
    rope_ref = ref_sub.add_parser("rope", help="fine newton rope reference (.npz)")
    try:
        importlib.import_module("wrenorm.tasks.rope.reference.generate").add_reference_arguments(rope_ref)
    except ModuleNotFoundError:
        pass
    for command, module, text in (("correct", "wrenorm.tasks.rope.control.correct_cli", "correct a command over real trials"),
                                  ("sensitivity", "wrenorm.tasks.rope.control.sensitivity",
                                   "how many command / parameter directions move the observed state")):
        cp = sub.add_parser(command, help=text)
        cp_sub = cp.add_subparsers(dest="system", required=True)
        try:
            mod = importlib.import_module(module)
            mod.add_arguments(cp_sub.add_parser(mod.SYSTEM, help=f"{command} for the {mod.SYSTEM} system"))
        except ModuleNotFoundError:
            pass
    bench = sub.add_parser("bench", help="throughput of each kernel and end-to-end fit times")
    try:
        importlib.import_module("wrenorm.bench").add_arguments(bench)
    except ModuleNotFoundError:
        pass
    return p


def cmd_fit(args) -> int:
    from .fit import prepare_out, run_fits

    if getattr(args, "_missing", False):
        raise InputError("fit", args.task, "this system is not available in this build")
    device = _device(args.device)
    mod = _task_module(args.task)
    problems = mod.build_problems(args, device) if hasattr(mod, "build_problems") else [mod.build_problem(args, device)]
    _apply_parameter_set(problems, args)
    out = prepare_out(args.out or _default_out(args.task), resume=args.resume, force=args.force)
    print(f"wrenorm fit {args.task}: writing {out}", file=sys.stderr)
    result = run_fits(problems, out, args, mod)
    _print_summary(result, out)
    return 0


def _print_summary(result: dict, out: Path) -> None:
    runs = result.get("runs", [result])
    for r in runs:
        res = r["resolution"]
        print(f"\n{r['task']} at {res}: loss measured {r['loss']['measured']:.4g} -> fitted {r['loss']['fitted']:.4g}")
        for name, p in r["parameters"].items():
            tag = " (frozen)" if p["frozen"] else ""
            std = f" ± {p['std']:.3g}" if p.get("std") is not None else ""
            print(f"  {name:>10}: measured {p['measured']:<10.5g} fitted {p['fitted']:.5g}{std}{tag}")
        v = r["validation"]
        print(f"  held-out verdict: {v['verdict']}" + (
            f" (mean error measured {v['mean_measured_error']:.4g} -> fitted {v['mean_fitted_error']:.4g},"
            f" tolerance {v['tolerance']})" if "mean_measured_error" in v else ""))
        if r.get("uncertainty", {}).get("warning"):
            print(f"  warning: {r['uncertainty']['warning']}")
    print(f"\nresult: {out / 'result.json'}" + (f"   view: python -m wrenorm view {out}" if (out / "recording.rrd").exists() or any(out.glob("*/recording.rrd")) else ""))


def cmd_flow(args) -> int:
    from .fit import prepare_out
    from .flow import POINTS_FILE, run_flow

    device = _device(args.device)
    mod = _task_module(args.task)
    if not hasattr(mod, "flow_problems"):
        raise InputError("flow", args.task, "this system has no resolution flow yet")
    if args.restarts < 2:
        raise InputError("--restarts", "restarts", "need at least 2 searches for a spread")
    problems = mod.flow_problems(args, device)
    _apply_parameter_set(problems, args)
    out = prepare_out(args.out or _default_out(f"flow-{args.task}"), resume=args.resume, force=args.force,
                      state=POINTS_FILE)
    flow = run_flow(problems, out, seed=args.seed, restarts=args.restarts, quiet=args.quiet, resume=args.resume,
                    generations=args.generations or getattr(mod, "FLOW_GENERATIONS", 60),
                    analytic=getattr(mod, "flow_analytic", None), record=not args.no_record)
    for pt in flow["points"]:
        line = ", ".join(f"{n}={p['fitted']:.5g}±{p['std_restarts']:.2g}" for n, p in pt["parameters"].items()
                         if not p["frozen"])
        print(f"{pt['resolution']}: {line}" + (f"  [undetermined: {', '.join(pt['undetermined'])}]" if pt["undetermined"] else ""))
    print(f"\nflow: {out / 'flow.json'}  plot: {out / 'flow.png'}")
    return 0


def cmd_view(args) -> int:
    run = args.run
    rrd = run / "recording.rrd" if run.is_dir() else run
    if not rrd.exists():
        raise InputError(str(run), "recording.rrd", "no recording in this run folder")
    try:
        import rerun  # noqa: F401  (the viewer ships with rerun-sdk)
    except ImportError:
        raise InputError("view", "rerun-sdk", "not installed: pip install 'wrenorm[viz]'") from None
    import subprocess

    files = [str(rrd)] + ([str(p) for p in sorted(run.glob("*/recording.rrd"))] if run.is_dir() else [])
    files = [f for f in files if Path(f).exists()]
    return subprocess.call([sys.executable, "-m", "rerun", *files])


def main(argv=None) -> int:
    import warp as wp

    # before any task module initialises Warp: no banner or missing-driver notice in users' output
    wp.config.log_level = wp.LOG_ERROR
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        if args.command == "fit":
            return cmd_fit(args)
        if args.command == "flow":
            return cmd_flow(args)
        if args.command == "view":
            return cmd_view(args)
        if args.command == "reference":
            return importlib.import_module("wrenorm.tasks.rope.reference.generate").run_reference(args)
        if args.command == "correct":
            return importlib.import_module("wrenorm.tasks.rope.control.correct_cli").run(args)
        if args.command == "sensitivity":
            return importlib.import_module("wrenorm.tasks.rope.control.sensitivity").run(args)
        if args.command == "bench":
            return importlib.import_module("wrenorm.bench").run(args)
    except InputError as e:
        print(f"wrenorm: error: {e}", file=sys.stderr)
        return 2
    except AllCandidatesFailed as e:
        print(f"wrenorm: fit failed: {e}", file=sys.stderr)
        return 3
    except KeyboardInterrupt:
        print("\nwrenorm: interrupted; continue with --resume --out <folder>", file=sys.stderr)
        return 130
    return 1
