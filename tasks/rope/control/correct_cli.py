"""`python -m wrenorm correct rope`: the correction loop end to end, with measured and with
renormalised (fitted) coarse-model parameters, writing correct.json, correct.png and a Rerun
recording (per trial: the real rope at its critical frame against the goal)."""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from wrenorm.errors import InputError, warn
from wrenorm.tasks.rope.options import DT
from wrenorm.tasks.rope.reference.generate import DEFAULT_SEGMENTS

SYSTEM = "rope"


def add_arguments(p: argparse.ArgumentParser) -> None:
    from wrenorm.options import add_list
    from wrenorm.tasks.rope.control.correct import DEFAULT_TOLERANCE, FD_STEP
    from wrenorm.tasks.rope.control.plan import DEFAULT_GENERATIONS, DEFAULT_POPSIZE
    from wrenorm.tasks.rope.control.secant import TRUST_NORMS

    p.add_argument("--out", type=Path, default=None, help="output folder (default runs/correct-rope-<time>)")
    p.add_argument("--seed", type=int, default=0, help="seed of the parameter fit and of --perturb")
    p.add_argument("--device", choices=["cpu", "cuda"], default="cpu")
    p.add_argument("--force", action="store_true", help="overwrite a non-empty --out folder")
    p.add_argument("--resume", action="store_true",
                   help="continue the interrupted correction in --out with its saved settings; real trials "
                        "already run are read back, not run again")
    p.add_argument("--quiet", action="store_true")
    p.add_argument("--no-record", action="store_true", help="skip the Rerun recording")
    p.add_argument("--variant", default="default",
                   help="real rope material (reference/materials.py): default, or one of the seven campaign ropes "
                        "stiff|soft|heavy|light|long|damped|heavy_end, or the flying knot's extremes thick|thread")
    p.add_argument("--real", choices=["fine", "newton", "coarse"], default="fine",
                   help="the real system: the fine rope of --engine, or a coarse chain with the FITTED parameters "
                        "(a quick stand-in whose answer is known); 'newton' is accepted for 'fine'")
    p.add_argument("--engine", default="newton",
                   help="simulator of the fine 'real' rope (correct.REAL_ROPES): newton (default) or mujoco (MuJoCo's "
                        "elastic rod; the goal is then that rope's own --goal throw)")
    p.add_argument("--goal", default="flick_high", help="built-in hand path whose real critical state is the goal")
    p.add_argument("--start", default="flick", help="built-in hand path the correction starts from (u = 0)")
    p.add_argument("--perturb", type=float, default=0.0,
                   help="add a seeded random command offset of this size (units of u) to the start")
    add_list(p, "--params", default=["renormalised-from-fitted"],
          metavar="renormalised-from-fitted|renormalised|fitted|measured|FILE",
          help="coarse models to steer with, each its own correction run: renormalised-from-fitted (the "
               "default, the best arm on held-out newton seeds; on MuJoCo's rod measured or renormalised do "
               "better: parameters refitted to the real trials after every "
               "trial, started from the values fitted to the rope's reference throws, prior at the measured "
               "values; steps in a trust region), renormalised (the same, started at the measured values), "
               "or fixed parameters stepped by --method: measured, fitted (once, to the rope's reference "
               "throws, before the trials), or a result.json")
    p.add_argument("--max-trials", type=int, default=10)
    p.add_argument("--tolerance", type=float, default=DEFAULT_TOLERANCE, help="goal reached at error <= this")
    p.add_argument("--method", choices=["gn", "plan", "qp"], default="gn",
                   help="gn: after the model's own first plan, trust-region Gauss-Newton steps through the chain's "
                        "sensitivity corrected by the real trials (renormalised: the refitted chain's, corrected by "
                        "all trials); plan: model-offset ILC, each command a batched CMA-ES plan on the coarse model "
                        "plus the offset learned from the real trials (renormalised: a plan on the refitted chain); "
                        "qp: linear trust-region step through the model's FD sensitivity re-measured at each best "
                        "command (fixed parameters only; renormalised arms then take gn steps)")
    p.add_argument("--no-plan-first", action="store_true",
                   help="(gn, plan) run the start command as trial 1 instead of the model's own plan from it")
    p.add_argument("--linearise-at", choices=("matched", "trial"), default="matched",
                   help="(gn steps) measure the chain's sensitivity where the chain reproduces the first hit's real "
                        "critical state (matched, space mapping's parameter extraction) or at that trial's own "
                        "command (trial)")
    p.add_argument("--first-step", choices=("gn", "space-mapping"), default="gn",
                   help="(gn steps, fixed parameters) trial 2 as a Gauss-Newton step (gn) or as space mapping's step: "
                        "the command moved by the offset of trial 1's match the other way (space-mapping)")
    p.add_argument("--start-pair", choices=("none", "first", "every"), default=None,
                   help="(gn steps) the real rope's critical state under the start command, recorded before the "
                        "trials (newton: the start throw's built-in reference; another engine: its fit throw where "
                        "one was recorded, else one run of it before the trials, as for the goal), as one more secant "
                        "pair correcting the chain's sensitivity, not counted as a trial: until the trials give a pair "
                        "of their own (first, the default with --method gn), at every step (every), or not (none, the "
                        "default with plan and qp)")
    p.add_argument("--popsize", type=int, default=DEFAULT_POPSIZE,
                   help="(plan; gn's first plan) CMA-ES population per search")
    p.add_argument("--generations", type=int, default=DEFAULT_GENERATIONS,
                   help="(plan; gn's first plan) CMA-ES generations per plan")
    p.add_argument("--radius", type=float, default=None,
                   help="initial trust radius (units of u; default 1.0 for gn and qp, 1.5 for plan)")
    p.add_argument("--reg", type=float, default=None,
                   help="gn and qp: Levenberg/Tikhonov weight relative to mean diag(F^T F) (default 1e-2); plan: "
                        "weight of |u - u_best|^2 (default 1e-4)")
    p.add_argument("--fd-step", type=float, default=FD_STEP, help="(qp) finite-difference step (units of u)")
    p.add_argument("--secant", action=argparse.BooleanOptionalAction, default=None,
                   help="learn how the model's error changes with u from pairs of real trials (gn: ridge over all "
                        "pairs toward the chain's sensitivity; plan, qp: Broyden); "
                        "default on for gn and plan, off for qp; gn without it steps through the chain's sensitivity "
                        "alone")
    p.add_argument("--model-place", action="store_true",
                   help="(plan) predict the contact place with the coarse chain too (default: from the trials)")
    p.add_argument("--segments", type=int, default=10,
                   help="links of the coarse chain (10 = the flying knot's 11 point masses; any of 3-63)")
    p.add_argument("--prior-scale", type=float, default=None,
                   help="(renormalised) Gaussian prior of each refitted parameter around its measured value, as a "
                        "fraction of its search box (log box for log-scale parameters); default "
                        "renormalise.PRIOR_SCALE")
    p.add_argument("--decay", type=float, default=None,
                   help="(renormalised) weight of a trial per trial of age in the refit, in (0, 1]; default "
                        "renormalise.DECAY")
    p.add_argument("--min-radius", type=float, default=None,
                   help="(adaptive trust region) smallest trust radius (units of u); default renormalise.MIN_RADIUS")
    p.add_argument("--trust-region", choices=("fixed", "adaptive", "by-arm"), default="by-arm",
                   help="(gn, renormalised) fixed: every step may go --radius from the best command; adaptive: the "
                        "radius shrinks after a poor prediction and grows after a good one, between --min-radius and "
                        "--max-radius; by-arm (default): fixed for fixed parameters, adaptive for renormalised ones")
    p.add_argument("--velocity-weight", type=velocity_weight_arg, default="by-arm",
                   help="(gn steps) weight of the velocity rows in each Gauss-Newton step's least-squares problem "
                        "(the step only: trials are accepted and reported on the observable's error), a number >= 0; "
                        "by-arm (default): secant.VELOCITY_WEIGHT (0.5) for fixed parameters, 1 for renormalised ones")
    p.add_argument("--velocity-modes", type=velocity_modes_arg, default="by-arm",
                   help="(gn steps) keep the velocity rows of each Gauss-Newton step's least-squares problem to the "
                        "velocity profile's first N Legendre modes in arc length on each axis, N in 1-21 (the step "
                        "only: trials are accepted and reported on the observable's error); all: every row; by-arm "
                        "(default): secant.VELOCITY_MODES (2) for renormalised parameters, all for fixed ones")
    p.add_argument("--trust-norm", choices=TRUST_NORMS, default="box",
                   help="(gn steps) the trust region's shape: box (default), the radius bounds each coordinate of the "
                        "step; ball, the step's Euclidean length is at most secant.BALL_PER_RADIUS (2.5) x the radius")
    p.add_argument("--secant-locality", type=secant_locality_arg, default="none",
                   help="(gn steps) weigh each secant pair in the ridge fit of the sensitivity by its distance from "
                        "the best command: pairs within L units of u count fully, farther ones as (L / distance)^2; "
                        "none (default): every pair alike")
    p.add_argument("--first-plan-reg", type=first_plan_reg_arg, default="by-method",
                   help="weight of the squared distance (units of u) from the start command in trial 1's plan on the "
                        "chain: the chain reproduces the goal about as well along a long stretch of commands, and "
                        "this picks one nearer the start; a number >= 0, by-method (default): secant.FIRST_PLAN_REG "
                        "(0.003) where Gauss-Newton steps follow, else as-plans; as-plans: the loop's other plans' "
                        "weight (1e-4, a tie-breaker; the plan loop's --reg), as every run before the option. A run "
                        "that plans no trial 1 (qp, --no-plan-first) has none; refused where no run here plans one")
    p.add_argument("--first-plan-offset", choices=("none", "start"), default="none",
                   help="plan trial 1 on the chain alone (none, the default) or on the chain plus the real rope's "
                        "offset from it under the start command (start: output space mapping from the start throw "
                        "recorded before the trials, the one the start pair uses; measured on unseen seeds and not "
                        "the default). A run that plans no trial 1 (qp, --no-plan-first) has none; start is refused "
                        "where no run here plans one")
    p.add_argument("--max-radius", type=float, default=None,
                   help="(adaptive trust region) largest trust radius (units of u); default twice the command box's "
                        "bound")
    p.add_argument("--refit-generations", type=int, default=None,
                   help="(renormalised) CMA-ES generations of each refit; default renormalise.REFIT_GENERATIONS")
    p.add_argument("--dt", type=float, default=0.005, help="coarse time step (s)")
    p.add_argument("--fine-segments", type=int, default=DEFAULT_SEGMENTS,
                   help="segments of the fine rope; on newton another value than the built-in references' "
                        f"{DEFAULT_SEGMENTS} records the goal, start and fit throws on that rope before the trials")
    # what newton runs at another --fine-segments did before they recorded their own throws (the built-in
    # 64-segment rod's goal and throws, trials at N): kept so that such a run's command line repeats it
    p.add_argument("--builtin-throws", action=argparse.BooleanOptionalAction, default=None, help=argparse.SUPPRESS)
    p.add_argument("--fit-generations", type=int, default=30, help="CMA-ES generations of the renormalising fit")
    p.add_argument("--fit-throws", choices=("real", "newton"), default=None,
                   help="(fitted, renormalised-from-fitted) the reference throws the chain is fitted to before the "
                        "trials: the real rope's own (real, the default: newton's built-in throws, or on another "
                        "engine one run of each before the trials, kept in OUT/fit-throws), leaving out the goal's "
                        "throw and any throw that never hits itself; or the newton rope's built-in throws whatever "
                        "the engine (newton: a model of another simulator's rope, as the runs before this option)")


def _builtin_reference(name: str, variant: str, progress):
    """The fine rope's built-in throw under a named hand path (the goal, the start throw), generated when not cached."""
    from wrenorm.tasks.rope.reference.generate import builtin_reference_path, generate_reference, load_reference

    p = builtin_reference_path(name, variant)
    if p.exists():
        return load_reference(p)
    progress(f"generating the {variant} rope's {name} throw into {p}")
    return generate_reference(name, p, variant=variant)


def builtin_is_the_real_rope(settings: dict) -> bool:
    """Whether newton's built-in references are the rope that a run with these settings (vars(args), or a saved
    settings.json) steers: newton at their resolution."""
    return (settings.get("engine", "newton") == "newton"
            and settings.get("fine_segments", DEFAULT_SEGMENTS) == DEFAULT_SEGMENTS)


def builtin_throws_of(saved: dict) -> bool:
    """Whether a saved run took its goal, start and fit throws from newton's built-in references: as its settings say,
    or, saved before they said it, whenever it ran on newton (whatever its --fine-segments)."""
    said = saved.get("builtin_throws")
    return bool(said) if said is not None else saved.get("engine", "newton") == "newton"


def _goal_source(args) -> str:
    if args.real != "fine":
        return "the coarse stand-in under the goal path"
    return "built-in reference" if args.builtin_throws else "recorded on the real rope before the trials (OUT/goal)"


def _fit_throws(args, goal_path, out, progress) -> tuple[dict, dict, dict]:
    """The reference throws the chain is fitted to before the trials (name -> RopeReference), those left out with
    the reason, and every throw recorded (the start pair reuses the start throw's). --fit-throws real: the real
    rope's own, i.e. newton's built-in (64-segment) throws or, on another engine, one run of each before the trials
    (kept in OUT/fit-throws, read back on resume); the goal's throw is left out (a fit to the rope under the goal
    command would hand the loop the answer), and so is a throw that never hits itself (it has no critical state to
    fit). --fit-throws newton: newton's built-in throws whatever the engine."""
    from wrenorm.tasks.rope import observable as crit
    from wrenorm.tasks.rope.control.correct import StoredTrials, real_rope_class
    from wrenorm.tasks.rope.reference.generate import DEFAULT_DURATION, builtin_references
    from wrenorm.tasks.rope.reference.paths import FIT_PATHS, get_hand_path

    own = args.fit_throws == "real" and args.real == "fine"
    if not own or args.builtin_throws:
        newton = dict(zip(FIT_PATHS, builtin_references("fit", args.variant, progress=progress)))
        if not own:
            return newton, {}, newton
    paths = {name: get_hand_path(name, "--fit-throws") for name in FIT_PATHS}
    dropped = {name: "the goal's own throw" for name, path in paths.items()
               if np.array_equal(path.control_points, goal_path.control_points)
               and np.array_equal(path.durations, goal_path.durations)}
    names = [name for name in FIT_PATHS if name not in dropped]
    if args.builtin_throws:
        recorded = {name: newton[name] for name in names}
    else:
        rope = StoredTrials(real_rope_class(args.engine)(args.variant, args.fine_segments, DEFAULT_DURATION,
                                                         args.device), out / "fit-throws")
        progress(f"recording the fit throws {', '.join(names)} on the {args.engine} rope ({args.fine_segments} "
                 "segments) before the trials")
        recorded = {name: rope(paths[name]) for name in names}
    throws = {}
    for name, ref in recorded.items():
        if crit.from_reference(ref).hit[0]:
            throws[name] = ref
        else:
            dropped[name] = f"the {args.engine} rope never hits itself under it"
    if not throws:
        raise InputError("--fit-throws", "fit_throws", f"none of the fit throws {', '.join(FIT_PATHS)} can be fitted "
                         f"on the {args.variant} rope ({'; '.join(f'{n}: {w}' for n, w in dropped.items())}); "
                         "use --params measured, renormalised or a result.json, or --fit-throws newton (with --force)")
    return throws, dropped, recorded


def start_pair_for(start_pair: str | None, method: str) -> str:
    """--start-pair as run: left out, "first" with Gauss-Newton steps (measured in the README) and "none" with the
    other methods, which would ignore it; named with another method, refused."""
    if start_pair is None:
        return "first" if method == "gn" else "none"
    if start_pair != "none" and method != "gn":
        raise InputError("--start-pair", "start_pair", "the start pair corrects the Gauss-Newton steps' sensitivity: "
                                                       f"it needs --method gn, not {method}")
    return start_pair


def _start_recording(args, real, start_path, out, progress, fit_recorded=None):
    """The real rope under the start command, recorded before the trials, and where it came from: on newton the start
    throw's built-in reference (what the fitted parameters were fitted to), on another engine the fit throw of the
    same command where one was recorded, else one run of it, kept in OUT/start so a resumed run reads it back."""
    if args.real == "fine" and args.builtin_throws:
        return _builtin_reference(args.start, args.variant, progress), "built-in reference"
    if args.real == "fine" and args.fit_throws == "real" and args.start in (fit_recorded or {}):
        return fit_recorded[args.start], "the fit throw recorded before the trials"
    from wrenorm.tasks.rope.control.correct import StoredTrials

    progress(f"recording the start throw {args.start} before the trials")
    source = f"one {args.engine if args.real == 'fine' else 'coarse'} run before the trials"
    return StoredTrials(real.real, out / "start")(start_path), source


def _check_arguments(args) -> None:
    """Every option checked before a folder is made or a rope thrown (a bad one exits 2 naming it), and the ones
    left to the run's kind filled in: --start-pair by method, --real newton as fine, --fit-throws by real rope,
    --builtin-throws by rope and engine."""
    from wrenorm.cli import _device
    from wrenorm.tasks.rope.control.command import DEFAULT_BOUND
    from wrenorm.tasks.rope.control.correct import check_first_step, real_rope_class, trust_region_for
    from wrenorm.tasks.rope.reference.materials import get_variant

    get_variant(args.variant)
    args.device = _device(args.device)
    if not 1 <= args.max_trials <= 100:
        raise InputError("--max-trials", "max_trials", f"{args.max_trials} is outside [1, 100]")
    if not (np.isfinite(args.tolerance) and args.tolerance > 0):
        raise InputError("--tolerance", "tolerance", f"must be a finite number > 0, got {args.tolerance}")
    box = 2 * DEFAULT_BOUND  # the command box's width: no step is longer (1e300 had wasted a trial, or an SVD failed)
    for flag, value, zero_allowed, most in (("--radius", args.radius, False, box),
                                            ("--fd-step", args.fd_step, False, box), ("--reg", args.reg, True, 1e6)):
        if value is not None and not (np.isfinite(value) and (value >= 0 if zero_allowed else value > 0)
                                      and value <= most):
            least = ">=" if zero_allowed else ">"
            raise InputError(flag, flag[2:].replace("-", "_"), f"must be a finite number {least} 0 and at most "
                                                               f"{most:g}, got {value}")
    if not (np.isfinite(args.perturb) and 0 <= args.perturb <= 1e3):  # a larger one is clipped to the box, and said;
        # 1e300 overflowed on its way there
        raise InputError("--perturb", "perturb", f"must be a finite number in [0, 1000] (units of u), got "
                                                 f"{args.perturb}")
    if isinstance(args.velocity_weight, float) and args.velocity_weight > 1e3:
        raise InputError("--velocity-weight", "velocity_weight", f"must be at most 1000, got {args.velocity_weight:g}")
    if not (args.dt is None or DT[0] <= args.dt <= DT[1]):  # the chain checked it only after the goal throw had run
        raise InputError("--dt", "dt", f"{args.dt:g} s is outside [{DT[0]:g}, {DT[1]:g}] s")
    if not 4 <= args.fine_segments <= 1024:  # before either engine builds its rod (MuJoCo's checks divide by it)
        raise InputError("--fine-segments", "fine_segments", f"{args.fine_segments} is outside [4, 1024]")
    if not 1 <= args.fit_generations <= 1000:
        raise InputError("--fit-generations", "fit_generations", f"must be in [1, 1000], got {args.fit_generations}")
    if not (4 <= args.popsize <= 4096 and 1 <= args.generations <= 1000):
        raise InputError("--popsize/--generations", "value", "need popsize in [4, 4096] and generations in [1, 1000]")
    if args.seed < 0:
        raise InputError("--seed", "seed", f"must be >= 0, got {args.seed}")
    if not isinstance(args.params, list) or len(set(args.params)) != len(args.params):  # a resumed run's settings
        raise InputError("--params", "params", f"a list without repeats expected, got {args.params!r}")
    for label in args.params:
        if label not in RUN_LABELS and not Path(label).is_file():
            raise InputError(label, "--params", f"is neither one of {', '.join(RUN_LABELS)} nor an existing "
                                                "result.json")
    names = [run_name(label) for label in args.params]
    for i, name in enumerate(names):  # every fit writes result.json: two of them had one arm's records overwritten
        if name in names[:i]:
            other = args.params[names.index(name)]
            raise InputError(args.params[i], "--params", f"would be named {name!r} in real-trials/ and the report, as "
                                                         f"{other} is: one arm's trial records would overwrite the "
                                                         "other's; copy one under another name (fit-a.json)")
    if args.prior_scale is not None and not 0 < args.prior_scale <= 100:
        raise InputError("--prior-scale", "prior_scale", f"must be in (0, 100], got {args.prior_scale:g}")
    if args.decay is not None and not 0 < args.decay <= 1:
        raise InputError("--decay", "decay", f"must be in (0, 1], got {args.decay:g}")
    if args.min_radius is not None and not 0 < args.min_radius <= 6:
        raise InputError("--min-radius", "min_radius", f"must be in (0, 6], got {args.min_radius:g}")
    if args.max_radius is not None and not 0 < args.max_radius <= 6:
        raise InputError("--max-radius", "max_radius", f"must be in (0, 6], got {args.max_radius:g}")
    _check_step_options(args)
    _check_first_plan(args)
    arms = {label: _trust_options(args, label) for label in args.params}
    if args.trust_region != "by-arm" and not any(arms.values()):
        raise InputError("--trust-region", "trust_region", f"--method {args.method} with fixed parameters has no "
                                                           "trust region of these")
    if (args.min_radius is not None or args.max_radius is not None) and not _adapts(arms):
        raise InputError("--min-radius/--max-radius", "trust_region", "bound the adaptive trust region, and no run "
                                                                      "here has one (--trust-region adaptive)")
    for label, options in arms.items():  # the radii's own bounds, checked before any real run
        if options:
            trust_region_for(*_arm_method(args, label), options["trust_region"], args.radius, options["min_radius"],
                             options["max_radius"], DEFAULT_BOUND)
    if args.refit_generations is not None and not 1 <= args.refit_generations <= 1000:
        raise InputError("--refit-generations", "refit_generations",
                         f"must be in [1, 1000], got {args.refit_generations}")
    check_first_step(args.first_step, args.method == "gn", args.linearise_at)
    _check_fixed_parameter_options(args)
    args.start_pair = start_pair_for(args.start_pair, args.method)
    if not 3 <= args.segments <= 63:
        raise InputError("--segments", "segments", f"{args.segments} is outside [3, 63] (links of the coarse chain)")
    if args.real == "newton":
        args.real = "fine"
    if args.real == "coarse" and args.fit_throws == "real":
        raise InputError("--fit-throws", "fit_throws", "the coarse stand-in is the chain fitted to newton's built-in "
                                                       "throws; it has no throws of its own (leave the option out)")
    args.fit_throws = args.fit_throws or ("real" if args.real == "fine" else "newton")
    real_rope_class(args.engine)
    if args.engine == "mujoco" and args.real == "fine":  # before any folder or throw: MuJoCo's rod has a finest mesh
        from wrenorm.tasks.rope.reference.mujoco import check_resolution

        try:
            check_resolution(get_variant(args.variant), args.fine_segments)
        except InputError as e:
            raise InputError("--fine-segments", "fine_segments", e.problem) from None
    if args.builtin_throws is None:
        args.builtin_throws = builtin_is_the_real_rope(vars(args))
    elif args.builtin_throws and args.engine != "newton":
        raise InputError("--builtin-throws", "builtin_throws", f"the built-in throws are newton's, not {args.engine}'s")


def run(args) -> int:
    from wrenorm.cli import command_line
    from wrenorm.fit import write_report_or_warn
    from wrenorm.results import versions, write_atomic, write_json
    from wrenorm.runfolder import prepare_out
    from wrenorm.tasks.rope import observable as crit
    from wrenorm.tasks.rope.control.command import CommandSpace
    from wrenorm.tasks.rope.control.correct import (
        CoarseRope,
        StoredTrials,
        fit_parameters,
        parameters_from_file,
        real_rope_class,
        trial_rows,
    )
    from wrenorm.tasks.rope.problem import RopeProblem
    from wrenorm.tasks.rope.reference.paths import get_hand_path

    def progress(msg):
        if not args.quiet:
            print(msg, file=sys.stderr, flush=True)

    if args.resume:
        _restore_settings(args)
    _check_arguments(args)
    start_path, goal_path = get_hand_path(args.start, "--start"), get_hand_path(args.goal, "--goal")
    if args.start == args.goal and args.perturb == 0:
        raise InputError("--start", "start", f"is the goal's own throw ({args.goal}): its command already reaches the "
                                             "goal, so there is nothing to correct (choose another --start, or "
                                             "--perturb the start)")
    space = CommandSpace(start_path)
    out = prepare_out(args.out or Path("runs") / f"correct-rope-{time.strftime('%Y%m%d-%H%M%S')}",
                      resume=args.resume, force=args.force, state=SETTINGS_FILE)
    if not args.resume:
        saved = {k: v for k, v in vars(args).items() if k not in _NOT_SAVED}
        from wrenorm.tasks.rope.control.secant import VELOCITY_MODES

        saved[BY_ARM_MODES_KEY] = VELOCITY_MODES  # what by-arm means for the renormalised arms today
        saved[PARAMS_HASHES_KEY] = _params_hashes(args)
        write_json(out / SETTINGS_FILE, saved | {DIGEST_KEY: _settings_digest(saved)})
    t_all = time.perf_counter()

    if args.real == "fine" and not args.builtin_throws:
        # a rope without built-in references reaches its own goal state: the goal throw on it (kept with the trials)
        from wrenorm.tasks.rope.reference.generate import DEFAULT_DURATION

        progress(f"the goal: {args.variant} rope under {args.goal} on {args.engine} ({args.fine_segments} segments)")
        goal_ref = StoredTrials(real_rope_class(args.engine)(args.variant, args.fine_segments, DEFAULT_DURATION,
                                                             args.device), out / "goal")(goal_path)
    else:
        goal_ref = _builtin_reference(args.goal, args.variant, progress)
    problem = RopeProblem([goal_ref], segments=args.segments, dt=args.dt, device=args.device, names=[args.goal])
    # read before any trial: a bad file in a later arm was found after the earlier arms' trials
    from_files = {label: parameters_from_file(label, problem) for label in args.params if label not in RUN_LABELS}
    fitted, fit_info, fit_recorded = None, None, {}
    if "fitted" in args.params or "renormalised-from-fitted" in args.params or args.real == "coarse":
        fit_throws, dropped, fit_recorded = _fit_throws(args, goal_path, out, progress)
        progress(f"renormalising: CMA-ES fit of the {args.segments}-link chain to the {args.variant} rope's throws "
                 f"{', '.join(fit_throws)}" + "".join(f"; {n} left out: {why}" for n, why in dropped.items()))
        fitted, fit_info = fit_parameters(args.variant, args.segments, args.dt, args.seed, args.fit_generations,
                                          args.device, progress, throws=fit_throws)
        fit_info |= {"throws_from": args.fit_throws, "left_out": dropped,
                     "engine": args.engine if args.fit_throws == "real" else "newton"}
    if args.real == "fine":
        horizon = min(float(goal_ref.time[-1]), float(crit.from_reference(goal_ref).time[0]) + 0.5)
        real = real_rope_class(args.engine)(args.variant, args.fine_segments, horizon, args.device)
        real_doc = (f"{args.engine} rope, variant {args.variant}, {args.fine_segments} segments, {horizon:.2f} s "
                    "per trial")
    else:
        real = CoarseRope(problem, fitted)
        goal_ref = real(goal_path)
        real_doc = f"coarse chain with the fitted {args.variant} parameters (stand-in for the real rope)"
    goal = crit.Target.from_reference(goal_ref)
    real = StoredTrials(real, out / "real-trials")
    if real.folder.exists() and any(real.folder.iterdir()):
        progress(f"resuming: {len(list(real.folder.glob('trial-*.npz')))} real trials on record in {real.folder}")

    recorded, start_record, start_state = [], None, None
    if args.start_pair != "none" or any(_first_plan_offset(args, label) for label in args.params):
        start_ref, source = _start_recording(args, real, start_path, out, progress, fit_recorded)
        start_state = crit.from_reference(start_ref)
        recorded = [(np.zeros(space.dim), start_state)] if args.start_pair != "none" else []
        start_record = {"path": args.start, "hit": bool(start_state.hit[0]),
                        "error": float(goal.terms(start_state)["total"][0]), "source": source}
        if not start_state.hit[0]:
            lost = (["no start pair"] if recorded else []) + (["no offset for trial 1"] if args.first_plan_offset ==
                                                              "start" else [])
            progress(f"  the rope under the start command {args.start} never hits itself: {' and '.join(lost)}")
    u0 = np.zeros(space.dim)
    if args.perturb > 0:
        drawn = np.random.default_rng(args.seed).normal(size=space.dim) * args.perturb
        u0, _ = space.limit_step(np.zeros(space.dim), drawn)
        if not np.allclose(u0, drawn):
            warn(f"--perturb {args.perturb:g}: the perturbed start left the command box or the hand's limits and was "
                 f"clipped and shortened to {np.linalg.norm(u0) / np.linalg.norm(drawn):.3g} of its length (largest "
                 f"component {np.abs(u0).max():.3g} units of u; correct.json's start.command_u is the one used)")
    try:
        u_goal = space.encode(goal_path).tolist()
    except InputError:
        u_goal = None

    runs = {label: _correct_arm(args, label, real, problem, from_files.get(label, fitted), space, goal, u0, recorded,
                                start_state, progress)
            for label in args.params}

    result = {
        "schema": "wrenorm.correct/1", "system": SYSTEM, "variant": args.variant, "real_system": real_doc,
        "goal": {"path": args.goal, "from": _goal_source(args), "critical_time": float(goal.state.time[0]),
                 "contact_arclength": goal.state.s[0].tolist(), "command_u_of_goal_path": u_goal},
        "start": {"path": args.start, "perturb": args.perturb, "command_u": u0.tolist(),
                  "recorded_pair": start_record},
        "command": {"names": space.names, "scales": space.scales.tolist(), "bound": space.bound,
                    "max_speed": space.max_speed, "max_acceleration": space.max_acceleration,
                    "meaning": "u = waypoint offsets / scale (positions m, velocities m/s) and log duration ratios"},
        "tolerance": args.tolerance, "max_trials": args.max_trials,
        "error_meaning": "rope.py's weighted critical-state error to the goal: shape/length + 0.1 velocity/speed + "
                         "time/t_goal + 0.5 contact place; a trial without self-collision costs >= 5",
        "model": {"segments": args.segments, "dt": args.dt, "fit": fit_info},
        "settings": _settings_record(args),
        "runs": {label: {k: v for k, v in r.items() if k != "trials"}
                 | {"trials": trial_rows(r["trials"], space, problem.space)} for label, r in runs.items()},
        "real_runs": real.runs, "real_trials_read_back": real.reused, "real_trials_blown_up": real.unstored,
        "real_wall_s": real.wall_s,
        "wall_seconds": time.perf_counter() - t_all, "versions": versions(), "device": args.device,
        "command_line": reproduce_command(args) if args.resume else command_line(args),
    }
    write_json(out / "correct.json", result)
    write_atomic(out / "report.md", report_markdown(result))
    _plot(out / "correct.png", runs, args)
    write_report_or_warn(out, result, args.quiet)
    if not args.no_record:
        _record(out / "recording.rrd", runs, goal, args, goal_ref=goal_ref, real=real, space=space)
    for label, r in runs.items():
        verdict = f"reached in {r['trials_to_tolerance']} trials" if r["success"] else \
            f"not reached in {r['trials_used']} trials (best {r['best_error']:.4f})"
        errs = " ".join(f"{t.total:.3f}" for t in r["trials"])
        print(f"{label:>9}: {verdict}; errors {errs}")
    print(f"\nresult: {out / 'correct.json'}  plot: {out / 'correct.png'}")
    return 0


def _correct_arm(args, label: str, real, problem, fitted, space, goal, u0, recorded, start_state, progress) -> dict:
    """One arm of the run (its parameters: measured, fitted, renormalised, ... or a file, whose values `fitted` is
    then): correct() on the real rope with this arm's method and step options, each trial written to real-trials/ as
    soon as it is complete."""
    from wrenorm.progress import Progress
    from wrenorm.results import write_json
    from wrenorm.tasks.rope.control.correct import CoarseModel, correct, trial_row

    method, steps = _arm_method(args, label)
    name = run_name(label)

    bar = Progress(args.max_trials, f"correct rope, {name}", quiet=args.quiet, unit="trials")
    best = [np.inf]

    def on_trial(trial):
        # what this trial did and why, as soon as its record is complete (atomic; a resumed run rewrites it)
        write_json(real.folder / f"{name}-trial-{trial.index + 1:02d}.json",
                   {"run": name, "variant": args.variant} | trial_row(trial, space, problem.space))
        best[0] = min(best[0], trial.total)
        bar.update(1, force=True, error=f"{trial.total:.3f}", best=f"{best[0]:.3f}")

    if label in ("measured", "renormalised"):
        values = problem.space.measured
    else:  # fitted, renormalised-from-fitted, or a file's values
        values = fitted
    model = CoarseModel(problem, values, space, label)
    progress(f"correcting with the {label}-parameter coarse model (goal {args.goal}, start {args.start}, "
             f"{args.variant} rope)")
    res = correct(real, model, goal, u0, max_trials=args.max_trials, tolerance=args.tolerance,
                  radius=args.radius, reg=args.reg, fd_step=args.fd_step, secant=args.secant,
                  method=method, plan_first=not args.no_plan_first, seed=args.seed, popsize=args.popsize,
                  generations=args.generations, freeze_place=not args.model_place, progress=progress,
                  on_trial=on_trial, prior_scale=args.prior_scale, decay=args.decay,
                  refit_generations=args.refit_generations, **_trust_options(args, label),
                  prior_centre=problem.space.measured if method == "renormalise" else None, steps=steps,
                  linearise_at=args.linearise_at, first_step=args.first_step, recorded=recorded,
                  recorded_until="every" if args.start_pair == "every" else "first",
                  first_plan_reg=_first_plan_reg(args, label),
                  first_plan_offset=((np.zeros(space.dim), start_state) if _first_plan_offset(args, label)
                                     else None), **_step_options(args, label))
    bar.close()
    res["parameters"] = problem.space.as_dict(values)
    return res


def _settings_record(args) -> dict:
    """correct.json's "settings": the options the run was made with, as given (by-arm and unset ones as such)."""
    return {"method": args.method, "plan_first": not args.no_plan_first, "linearise_at": args.linearise_at,
            "first_step": args.first_step, "start_pair": args.start_pair,
            "radius": args.radius if args.radius is not None else _default("radius", args.method),
            "reg": args.reg if args.reg is not None else _default("reg", args.method),
            "fd_step": args.fd_step, "seed": args.seed,
            "secant": args.secant if args.secant is not None else args.method in ("plan", "gn"),
            "popsize": args.popsize, "generations": args.generations,
            "place_from": "coarse model" if args.model_place else "trials", "engine": args.engine,
            "real": args.real, "segments": args.segments, "prior_scale": args.prior_scale,
            "decay": args.decay, "refit_generations": args.refit_generations,
            "trust_region": args.trust_region, "min_radius": args.min_radius, "max_radius": args.max_radius,
            "velocity_weight": args.velocity_weight, "velocity_modes": args.velocity_modes,
            "trust_norm": args.trust_norm, "secant_locality": args.secant_locality,
            "first_plan_reg": args.first_plan_reg, "first_plan_offset": args.first_plan_offset,
            "fit_throws": args.fit_throws,
            "fine_segments": args.fine_segments, "builtin_throws": args.builtin_throws,
            "note": "method applies to the fixed-parameter runs (measured, fitted, FILE); the renormalised "
                    "run refits and plans in a trust region"}


TRIAL_COLUMNS = ["trial", "error", "predicted", "model floor", "model alone", "accepted", "contact t / place",
                 "plan radius", "rho -> radius", "refit loss", "parameters changed (x measured)"]


def last_floor(r: dict) -> dict | None:
    """The corrected model's floor at the run's last step (secant.model_floor), where its steps record one."""
    floors = [(t.get("next_step") or {}).get("model_floor") for t in r.get("trials", [])]
    return next((f for f in reversed(floors) if f), None)


def sweep_rows(result: dict) -> list[dict]:
    """A sweep's rows of one finished correction (wrenorm.sweep.table): one per arm, the run's outcome as the campaign
    table counts it (trials to the tolerance, max_trials + 1 where never reached), the best error, trial 1's, and the
    corrected model's last floor."""
    rows = []
    tolerance, budget = result.get("tolerance"), result.get("max_trials")
    model = result.get("model") or {}
    for label, r in result.get("runs", {}).items():
        trials, floor = r.get("trials") or [], last_floor(r)
        reached = r.get("trials_to_tolerance")
        rows.append({"resolution": {k: model[k] for k in ("segments", "dt") if k in model},
                     "arm": label, "reached": bool(r.get("success")),
                     "trials": reached if reached is not None else (budget + 1 if budget is not None else None),
                     "best_error": r.get("best_error"), "best_trial": r.get("best_trial"),
                     "trials_used": r.get("trials_used"), "first_trial_error": trials[0]["error"] if trials else None,
                     "last_floor": floor["error"] if floor else None,
                     "floor_above_tolerance": (floor["error"] > tolerance) if floor and tolerance is not None else None,
                     "stop_reason": r.get("stop_reason") or "", "tolerance": tolerance, "max_trials": budget,
                     "real_system": result.get("real_system", ""), "wall_seconds": result.get("wall_seconds")})
    return rows


def sweep_summary(rows: list[dict]) -> list[str]:
    """Per arm over a sweep's finished corrections, as the campaign counts them: runs that reached the tolerance, the
    median trials (a miss counting max_trials + 1) and the median best error."""
    lines = []
    for arm in dict.fromkeys(r["arm"] for r in rows if r.get("arm")):
        mine = [r for r in rows if r.get("arm") == arm]
        trials = [r["trials"] for r in mine if r.get("trials") is not None]
        best = [r["best_error"] for r in mine if r.get("best_error") is not None]
        if not (trials and best):
            lines.append(f"{arm}: {len(mine)} runs")
            continue
        lines.append(f"{arm}: reached the tolerance in {sum(bool(r.get('reached')) for r in mine)} of {len(mine)} "
                     f"runs, median {np.median(trials):g} trials (a miss counts max_trials + 1), median best error "
                     f"{np.median(best):.3f}")
    return lines


def run_verdict(r: dict, tolerance: float) -> str:
    if r["success"]:
        return f"reached the tolerance in {r['trials_to_tolerance']} trials"
    floor = last_floor(r)
    if r.get("stop_reason") == "chain_never_hits":
        return f"did not reach the tolerance in {r['trials_used']} trials (best {r['best_error']:.4f}): {r['stopped']}"
    # the floor is the model's belief when the last trial was planned, not why the run ended (a 3-trial budget ran
    # out and was said to be "stopped by the model": a probe of stop 47)
    why = "" if floor is None else (
        f"; when its last trial was planned the corrected model predicted no command better than {floor['error']:.4f}"
        " anywhere in the command box (its linear model, no trust radius)"
        + (", above the tolerance: the model saw no way to the goal" if floor["error"] > tolerance else ""))
    return f"did not reach the tolerance in {r['trials_used']} trials (best {r['best_error']:.4f}{why})"


def trial_cells(result: dict, label: str) -> list[list[str]]:
    """One row of TRIAL_COLUMNS per trial of run `label`: what was tried, what the model predicted, what the rope
    did, and how the model and the trust region reacted (report.md and report.html show the same rows)."""
    def f(x):
        return "" if x is None else f"{x:.3f}"

    r = result["runs"][label]
    # the refit's prior centre is the measured values; the run's own `parameters` are its start values, which for the
    # default arm are the fitted ones (the column divided by those while saying "x measured": a probe of stop 47)
    measured = (r.get("renormalise") or {}).get("prior_centre") or r.get("parameters") or {}
    rows, floor = [], None
    for t in r["trials"]:
        ms = t.get("measured_state") or {}
        place = (f"{ms['time']:.3f} s / {ms['contact_arclength'][0]:.2f}-{ms['contact_arclength'][1]:.2f}"
                 if ms.get("self_collision") else "no self-collision")
        tr = t.get("trust") or {}
        rho = "" if not tr else (f"{'nan' if tr.get('rho') is None else format(tr['rho'], '.2f')} -> "
                                 f"{tr['radius_after']:.2f} ({tr['verdict']})")
        rf = t.get("refit") or {}
        moved = ""
        if rf:
            moved = ", ".join(f"{n} {v / measured[n]:.2g}" for n, v in rf["values"].items()
                              if measured.get(n) and abs(v / measured[n] - 1) > 0.05)
        refit = "" if not rf else f"{rf['loss_before']:.3f} -> {rf['loss']:.3f}"
        rows.append([str(t["trial"]), f"{t['error']:.4f}", f(t["predicted_error"]), f(floor),
                     f(t["model_alone_error"]), "yes" if t["accepted"] else "no", place, f"{t['trust_radius']:.2f}",
                     rho, refit, moved])
        floor = ((t.get("next_step") or {}).get("model_floor") or {}).get("error")  # made when the next was planned
    return rows


def run_method(r: dict) -> str:
    """The run's method and trust region, as it ran (a run saved before the rule was recorded: the method alone)."""
    from wrenorm.tasks.rope.observable import SAMPLES

    region = (r.get("gauss_newton") or r.get("renormalise") or {}).get("trust_region") or {}
    if "rule" not in region:
        return r["method"]
    radius = (f"fixed at {region['max_radius']:g}" if region["rule"] == "fixed"
              else f"{region['min_radius']:g}-{region['max_radius']:g}")
    weight = (r.get("gauss_newton") or {}).get("velocity_weight", 1.0)
    modes = (r.get("gauss_newton") or {}).get("velocity_modes")
    norm = "" if region.get("norm", "box") == "box" else f" ({region['norm']})"
    return (f"{r['method']}, trust radius {radius}{norm}"
            + ("" if weight == 1.0 else f", velocity rows weighted {weight:g}")
            + ("" if modes is None or modes >= SAMPLES else f", velocity rows' first {modes} modes"))


def report_markdown(result: dict) -> str:
    """Per run, per trial: what was tried, what the model predicted, what the rope did, and how the model and
    the trust region reacted; a reader sees why the run converged or did not."""
    start, settings = result.get("start") or {}, result.get("settings") or {}
    begun = start.get("path", "?") + (f" perturbed ({start['perturb']})" if start.get("perturb") is not None else "")
    lines = [f"# correct rope: {result['variant']} rope, goal {result['goal']['path']}, from {begun}",
             "", f"real system: {result['real_system']}; coarse chain {result['model']['segments']} links; "
                 f"seed {settings.get('seed', '?')}; at most {result.get('max_trials', '?')} trials; "
                 f"tolerance {result['tolerance']:g}; error = {result['error_meaning']}", ""]
    for label, r in result["runs"].items():
        lines += [f"## {label} ({run_method(r)}): {run_verdict(r, result['tolerance'])}", "",
                  "| " + " | ".join(TRIAL_COLUMNS) + " |", "|" + "---|" * len(TRIAL_COLUMNS)]
        lines += ["| " + " | ".join(row) + " |" for row in trial_cells(result, label)]
        lines.append("")
    lines.append("Per-trial records with the full predicted and measured critical states: real-trials/*-trial-NN.json")
    return "\n".join(lines) + "\n"


RUN_LABELS = ("renormalised", "renormalised-from-fitted", "measured", "fitted")


def run_name(label: str) -> str:
    """An arm's name in files, the report and the recording: the label itself, or a parameter file's stem."""
    return label if label in RUN_LABELS else Path(label).stem


SETTINGS_FILE = "settings.json"
BY_ARM_MODES_KEY = "by_arm_velocity_modes"  # settings.json: what --velocity-modes by-arm gave the renormalised arms
DIGEST_KEY = "_digest"
PARAMS_HASHES_KEY = "params_sha256"  # settings.json: the content of each --params result.json the run read


def _kind(value) -> str | None:
    """A saved setting's kind where the option fixes it (numbers, flags, lists); None where a default is a word
    that stands for a number chosen later (e.g. --velocity-weight by-method) or there is none."""
    if isinstance(value, bool):
        return "flag"
    if isinstance(value, (int, float)):
        return "number"
    if isinstance(value, (list, tuple)):
        return "list"
    return None


def _settings_digest(saved: dict) -> str:
    from wrenorm.results import stored_digest

    return stored_digest(saved)


_NOT_SAVED = ("out", "resume", "force", "quiet", "no_record", "command", "system", "func")


# options added after runs were saved: what a run saved without them did, and how to say it
_AS_RUN_BEFORE_THE_OPTION = {"start_pair": ("none", "ran without a start pair"),
                             "fit_throws": ("newton", "was fitted to the newton rope's throws"),
                             "max_radius": (None, "had no --max-radius"),
                             # gn steps adapted in every arm; plan and qp had none in fixed arms, as by-arm now
                             "trust_region": (lambda saved: "adaptive" if saved.get("method", "gn") == "gn"
                                              else "by-arm", "adapted its trust radius in every run that had one"),
                             # gn steps weighed every row alike; plan and qp runs have no such step to weigh
                             "velocity_weight": (lambda saved: 1.0 if saved.get("method", "gn") == "gn" else "by-arm",
                                                 "weighed the velocity rows of its steps as the others"),
                             "secant_locality": ("none", "weighed every secant pair alike"),
                             "velocity_modes": (lambda saved: "all" if _saved_steps(saved) else "by-arm",
                                                "kept every velocity row of its steps"),
                             "trust_norm": ("box", "stepped inside a box of the trust radius"),
                             "first_plan_reg": ("as-plans", "planned trial 1 with the other plans' weight"),
                             "first_plan_offset": ("none", "planned trial 1 on the chain alone"),
                             "builtin_throws": (builtin_throws_of,
                                                "took its goal and throws from newton's built-in references")}


def _saved_steps(saved: dict) -> bool:
    """Whether a saved run had an arm that steps by Gauss-Newton (a plan loop, or qp with fixed parameters, has none
    to shape: a step option's old value would be refused there)."""
    from wrenorm.tasks.rope.control.correct import takes_gn_steps

    args = argparse.Namespace(method=saved.get("method", "gn"))
    return any(takes_gn_steps(*_arm_method(args, label)) for label in saved.get("params", ()))


def _typed_options(args) -> set[str]:
    """The settings named on the command line (`wrenorm.cli.main` keeps it in args._argv), whatever their values: an
    option typed at its default is a request too. Empty where the line is not known (args built by a test)."""
    import argparse

    argv = list(getattr(args, "_argv", None) or [])
    command, system = getattr(args, "command", None), getattr(args, "system", None)
    if command not in argv or system not in argv[argv.index(command) + 1:]:
        return set()
    tail = argv[argv.index(system, argv.index(command) + 1) + 1:]
    parser = argparse.ArgumentParser(add_help=False)
    add_arguments(parser)
    for action in parser._actions:
        action.default = argparse.SUPPRESS
    try:
        named, _ = parser.parse_known_args(tail)
    except SystemExit:  # the real parser already accepted this line
        return set()
    return set(vars(named))


def _params_hashes(args) -> dict:
    from wrenorm.cli import content_hashes

    files = [label for label in args.params if label not in RUN_LABELS]
    return content_hashes([f for f in files if Path(f).is_file()])


def _restore_settings(args) -> None:
    """--resume: the interrupted run's settings, so its plans and trials repeat exactly. An option left out takes
    the saved value; one given with another value than the run had is refused, naming it (also one typed at its
    default: the user asked for that value)."""
    if args.out is None:
        raise InputError("--resume", "out", "name the folder of the interrupted correction with --out")
    f = Path(args.out) / SETTINGS_FILE
    if not f.is_file():  # checked before any setting is taken from it; prepare_out checks again
        raise InputError(str(args.out), "--resume", f"no saved state ({SETTINGS_FILE}) in this folder to resume from")
    try:
        saved = json.loads(f.read_text())
    except (OSError, ValueError) as e:
        raise InputError(str(f), SETTINGS_FILE, f"cannot be read: {e}") from None
    if not isinstance(saved, dict):
        raise InputError(str(f), SETTINGS_FILE, "is not a settings object")
    digest = saved.pop(DIGEST_KEY, None)  # absent: saved before settings carried one (stop 45), read as before
    if digest is not None and digest != _settings_digest(saved):
        raise InputError(str(f), SETTINGS_FILE, "was changed since the run wrote it: its trials belong to the settings "
                                                "it ran with; start a new run for other settings")
    fresh = argparse.ArgumentParser()
    add_arguments(fresh)
    defaults = vars(fresh.parse_args([]))
    typed = _typed_options(args)
    for key, value in saved.items():
        if key in _NOT_SAVED or key not in defaults:
            continue
        if value is not None and _kind(defaults[key]) not in (None, _kind(value)):
            raise InputError(str(f), key, f"is {value!r}, not a {_kind(defaults[key])} as the option takes")
        if key == "device" and isinstance(value, str) and value.startswith("cuda"):
            value = "cuda"  # saved as the run resolved it ("cuda:0"); the option's choice is "cuda"
        given = getattr(args, key, None)
        if (given != defaults[key] or key in typed) and json.loads(json.dumps(given, default=str)) != value:
            raise InputError(f"--{key.replace('_', '-')}", key, f"the interrupted correction ran with {value!r}, "
                                                                f"this run asks for {given!r}; resume with the same "
                                                                "options (or leave them out)")
        setattr(args, key, value)
    for key, (as_run, how) in _AS_RUN_BEFORE_THE_OPTION.items():
        if saved.get(key) is None:  # saved before the option existed: the run had the old behaviour
            as_run = as_run(saved) if callable(as_run) else as_run
            given = getattr(args, key)
            if given not in (None, as_run, defaults[key]) or (key in typed and given != as_run):
                raise InputError(f"--{key.replace('_', '-')}", key, f"the interrupted correction {how}, this run asks "
                                                                    f"for {given!r}; leave it out")
            setattr(args, key, as_run)
    # by-arm's number of velocity modes for the renormalised arms when the run was saved: 3 before it was saved with
    # it (stops 49 and before; a run saved before --velocity-modes has "all" from above and never reads it)
    if args.velocity_modes == "by-arm":
        args.by_arm_velocity_modes = saved.get(BY_ARM_MODES_KEY, 3)
    # a --params file rewritten under the same name: the stored trials were planned on the model it held (a resume
    # had thrown them away and thrown every trial again on the new model, review of stop 54); saved before: unchecked
    then = saved.get(PARAMS_HASHES_KEY)
    if isinstance(then, dict):
        now = _params_hashes(args)
        for name in sorted(set(then) | set(now)):
            if then.get(name) != now.get(name):
                raise InputError(name, "--params", f"is not the file the interrupted correction read (sha256 "
                                                   f"{str(then.get(name))[:12]}, now "
                                                   f"{str(now.get(name))[:12] if name in now else 'missing'}): its "
                                                   "trials were planned on that model; resume with the same file, or "
                                                   "start a new run")
    if "trust_region" not in saved and not _adapts({label: _trust_options(args, label) for label in args.params}):
        args.min_radius = None  # saved before the option by a run where no arm adapted: it was ignored then


def _by_arm_modes_changed(args) -> bool:
    """A resumed run whose by-arm velocity modes are not today's, and whose stepping arms all renormalise (a fixed arm
    keeps every mode by arm, which one --velocity-modes number cannot say beside the renormalised arms')."""
    from wrenorm.tasks.rope.control.correct import takes_gn_steps
    from wrenorm.tasks.rope.control.secant import VELOCITY_MODES

    modes = getattr(args, "by_arm_velocity_modes", None)
    stepping = [label for label in args.params if takes_gn_steps(*_arm_method(args, label))]
    return (modes not in (None, VELOCITY_MODES) and bool(stepping)
            and all(_arm_method(args, label)[0] == "renormalise" for label in stepping))


def reproduce_command(args) -> str:
    """The command that repeats a resumed run from scratch. `--resume --out X` as typed names none of the run's
    settings, and the same line without --resume would run today's defaults, so the line is rebuilt from the
    restored settings: every option whose value differs from its default, including those an old run had from
    before the option existed (e.g. `--velocity-weight 1.0`)."""
    import shlex

    parser = argparse.ArgumentParser()
    add_arguments(parser)
    argv = ["correct", "rope"]
    for action in parser._actions:
        if not action.option_strings or action.dest in ("help", "resume", "force"):
            continue
        value = getattr(args, action.dest, action.default)
        if action.dest == "device":
            value = "cuda" if str(value).startswith("cuda") else value  # the run's "cuda:0"
        if action.dest == "builtin_throws" and value == builtin_is_the_real_rope(vars(args)):
            continue  # what a fresh run derives from --engine and --fine-segments
        if action.dest == "velocity_modes" and value == "by-arm" and _by_arm_modes_changed(args):
            value = str(args.by_arm_velocity_modes)  # every arm that steps renormalises: one number says it
        if value == action.default or value is None:
            continue
        flag = next(o for o in action.option_strings if o.startswith("--"))
        if isinstance(action, argparse.BooleanOptionalAction):
            argv.append(flag if value else action.option_strings[1])
        elif action.nargs == 0:  # store_true
            argv.append(flag)
        elif isinstance(value, (list, tuple)):
            argv += [flag, *map(str, value)]
        else:
            argv += [flag, str(value)]
    return "python -m wrenorm " + shlex.join(argv)


def _trust_rule(args, label: str) -> str:
    """The trust region of the run with parameters `label`: --trust-region, where by-arm means fixed for fixed
    parameters and adaptive for renormalised ones."""
    if args.trust_region != "by-arm":
        return args.trust_region
    return "adaptive" if label.startswith("renormalised") else "fixed"


def _check_fixed_parameter_options(args) -> None:
    """--method qp and --first-step space-mapping act on fixed-parameter runs only (a renormalised run takes
    Gauss-Newton steps under qp, and its refitted chain reproduces trial 1 at its own command, so space mapping's step
    would not move): refused where every run here renormalises, as the default arm does."""
    if any(not label.startswith("renormalised") for label in args.params):
        return
    for flag, key, given in (("--method qp", "method", args.method == "qp"),
                             ("--first-step space-mapping", "first_step", args.first_step == "space-mapping")):
        if given:
            raise InputError(flag.split()[0], key, f"{flag} acts on fixed parameters, and every run here renormalises "
                                                   f"({', '.join(args.params)}): add --params fitted, measured or a "
                                                   "result.json")


def _arm_method(args, label: str) -> tuple[str, str]:
    """correct()'s method and steps for the run with parameters `label`: renormalised runs refit (planning or
    stepping as --method says), the others take --method."""
    return ("renormalise" if label.startswith("renormalised") else args.method), (
        "plan" if args.method == "plan" else "gn")


def _trust_options(args, label: str) -> dict:
    """correct()'s trust-region options for the run with parameters `label`: none for the plan and qp loops of
    fixed parameters (they have none), the radius bounds only where it adapts."""
    if _arm_method(args, label)[0] not in ("gn", "renormalise"):
        return {}
    rule = _trust_rule(args, label)
    adaptive = rule == "adaptive"
    return {"trust_region": rule, "min_radius": args.min_radius if adaptive else None,
            "max_radius": args.max_radius if adaptive else None}


def number_or_word(word: str | tuple, positive: bool):
    """An argparse type: `word` (or one of a tuple of words), or a finite number >= 0 (> 0 when `positive`),
    returned as a float so that a resumed run compares numbers."""
    bound = "> 0" if positive else ">= 0"
    words = (word,) if isinstance(word, str) else tuple(word)
    word = " nor ".join(words)

    def parse(text) -> float | str:
        if text in words:
            return text
        try:
            value = float(text)
        except (TypeError, ValueError):
            value = float("nan")
        if not (np.isfinite(value) and (value > 0 if positive else value >= 0)):
            raise argparse.ArgumentTypeError(f"{text!r} is neither a finite number {bound} nor {word}")
        return value

    return parse


velocity_weight_arg = number_or_word("by-arm", positive=False)  # --velocity-weight
secant_locality_arg = number_or_word("none", positive=True)  # --secant-locality
first_plan_reg_arg = number_or_word(("by-method", "as-plans"), positive=False)  # --first-plan-reg


def velocity_modes_arg(text):
    """--velocity-modes: by-arm, all, or a whole number of modes in 1-21."""
    from wrenorm.tasks.rope.observable import SAMPLES

    if text in ("by-arm", "all"):
        return text
    try:
        value = int(str(text))
    except ValueError:
        value = 0
    if not 1 <= value <= SAMPLES:
        raise argparse.ArgumentTypeError(f"{text!r} is neither a whole number of modes in 1-{SAMPLES} nor by-arm or "
                                         "all")
    return value


def _velocity_modes(args) -> int | None:
    """--velocity-modes as a number of modes (all: every one); None for by-arm (correct() picks it by the arm)."""
    from wrenorm.tasks.rope.observable import SAMPLES

    if args.velocity_modes == "by-arm":
        return None
    return SAMPLES if args.velocity_modes == "all" else int(args.velocity_modes)


def _velocity_weight(args) -> float | None:
    """--velocity-weight as a number; None for by-arm (correct() picks it by the arm's method)."""
    return None if args.velocity_weight == "by-arm" else float(args.velocity_weight)


def _first_plan_reg(args, label: str) -> float | None:
    """correct()'s first_plan_reg for the run with parameters `label`: None where that run plans no trial 1 (qp,
    --no-plan-first) and for by-method (correct() picks it by the arm's loop); for as-plans the weight of that loop's
    other plans (None where they are plans, whose weight correct() takes from --reg)."""
    from wrenorm.tasks.rope.control import plan as rope_plan
    from wrenorm.tasks.rope.control.correct import takes_gn_steps

    if args.first_plan_reg == "by-method" or not _plans_trial_one(args, label):
        return None
    if args.first_plan_reg == "as-plans":
        return rope_plan.DEFAULT_REG if takes_gn_steps(*_arm_method(args, label)) else None
    return float(args.first_plan_reg)


def _plans_trial_one(args, label: str) -> bool:
    """Whether the run with parameters `label` plans trial 1 on the chain (correct.plans_first for its loop)."""
    from wrenorm.tasks.rope.control.correct import plans_first

    return plans_first(*_arm_method(args, label), not args.no_plan_first)


def _check_first_plan(args) -> None:
    """--first-plan-reg (a number) and --first-plan-offset start act on trial 1's plan: refused where no run here plans
    it (checked before any real run). --first-plan-offset is none or start: a resumed run's settings bypass argparse."""
    if args.first_plan_offset not in ("none", "start"):
        raise InputError("--first-plan-offset", "first_plan_offset", f"{args.first_plan_offset!r} is not none or start")
    if any(_plans_trial_one(args, label) for label in args.params):
        return
    for flag, key, given, what in (
            ("--first-plan-reg", "first_plan_reg", args.first_plan_reg not in ("by-method", "as-plans"), "weighs"),
            ("--first-plan-offset", "first_plan_offset", args.first_plan_offset == "start", "shifts")):
        if given:
            raise InputError(flag, key, f"{what} trial 1's plan, and no run here plans it (--no-plan-first, or "
                                        "--method qp)")


def _first_plan_offset(args, label: str) -> bool:
    """Whether the run with parameters `label` plans trial 1 on the chain plus the start throw's offset: with start,
    wherever that run plans a trial 1."""
    return args.first_plan_offset == "start" and _plans_trial_one(args, label)


def _check_step_options(args) -> None:
    """--velocity-weight, --velocity-modes, --trust-norm and --secant-locality are given only where an arm steps by
    Gauss-Newton, the locality only with secant pairs (checked before any real run)."""
    if args.secant is False and args.secant_locality != "none":
        raise InputError("--secant-locality", "secant_locality", "weighs the secant pairs, and --no-secant uses none")
    if any(_step_options(args, label) for label in args.params):
        return
    for flag, key, given in (("--velocity-weight", "velocity_weight", args.velocity_weight != "by-arm"),
                             ("--velocity-modes", "velocity_modes", args.velocity_modes != "by-arm"),
                             ("--trust-norm", "trust_norm", args.trust_norm != "box"),
                             ("--secant-locality", "secant_locality", args.secant_locality != "none")):
        if given:
            raise InputError(flag, key, f"shapes Gauss-Newton steps, and no run here takes one (--method "
                                        f"{args.method})")


def _step_options(args, label: str) -> dict:
    """correct()'s Gauss-Newton step options for the run with parameters `label`: none where it plans instead."""
    from wrenorm.tasks.rope.control.correct import takes_gn_steps

    method = _arm_method(args, label)
    if not takes_gn_steps(*method):
        return {}
    modes = _velocity_modes(args)
    if modes is None and method[0] == "renormalise":  # by-arm, as it was when a resumed run was saved
        modes = getattr(args, "by_arm_velocity_modes", None)
    return {"velocity_weight": _velocity_weight(args), "velocity_modes": modes, "trust_norm": args.trust_norm,
            "secant_locality": None if args.secant_locality == "none" else float(args.secant_locality)}


def _adapts(arms: dict) -> bool:
    return any(options.get("trust_region") == "adaptive" for options in arms.values())


def _default(name: str, method: str) -> float:
    from wrenorm.tasks.rope.control import correct as rope_correct
    from wrenorm.tasks.rope.control import plan as rope_plan
    from wrenorm.tasks.rope.control import secant

    if name == "radius":
        radii = {"plan": rope_correct.DEFAULT_PLAN_RADIUS, "gn": secant.GN_RADIUS}
        return radii.get(method, rope_correct.DEFAULT_RADIUS)
    return {"plan": rope_plan.DEFAULT_REG, "gn": secant.GN_REG}.get(method, rope_correct.DEFAULT_REG)


def _plot(path: Path, runs: dict, args) -> None:
    from wrenorm.viz.plots import _figure, save_figure

    plt = _figure()
    fig, ax = plt.subplots(figsize=(6, 3.8))
    floor_label = "corrected model's floor when planned"
    for label, r in runs.items():
        tr = r["trials"]
        line, = ax.semilogy([t.index + 1 for t in tr], [t.total for t in tr], "o-", label=f"{label} parameters")
        rej = [t for t in tr if not t.accepted]
        ax.semilogy([t.index + 1 for t in rej], [t.total for t in rej], "x", color="k")
        floors = [(t.index + 2, t.sensitivity["model_floor"]["error"]) for t in tr[:-1]
                  if (t.sensitivity or {}).get("model_floor")]
        if floors:
            ax.semilogy(*zip(*floors), "_", color=line.get_color(), ms=12, mew=1.5, label=floor_label)
            floor_label = None
    ax.axhline(args.tolerance, color="k", lw=0.7, ls="--", label="tolerance")
    ax.set_xlabel("real trial")
    ax.xaxis.get_major_locator().set_params(integer=True)
    ax.set_ylabel("critical-state error to goal")
    ax.set_title(f"rope command correction: {args.engine} {args.variant} rope, {args.start} to {args.goal}, "
                 f"{args.segments} links, seed {args.seed}, at most {args.max_trials} trials; x = rejected", fontsize=8)
    ax.legend(fontsize=8)
    save_figure(fig, path)
    plt.close(fig)


def _run_color(name: str, COLORS: dict):
    return COLORS.get(name, (120, 200, 80))


def _log_throw(rec, who: str, ref, color, what: str) -> None:
    """A whole throw on "sim_time": the rope and the hand every 20 ms, and its first self-collision, labelled."""
    from wrenorm.tasks.rope import observable as crit

    stride = max(1, int(round(0.02 / ref.dt)))
    for f in range(0, len(ref.time), stride):
        t = float(ref.time[f])
        rec.log_lines3d(f"throw/{who}/rope", t, [ref.markers[f]], colors=color, radii=0.004)
        rec.log_points3d(f"throw/{who}/hand", t, ref.hand[f][None], colors=color, radii=0.012)
    try:
        st = crit.from_reference(ref)
    except Exception:  # noqa: BLE001  (a trial without a self-collision has no critical state to mark)
        return
    t = float(st.time[0])
    rec.log_points3d(f"throw/{who}/critical", t, st.pos[0], colors=color, radii=0.008,
                     labels=[f"{what}: first contact {t:.3f} s"] + [""] * (len(st.pos[0]) - 1))


def _record(path: Path, runs: dict, goal, args, goal_ref=None, real=None, space=None) -> None:
    """Per trial: the real rope's shape at its first self-collision under each model's command,
    against the goal's (white); every run's error per trial against the tolerance; and the whole throw of the
    goal and of each run's best trial (read back from the stored real trials) on "sim_time"."""
    from wrenorm.viz.record import COLORS, Recorder, rerun_available

    if not rerun_available():
        return
    import rerun as rr

    rec = Recorder(path, application_id="wrenorm-correct")
    s = rec.stream
    try:
        s.log("shape/goal", rr.LineStrips3D([goal.state.pos[0].astype(np.float32)], colors=[COLORS["reference"]],
                                            radii=0.004), static=True)
        names = []
        for label, r in runs.items():
            name = run_name(label)
            names.append(name)
            for t in r["trials"]:
                rec.log_scalar(f"error/{name}", t.index + 1, t.total, timeline="trial", color=_run_color(name, COLORS))
                rec.log_scalar("error/tolerance", t.index + 1, args.tolerance, timeline="trial")
                if t.hit:
                    s.log(f"shape/{name}", rr.LineStrips3D([t.state.pos[0].astype(np.float32)], radii=0.004,
                                                           colors=[_run_color(name, COLORS)]))
                else:
                    s.log(f"shape/{name}", rr.Clear(recursive=False))
        rec.add_view("(timeline trial) real rope at its first self-collision: goal white, "
                     + ", ".join(f"{n} model {'orange' if n == 'measured' else 'blue' if n == 'fitted' else 'green'}"
                                 for n in names), ["/shape/**"], "spatial3d",
                     around=np.concatenate([goal.state.pos[0]] + [t.state.pos[0] for r in runs.values()
                                                                  for t in r["trials"] if t.hit]))
        rec.add_view(f"(timeline trial) error per real trial (goal reached at <= {args.tolerance})", ["/error/**"])
        if goal_ref is not None and real is not None and space is not None:
            _log_throw(rec, "goal", goal_ref, COLORS["reference"], "goal")
            around = [goal_ref.markers.reshape(-1, 3)]
            for label, r in runs.items():
                name = run_name(label)
                best = min(r["trials"], key=lambda t: t.total)
                try:
                    ref = real(space.decode(best.u))  # read back from OUT/real-trials, never simulated again
                except Exception as e:  # noqa: BLE001  (the view is lost for this run, not the recording)
                    rec.log_text(f"throw/{name}/missing", f"{name}: best trial not readable ({e})")
                    continue
                _log_throw(rec, name, ref, _run_color(name, COLORS), f"{name}, best trial {best.index + 1}")
                around.append(ref.markers.reshape(-1, 3))
            rec.add_view("(timeline sim_time) the whole throw: goal white, each run's best trial in its colour",
                         ["/throw/**"],
                         "spatial3d", around=np.concatenate(around))
            rec.show_timeline("sim_time")
        rec.close()
    except BaseException:
        rec.abort()
        raise
