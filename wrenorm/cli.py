"""Command line, built from the registry of systems (wrenorm.system):

    python -m wrenorm fit <system> ...        fit a system's effective parameters
    python -m wrenorm flow <system> ...       effective parameters against resolution
    python -m wrenorm <verb> <system> ...     a system's extra commands (e.g. `reference rope`)
    python -m wrenorm sweep SPEC.toml ...     many fits from one spec, as Ray tasks (wrenorm/sweep/)
    python -m wrenorm view RUN | bench

Every user mistake (bad file, bad option value) ends with one line naming the file or option, the field
and the problem, and exit code 2, never a traceback; Ctrl-C ends with exit 130.
"""
from __future__ import annotations

import argparse
import gc
import json
import os
import sys
import time
from pathlib import Path

from .errors import AllCandidatesFailed, InputError, warn
from .options import OneLineParser, add_list, add_number, number, path_kind
from .results import flow_point_std
from .system import resolve, systems

CORE_VERBS = ("fit", "flow", "view", "bench")
SEARCHES = ("cmaes", "least-squares", "cmaes+least-squares")


def _default_out(name: str) -> Path:
    return Path("runs") / f"{name}-{time.strftime('%Y%m%d-%H%M%S')}"


def _device(name: str) -> str:
    from .warp_init import init_warp

    wp = init_warp(name)
    if name.startswith("cuda") and not wp.is_cuda_available():
        raise InputError("--device", "device", "cuda requested but no CUDA device is available")
    return "cuda:0" if name.startswith("cuda") else "cpu"


def _run_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--out", type=Path, default=None,
                   help="run folder (default runs/<system>-<time>; a flow: runs/flow-<system>-<time>)")
    add_number(p, "--seed", default=0, lo=0, hi=2**31 - 1, integer=True, help="random seed")
    p.add_argument("--device", choices=["cpu", "cuda"], default="cpu")
    p.add_argument("--force", action="store_true", help="clear a non-empty --out folder that wrenorm wrote")
    p.add_argument("--resume", action="store_true", help="continue the interrupted run in --out")
    p.add_argument("--quiet", action="store_true", help="no progress output")
    p.add_argument("--no-record", action="store_true", help="skip the Rerun recording")
    add_list(p, "--free", default=[], metavar="NAME", unordered=True,
             help="also fit these parameters (expand the set when the held-out verdict says 'expand')")
    add_list(p, "--freeze", default=[], metavar="NAME", unordered=True,
             help="hold these parameters at their measured values")


def _fit_arguments(p: argparse.ArgumentParser, system) -> None:
    d = system.search
    _run_arguments(p)
    p.add_argument("--search", choices=list(SEARCHES), default=d.method,
                   help=f"how the parameters are searched (this system's default: {d.method}): cmaes for event and "
                        "contact observables, least-squares (Levenberg-Marquardt) for smooth residuals, "
                        "cmaes+least-squares for a global search polished locally")
    add_number(p, "--generations", default=d.generations, lo=1, hi=100000, integer=True, help="CMA-ES generations")
    add_number(p, "--popsize", default=d.popsize, lo=4, hi=1_000_000, integer=True,
               help="CMA-ES population", default_text=None if d.popsize else "pycma's for the dimension")
    add_number(p, "--sigma0", default=d.sigma0, lo=0.0, lo_open=True, hi=1.0,
               help="initial CMA-ES step in normalised [0, 1] coordinates")
    add_number(p, "--searches", default=None, lo=1, hi=65536, integer=True,
               help="seeded CMA-ES searches side by side in one batched evaluation; the best is kept and the spread "
                    f"of their optima reported (default by device kind: cpu 1, cuda {d.wide_searches} with "
                    f"{d.wide_popsize_factor}x pycma's population)")
    add_number(p, "--restarts", default=d.restarts, lo=0, hi=1000, integer=True,
               help="identifiability check after the fit: further seeded searches side by side (0: none; else >= 2)")
    add_number(p, "--polish", default=d.polish, lo=0, hi=10000, integer=True,
               help="L-BFGS evaluations on Warp-tape gradients after the search (systems with a tape; 0: none)")
    system.add_arguments(p)


def _flow_arguments(p: argparse.ArgumentParser, system) -> None:
    _run_arguments(p)
    add_list(p, "--resolutions", item=number(), default=None, metavar="R", help=system.flow.resolutions_help)
    add_number(p, "--restarts", default=4, lo=2, hi=1000, integer=True,
               help="seeded CMA-ES searches side by side per resolution (their spread is the uncertainty; what "
                    "fit calls --searches, not fit's --restarts, the check after a fit)")
    add_number(p, "--generations", default=system.flow.generations, lo=1, hi=100000, integer=True)
    add_number(p, "--popsize", default=16, lo=4, hi=1_000_000, integer=True, help="CMA-ES population per search")
    how = p.add_mutually_exclusive_group()
    how.add_argument("--together", dest="together", action="store_true", default=None,
                     help="every resolution's searches in one generation loop (default on cuda)")
    how.add_argument("--in-turn", dest="together", action="store_false",
                     help="one resolution after another, each starting from the previous result (default on cpu)")
    system.flow.add_arguments(p)


def _selected(argv: list[str]) -> tuple[str | None, str | None]:
    words = [a for a in argv if not a.startswith("-")]
    return (words[0] if words else None), (words[1] if len(words) > 1 else None)


def build_parser(argv: list[str] | None = None) -> argparse.ArgumentParser:
    """The parser; only the sub-command named in argv gets its options (so building it stays cheap)."""
    verb, name = _selected(list(sys.argv[1:] if argv is None else argv))
    registered = systems()
    p = OneLineParser(prog="wrenorm", description="Fit effective, resolution-dependent parameters of coarse robot "
                                                   "models (renormalisation) with batched Warp kernels.")
    p.add_argument("--verbose", action="store_true", help="show Warp's start-up and module-load lines")
    sub = p.add_subparsers(dest="command", required=True, parser_class=OneLineParser)
    fit = sub.add_parser("fit", help="fit a system's effective parameters")
    fit_sub = fit.add_subparsers(dest="system", required=True, parser_class=OneLineParser)
    for s in registered.values():
        sp = fit_sub.add_parser(s.name, help=s.help)
        if verb == "fit" and name == s.name:
            _fit_arguments(sp, s)
    flow = sub.add_parser("flow", help="effective parameters as functions of resolution, with uncertainty")
    flow_sub = flow.add_subparsers(dest="system", required=True, parser_class=OneLineParser)
    for s in registered.values():
        if s.flow is not None:
            sp = flow_sub.add_parser(s.name, help=f"resolution flow of the {s.name} system")
            if verb == "flow" and name == s.name:
                _flow_arguments(sp, s)
    extra: dict[str, argparse._SubParsersAction] = {}
    for s in registered.values():
        for c in s.commands:
            if c.verb not in extra:
                vp = sub.add_parser(c.verb, help=c.help)
                extra[c.verb] = vp.add_subparsers(dest="system", required=True, parser_class=OneLineParser)
            sp = extra[c.verb].add_parser(s.name, help=c.help)
            if verb == c.verb and name == s.name:
                resolve(c.add_arguments)(sp)
    sweep = sub.add_parser("sweep", help="many fits from one TOML spec, as Ray tasks (local or on a cluster)")
    if verb == "sweep":
        from .sweep.run import add_arguments as add_sweep_arguments

        add_sweep_arguments(sweep)
    view = sub.add_parser("view", help="open a run's recording in the Rerun viewer, or its report page")
    view.add_argument("run", type=Path)
    view.add_argument("--report", action="store_true",
                      help="(re)write the run's report.html from its result and open it in a browser where one is")
    view.add_argument("--web", action="store_true",
                      help="serve the recording to Rerun's web viewer in a browser instead of a native window (also "
                           "where this machine has no display)")
    bench = sub.add_parser("bench", help="throughput of each kernel and end-to-end fit times")
    if verb == "bench":
        from .bench import add_arguments

        add_arguments(bench)
    return p


def check_parameter_set(system, args) -> None:
    """--free / --freeze name no parameter twice and, where the system says its names without building a problem
    (System.parameter_names), only its parameters: refused before any reference is loaded."""
    from .system import parameter_names

    free, freeze = list(getattr(args, "free", [])), list(getattr(args, "freeze", []))
    both = sorted(set(free) & set(freeze))
    if both:
        raise InputError("--free/--freeze", ",".join(both), "named both free and frozen")
    names = parameter_names(system, args) if free or freeze else None
    for flag, given in (("--free", free), ("--freeze", freeze)):
        unknown = [n for n in given if names is not None and n not in names]
        if unknown:
            raise InputError(flag, ",".join(unknown), f"unknown parameter of {system.name}; known: {', '.join(names)}")


def _apply_parameter_set(problems, args) -> None:
    """--free / --freeze: the paper's procedure starts from the smallest set and grows it when
    held-out conditions say the omitted physics was not absorbed (names checked by check_parameter_set)."""
    free, freeze = list(args.free), list(args.freeze)
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


def _command_actions(args) -> list:
    """The options of the command `args` was parsed for (fit rope, flow pd, ...), from a parser built for it."""
    p = build_parser([args.command, args.system])
    for name in (args.command, args.system):
        sub = next(a for a in p._actions if isinstance(a, argparse._SubParsersAction))
        p = sub.choices[name]
    return p._actions


def _inputs(args) -> list:
    """Files and folders the command reads (never cleared by --force, hashed for --resume): every option whose metavar
    names FILE or DIR (`options.path_kind`, as the sweep finds them), so a system's own input option is one too."""
    out = []
    for action in _command_actions(args):
        kind, labels = path_kind(action)
        if kind is None:
            continue
        v = getattr(args, action.dest, None)
        out += [x for x in (v if isinstance(v, list) else [v])
                if isinstance(x, (str, Path)) and str(x) not in labels and Path(x).exists()]
    return out


def code_digest(system: str) -> str:
    """sha256 of the sources a fit's numbers come from (the engine's modules, the kernels, the system's package), so a
    resume after the code changed under the same version (a contributor iterating on a system) is refused rather
    than mixing two problems' losses."""
    import hashlib
    import importlib

    import wrenorm.kernels

    build = systems()[system].build
    module = build.partition(":")[0] if isinstance(build, str) else build.__module__
    roots = [(Path(__file__).parent, False), (Path(wrenorm.kernels.__file__).parent, True),
             (Path(importlib.import_module(module).__file__).parent, True)]
    h = hashlib.sha256()
    for root, recursive in roots:
        for f in sorted(root.rglob("*.py") if recursive else root.glob("*.py")):
            h.update(f.name.encode())
            h.update(f.read_bytes())
    return h.hexdigest()


def content_hashes(paths) -> dict:
    """sha256 of every input file (a folder: of its files, in name order), so a resumed run can tell that an input
    changed under the same name."""
    import hashlib

    out = {}
    for item in paths:
        p = Path(item)
        files = sorted(f for f in p.rglob("*") if f.is_file()) if p.is_dir() else [p]
        h = hashlib.sha256()
        for f in files:
            h.update(f.name.encode())
            with open(f, "rb") as fh:
                for block in iter(lambda: fh.read(1 << 20), b""):
                    h.update(block)
        out[str(item)] = h.hexdigest()
    return out


def search_width(system, device: str, searches: int | None, popsize: int | None, n_free: int) -> tuple:
    """(searches, popsize) of a fit: as given, else by the device's kind (see SearchDefaults)."""
    import math

    if searches is not None or not device.startswith("cuda"):
        return searches or 1, popsize
    d = system.search
    base = popsize or 4 + int(3 * math.log(max(n_free, 1)))  # pycma's default population for the dimension
    return d.wide_searches, (popsize if popsize is not None else d.wide_popsize_factor * base)


def command_line(args) -> str:
    """The command that reproduces this run (as typed, less --resume), for result.json and the report."""
    import shlex

    argv = [a for a in getattr(args, "_argv", sys.argv[1:]) if a != "--resume"]
    return "python -m wrenorm " + shlex.join(argv)


def _refuse_earlier_state(args, state_file: str) -> None:
    """A fit folder saved before the search log (its state rewritten whole every generation, `search_state.json`, in
    the folder or a sub-run's) cannot be continued: say so, rather than that no state was found."""
    from .runfolder import _is_run

    out = Path(args.out) if args.resume and args.out else None
    if out is None or not out.is_dir() or not _is_run(out):
        return
    folders = [out, *sorted(d for d in out.iterdir() if d.is_dir())]
    earlier = [d / "search_state.json" for d in folders if (d / "search_state.json").is_file()]
    if earlier and not any((d / state_file).is_file() for d in folders):
        raise InputError(str(earlier[0]), "--resume", "was saved by an earlier wrenorm (one state rewritten every "
                         f"generation, before {state_file}); it cannot be continued: run again")


def cmd_fit(args) -> int:
    from .fit import STATE_FILE, FitSettings, run_fits
    from .results import versions
    from .runfolder import prepare_out

    system = systems()[args.system]
    if args.restarts == 1:
        raise InputError("--restarts", "restarts", "needs 0 (none) or at least 2 searches for a spread")
    check_parameter_set(system, args)
    device = _device(args.device)
    problems = resolve(system.build)(args, device)
    _apply_parameter_set(problems, args)
    if args.search != "cmaes" and not all(p.has_residuals for p in problems):
        raise InputError("--search", "search", f"{args.search} needs residuals, which {args.system} does not expose")
    if args.search == "least-squares":
        typed = [f for f in ("--generations", "--popsize", "--sigma0", "--searches")
                 if any(a == f or a.startswith(f + "=") for a in getattr(args, "_argv", []))]
        if typed:
            warn(f"{', '.join(typed)}: CMA-ES settings, which --search least-squares (this fit's search) does not use; "
                 "--search cmaes or cmaes+least-squares uses them")
    searches, popsize = search_width(system, device, args.searches, args.popsize, len(problems[0].space.free))
    settings = FitSettings(seed=args.seed, generations=args.generations, popsize=popsize, sigma0=args.sigma0,
                           polish=args.polish, restarts=args.restarts, searches=searches, method=args.search)
    _refuse_earlier_state(args, STATE_FILE)
    inputs = _inputs(args)
    out = prepare_out(args.out or _default_out(args.system), resume=args.resume, force=args.force,
                      state=STATE_FILE, inputs=inputs, command=f"fit {args.system}")
    if not args.quiet:
        print(f"wrenorm fit {args.system}: writing {out}", file=sys.stderr)
    identity = {"system_options": _system_options(args), "inputs": content_hashes(inputs),
                "versions": {k: v for k, v in versions().items() if k in ("wrenorm", "warp-lang", "cma", "numpy")},
                "code": code_digest(args.system)}
    result = run_fits(problems, out, settings, resume=args.resume, record=not args.no_record, quiet=args.quiet,
                      identity=identity, command=command_line(args))
    _print_summary(result, out)
    return 0


_ENGINE_OPTIONS = {"command", "system", "out", "resume", "force", "quiet", "no_record", "device", "seed",
                   "generations", "popsize", "sigma0", "polish", "restarts", "searches", "search", "verbose",
                   "resolutions", "free", "freeze", "together"}


def _system_options(args) -> dict:
    """The options that shape the problem itself (a resumed run must keep them), as plain data."""
    out = {}
    for k, v in sorted(vars(args).items()):
        if k in _ENGINE_OPTIONS or k.startswith("_"):
            continue
        out[k] = [str(x) for x in v] if isinstance(v, (list, tuple)) else (str(v) if isinstance(v, Path) else v)
    return json.loads(json.dumps(out, default=str))


def _print_summary(result: dict, out: Path) -> None:
    runs = result.get("runs", [result])
    for r in runs:
        res = r["resolution"]
        print(f"\n{r['task']} at {res}: loss measured {r['loss']['measured']:.4g} -> fitted {r['loss']['fitted']:.4g}")
        unc = r.get("uncertainty") or {}
        # where the model misses its noise-normalised data by more than their noise, the std that takes the misfit as
        # noise too is the honest one to read beside the posterior's (the real fish: 3.7x wider; a review of stop 55
        # found only the narrower printed)
        wider = (unc.get("std_inflated_by_misfit") or {}) if (unc.get("chi2_per_dof") or 0.0) > 1.0 else {}
        for name, p in r["parameters"].items():
            tag = " (frozen)" if p["frozen"] else ""
            std = f" ± {p['std']:.3g}" if p.get("std") is not None else ""
            if std and wider.get(name) is not None:
                std += f" (± {wider[name]:.3g} from the data alone, the misfit taken as noise)"
            print(f"  {name:>10}: measured {p['measured']:<10.5g} fitted {p['fitted']:.5g}{std}{tag}")
        v = r["validation"]
        print(f"  held-out verdict: {v['verdict']}" + (
            f" (mean error measured {v['mean_measured_error']:.4g} -> fitted {v['mean_fitted_error']:.4g}; the "
            f"verdict's worst fitted {'no event, at least ' if v.get('worst_is_miss') else ''}"
            f"{v['worst_fitted_error']:.4g} ({v.get('worst_condition', '?')}) against its "
            f"tolerance {v.get('worst_tolerance', v['tolerance']):.4g})" if "worst_fitted_error" in v else ""))
        if v.get("note") and (v.get("flagged_conditions") or v.get("fitted_misses") or v.get("measured_misses")
                              or v["verdict"] == "unvalidated"):
            print(f"  {v['note']}")
        from .uncertainty import not_pinned_text

        for key, who in (("searches_spread", "searches side by side"), ("restarts", "further seeded searches")):
            spread = r.get(key) or {}
            if spread.get("optima"):
                rng = spread.get("held_out_mean_error_range")
                held = f"held-out mean error {rng[0]:.4g} .. {rng[1]:.4g}; " if rng else ""
                if spread.get("main_search_included"):  # a restart replaced the main search, which joined them
                    who = "seeded searches (the main one and its restarts)"
                print(f"  across {len(spread['optima'])} {who}: {held}"
                      f"not pinned: {not_pinned_text(spread, r.get('uncertainty') or {})}")
        for w in r.get("warnings", []):
            print(f"  warning: {w}")
    view = (out / "recording.rrd").exists() or any(out.glob("*/recording.rrd"))
    print(f"\nresult: {out / 'result.json'}" + (f"   view: python -m wrenorm view {out}" if view else ""))


def cmd_flow(args) -> int:
    from .flow import POINTS_FILE, run_flow
    from .runfolder import prepare_out

    system = systems()[args.system]
    # a flow's --axis A varies the option --A over --resolutions (the systems' flow options default it to None, so
    # a value typed for it is seen): refused rather than ignored
    axis = getattr(args, "axis", None)
    if axis and getattr(args, axis, None) is not None:
        raise InputError(f"--{axis}", axis, f"--axis {axis} varies it over --resolutions; give the values there (or "
                                            "vary the other axis)")
    check_parameter_set(system, args)
    device = _device(args.device)
    problems = resolve(system.flow.build)(args, device)
    _apply_parameter_set(problems, args)
    inputs = _inputs(args)
    out = prepare_out(args.out or _default_out(f"flow-{args.system}"), resume=args.resume, force=args.force,
                      state=POINTS_FILE, inputs=inputs, command=f"flow {args.system}")
    analytic = resolve(system.flow.analytic) if system.flow.analytic else None
    identity = {"system_options": _system_options(args), "inputs": content_hashes(inputs),
                "code": code_digest(args.system)}
    flow = run_flow(problems, out, seed=args.seed, restarts=args.restarts, popsize=args.popsize, quiet=args.quiet,
                    resume=args.resume, generations=args.generations, analytic=analytic, record=not args.no_record,
                    identity=identity, command=command_line(args),
                    together=device.startswith("cuda") if args.together is None else args.together)
    for pt in flow["points"]:
        std = {n: float("nan") if flow_point_std(p) is None else flow_point_std(p)  # None: a NaN read back
               for n, p in pt["parameters"].items()}
        line = ", ".join(f"{n}={p['fitted']:.5g}±{std[n]:.2g}" for n, p in pt["parameters"].items() if not p["frozen"])
        und = f"  [undetermined: {', '.join(pt['undetermined'])}]" if pt["undetermined"] else ""
        print(f"{pt['resolution']}: {line}{und}")
        if pt.get("warning"):
            print(f"  warning: {pt['warning']}")
    print(f"\nflow: {out / 'flow.json'}  plot: {out / 'flow.png'}")
    return 0


def cmd_view(args) -> int:
    run = args.run
    if not run.exists():  # "no recording in this run folder" had been said of a path that does not exist
        raise InputError(str(run), "run", "does not exist: give a run folder (or its recording.rrd)")
    if args.report:
        import webbrowser

        from wrenorm.viz.report import write_report

        if not run.is_dir():
            raise InputError(str(run), "run", "a run folder is needed for --report")
        page = write_report(run)
        print(page)
        if os.environ.get("DISPLAY") or sys.platform in ("darwin", "win32"):
            webbrowser.open(page.resolve().as_uri())
        return 0
    rrd = run / "recording.rrd" if run.is_dir() else run
    # a fit at several resolutions records one per sub-run (f_sim100/recording.rrd, ...) and none above them
    if not rrd.exists() and not (run.is_dir() and any(run.glob("*/recording.rrd"))):
        raise InputError(str(run), "recording.rrd", "no recording in this run folder")
    try:
        import rerun  # noqa: F401  (the viewer ships with rerun-sdk)
    except ImportError:
        raise InputError("view", "rerun-sdk", "not installed: pip install 'wrenorm[viz]'") from None
    import subprocess

    files = [str(rrd)] + ([str(p) for p in sorted(run.glob("*/recording.rrd"))] if run.is_dir() else [])
    files = [f for f in files if Path(f).exists()]
    for f in files:
        _check_recording(Path(f))
    if args.web:
        return subprocess.call([sys.executable, "-m", "rerun", *files, "--web-viewer"])
    if sys.platform.startswith("linux") and not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
        # the native viewer would fail here in many lines of windowing errors
        print(f"wrenorm: no display here (DISPLAY and WAYLAND_DISPLAY are unset), so the viewer has no window: run "
              f"`python -m wrenorm view {run} --web` and open the address it prints in a browser, or copy "
              f"{' '.join(files)} to a machine with a display and run `rerun FILE`", file=sys.stderr)
        return 1
    return subprocess.call([sys.executable, "-m", "rerun", *files])


RRD_MAGIC = b"RRF2"  # the first bytes of a Rerun recording (rerun-sdk 0.41's encoder; RRF0/RRF1: older Rerun,
# a later digit: a later format, left to the viewer)


def _check_recording(path: Path) -> None:
    """Refuse, before the viewer starts, a file that is not a Rerun recording this rerun-sdk reads."""
    if not path.is_file():
        raise InputError(str(path), "recording", "is not a file")
    with open(path, "rb") as f:
        head = f.read(len(RRD_MAGIC))
    if head in (b"RRF0", b"RRF1"):
        raise InputError(str(path), "recording", f"written by an older Rerun ({head.decode()}) that this rerun-sdk "
                                                 "cannot read: run the fit again to record it")
    if head[:3] == RRD_MAGIC[:3] and len(head) == len(RRD_MAGIC):  # this version's or a later one: the viewer says
        return
    start = f"starts with {head!r}" if head else "is empty"
    raise InputError(str(path), "recording", f"not a Rerun recording (.rrd files start with {RRD_MAGIC.decode()!r}; "
                                             f"this one {start})")


def _dispatch(args) -> int:
    if args.command == "fit":
        return cmd_fit(args)
    if args.command == "flow":
        return cmd_flow(args)
    if args.command == "view":
        return cmd_view(args)
    if args.command == "sweep":
        from .sweep.run import cmd_sweep

        return cmd_sweep(args)
    if args.command == "bench":
        from .bench import run

        return run(args)
    command = next(c for c in systems()[args.system].commands if c.verb == args.command)
    return resolve(command.run)(args)


def main(argv=None) -> int:
    from .runfolder import held, release

    previous_handlers, holding = None, held()
    try:
        args = build_parser(argv).parse_args(argv)
        args._argv = list(sys.argv[1:] if argv is None else argv)
        from .interrupt import install, resume_hint
        from .warp_init import init_warp

        previous_handlers = install(resume_hint(args))
        # before any task module initialises Warp: no banner or missing-driver line in users' output
        init_warp(getattr(args, "device", "cpu") or "cpu", args.verbose)
        return _dispatch(args)
    except SystemExit as e:  # argparse: --help (0) or a bad option (2, already reported on one line)
        return int(e.code or 0) if isinstance(e.code, int) or e.code is None else 2
    except InputError as e:
        print(f"wrenorm: error: {e}", file=sys.stderr)
        return 2
    except AllCandidatesFailed as e:
        print(f"wrenorm: fit failed: {e}", file=sys.stderr)
        return 3
    except KeyboardInterrupt:
        from .interrupt import exit_code, resume_hint

        print(f"\nwrenorm: interrupted{resume_hint(locals().get('args'))}", file=sys.stderr)
        return exit_code()
    except BrokenPipeError as e:  # `... | head`: the reader left; nothing went wrong here
        if e.filename is not None or sys.stdout.isatty():  # a file or a child's pipe: a real error, said
            print(f"wrenorm: error: {e.filename or 'pipe'}: {e.strerror or 'broken pipe'}", file=sys.stderr)
            return 2
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())  # Python's own flush at exit would hit the closed pipe again
        return 0
    except OSError as e:
        where = e.filename or "file system"
        print(f"wrenorm: error: {where}: {e.strerror or e.__class__.__name__}", file=sys.stderr)
        return 2
    finally:
        from .interrupt import restore

        restore(previous_handlers)
        release(keep=holding)
        # Python's last collections walk Warp's ~100k objects (half a second at exit): they live until exit anyway
        gc.freeze()
