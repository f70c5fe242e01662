"""Task-level iterative learning on the rope (the flying knot's correction loop).

Each trial runs the command on the "real" rope (any callable `real(hand_path) -> RopeReference`;
by default the fine newton rope), measures the critical state Z at its first self-collision, and
updates the command u by a regularised trust-region step through the COARSE model's sensitivity
F = dZ/du (weighted units of tasks/rope/observable.py):

    du = argmin |F du + e|^2 + lam |du|^2   s.t.  lo <= u + du <= hi,  |du|_inf <= radius

(scipy lsq_linear on the stacked system), then shortened until the hand's speed and
acceleration limits hold. A trial that does not improve the best error is rejected: the next
step starts again from the best command (a real trial is the expensive thing, so the loop never
walks on from a worse command), within the same radius where the trust region is fixed (the
rejected trial's secant pair has already corrected the step) and half of it where it adapts
(trust_region_for). lam = reg * mean(diag F^T F).

Why finite differences and not Warp's tape for F: Z is sampled at an EVENT (the first frame a
gap turns negative). Its derivative needs the implicit term dt*/du = -(dg/du)/(dg/dt) and is
undefined where the first-hitting segment pair switches; a tape through the stepping sees
neither (and the forward kernel is built without backward). A central difference with a step
of a fraction of a unit of u (mm, cm/s, 1 % time) measures the secant of the event map, which
is what the correction needs, and costs one batched rollout: all 2 dim(u) perturbed commands
(plus the centre) are chains of ONE launch, as fast as a single chain on this CPU.
"""
from __future__ import annotations

import hashlib
import time
import zipfile
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from wrenorm.errors import InputError
from wrenorm.jacobian import jacobian
from wrenorm.problem import Condition
from wrenorm.tasks.rope import observable as crit
from wrenorm.tasks.rope.control import secant as gauss_newton  # the module; `secant` is an argument here
from wrenorm.tasks.rope.control.command import CommandSpace
from wrenorm.tasks.rope.control.secant import qp_step

FD_STEP = 0.1  # units of u: 5 mm, 5 cm/s, 1 % of a segment's time
DEFAULT_TOLERANCE = 0.05  # total error (rope.py units): ~2 % of the length in shape, 2 % in time
DEFAULT_RADIUS = 1.0  # initial trust radius in units of u (qp)
DEFAULT_PLAN_RADIUS = 1.5  # initial trust radius of the plans after trial 0 (plan)
DEFAULT_REG = 1e-2


# ------------------------------------------------------------------------------ coarse model
class CoarseModel:
    """The coarse chain (a RopeProblem at its resolution) with fixed parameter values, as a map
    from commands to critical states; many commands per rollout."""

    def __init__(self, problem, values, space: CommandSpace, label: str = "measured"):
        self.problem = problem
        self.values = np.asarray(values, dtype=np.float64).reshape(-1)
        self.space = space
        self.label = label
        self.case = problem.train[0].data  # horizon and start state (the rope hangs still at the start point)

    def hands(self, U: np.ndarray) -> list[Condition]:
        cs = self.case
        t0 = float(cs.ref.time[0])
        H = self.space.batch_positions(U, t0 + self.problem.dt * np.arange(cs.steps + 1))
        return [Condition(f"u{i}", replace(cs, hand=h)) for i, h in enumerate(H)]

    def rollout(self, U: np.ndarray, trajectory_every: int | None = None):
        return self.problem.simulate(self.values[None], self.hands(U), trajectory_every=trajectory_every)

    def states(self, U: np.ndarray) -> crit.CriticalStates:
        res = self.rollout(U)
        return crit.from_rollout(res, self.problem.n, 0.0)  # problem.simulate times from the motion's start

    def sensitivity(self, u: np.ndarray, goal: crit.Target, h: float = FD_STEP) -> tuple[np.ndarray, dict]:
        """F = de/du (goal.dim, dim) by central differences, all perturbations in one rollout.

        A perturbed chain that misses the collision falls back to the one-sided difference of
        the other side; if both miss, the column is 0 (that direction is not trusted).
        """
        t = time.perf_counter()
        jac = jacobian(lambda U: goal.residual(self.states(U)), u, h)
        return jac.J, {"rollouts": jac.evaluations, "wall_s": time.perf_counter() - t,
                       "centre_hit": bool(np.all(np.isfinite(jac.f0))), "columns": jac.kinds, "e_centre": jac.f0}


# ------------------------------------------------------------------------------ real systems
def _plan_or_look_closer(model, goal, centre, radius, offset, seed, starts, plan_opts):
    """A plan from `centre` that moves; where nothing better is predicted in the box, the box halves (3 tries).
    Returns (plan, feasible command, its step scale, the radius used)."""
    from wrenorm.tasks.rope.control import plan as rope_plan

    for retry in range(3):
        p = rope_plan.plan(model, goal, centre, radius, offset, seed=seed + retry + 1, starts=starts, **plan_opts)
        u, scale_used = _feasible(model.space, centre, p["u"])
        if np.abs(u - centre).max() > 1e-9:
            break
        radius *= 0.5
    return p, u, scale_used, radius


class FineRope:
    """A fine rope simulator (newton's rod or MuJoCo's elastic rod, tasks/rope/reference/) as the real system:
    maps a HandPath to a RopeReference; repeated commands are cached, `runs` and `wall_s` count the work."""

    engine = "newton"

    def __init__(self, variant: str = "default", segments: int = 64, duration: float = 1.5, device: str = "cpu"):
        from wrenorm.tasks.rope.reference.materials import get_variant

        get_variant(variant)
        self.variant, self.segments, self.duration, self.device = variant, int(segments), float(duration), device
        self.runs, self.wall_s = 0, 0.0
        self._cache = {}

    @property
    def identity(self) -> str:
        """What a trial's answer depends on besides its command (StoredTrials checks a stored trial against it)."""
        return f"{self.engine} variant={self.variant} segments={self.segments} duration={self.duration:g}"

    def __call__(self, path):
        from wrenorm.tasks.rope.reference.generate import generate_reference

        key = (path.control_points.tobytes(), path.durations.tobytes())
        if key not in self._cache:
            t = time.perf_counter()
            self._cache[key] = generate_reference(path, segments=self.segments, variant=self.variant,
                                                  duration=self.duration, device=self.device, engine=self.engine)
            self.wall_s += time.perf_counter() - t
            self.runs += 1
        return self._cache[key]


class NewtonRope(FineRope):
    engine = "newton"


class MujocoRope(FineRope):
    """MuJoCo's elastic rod (a 1D flexcomp): a simulator the correction was not developed against."""

    engine = "mujoco"


REAL_ROPES = {"newton": NewtonRope, "mujoco": MujocoRope}  # fine simulators that can play the real rope


def real_rope_class(engine: str):
    """The fine 'real' rope of `engine`: a class built as cls(variant, segments, duration, device)."""
    if engine not in REAL_ROPES:
        raise InputError("--engine", "engine", f"unknown fine rope {engine!r}; available: {sorted(REAL_ROPES)}")
    return REAL_ROPES[engine]


class StoredTrials:
    """A real system whose every trial is written to `folder` (atomic npz) as it finishes and read
    back from there when the same command comes again: an interrupted correction resumes without
    re-running a real trial. The loop always uses the stored copy, even right after the trial, so a
    resumed run sees the very numbers an uninterrupted one saw (the file keeps markers in float32)."""

    def __init__(self, real, folder):
        self.real = real
        self.folder = Path(folder)
        self.folder.mkdir(parents=True, exist_ok=True)
        self.reused = 0
        self.unstored = 0
        self._seen: set[str] = set()

    def key_for(self, path) -> str:
        """The trial's full key, stored in its file: the command and the real system (engine, rope, resolution), so
        a file copied under another trial's name, or left by a run on another rope, is not read as this trial."""
        identity = getattr(self.real, "identity", type(self.real).__name__)
        return hashlib.sha256(f"{identity} {self.file_for(path).name}".encode()).hexdigest()

    @property
    def runs(self) -> int:
        return self.real.runs

    @property
    def wall_s(self) -> float:
        return self.real.wall_s

    def file_for(self, path) -> Path:
        key = hashlib.sha256(np.ascontiguousarray(path.control_points, np.float64).tobytes()
                             + np.ascontiguousarray(path.durations, np.float64).tobytes()).hexdigest()[:24]
        return self.folder / f"trial-{key}.npz"

    def __call__(self, path):
        from wrenorm.tasks.rope.reference.generate import load_reference, save_reference

        f = self.file_for(path)
        if not f.exists():
            ref = self.real(path)
            try:
                save_reference(f, ref, extra={"trial_key": np.array(self.key_for(path))})
            except InputError:
                # a trial that blew up (non-finite markers) is not a valid reference file: it costs
                # this trial (no self-collision, large error), is kept in memory only, and a resumed
                # run repeats it (the real system is deterministic here)
                self.unstored += 1
                return ref
        elif f.name not in self._seen:
            self.reused += 1
            self._check_key(f, path)
        self._seen.add(f.name)
        return load_reference(f)

    def _check_key(self, f: Path, path) -> None:
        try:
            with np.load(f, allow_pickle=False) as data:
                stored = str(data["trial_key"]) if "trial_key" in data.files else None
        except (OSError, ValueError, zipfile.BadZipFile, EOFError) as e:  # a truncated file had been a traceback
            raise InputError(str(f), "file", f"is not a readable .npz archive ({e.__class__.__name__}: {e}): remove "
                                             "it to run that trial again") from None
        # a file written before trials carried their key (stop 45) is read as before
        if stored is not None and stored != self.key_for(path):
            raise InputError(str(f), "trial_key", "was recorded for another command or another real rope (engine, "
                                                  "variant, resolution) than this run's trial under that name; "
                                                  "resume in the run's own folder, or start a new run")


class CoarseRope:
    """A coarse chain with its own parameters posing as the real rope (a system whose correct
    answer is known: used by tests and for quick runs). Returns the full trajectory as a
    RopeReference so it is measured exactly like the fine rope."""

    def __init__(self, problem, values, duration: float | None = None):
        self.problem, self.values = problem, np.asarray(values, dtype=np.float64)
        self.runs, self.wall_s = 0, 0.0
        self.duration = duration

    @property
    def identity(self) -> str:
        values = hashlib.sha256(self.values.tobytes()).hexdigest()[:16]
        return f"coarse segments={self.problem.segments} dt={self.problem.dt:g} values={values} " \
               f"duration={self.duration}"

    def __call__(self, path):
        from wrenorm.tasks.rope.reference.generate import RopeReference

        t = time.perf_counter()
        pb, cs = self.problem, self.problem.train[0].data
        t0 = float(cs.ref.time[0])
        steps = cs.steps if self.duration is None else int(round(self.duration / pb.dt))
        hand = path.positions(t0 + pb.dt * np.arange(steps + 1))
        res = pb.sim.rollout(cs.pos0[None], cs.vel0[None], hand[None], np.zeros(1, np.int32),
                             pb.chain_params(self.values), steps, t0=t0, stop_at_hit=False, trajectory_every=1)
        self.runs += 1
        self.wall_s += time.perf_counter() - t
        return RopeReference(time=res.trajectory_times, markers=res.trajectory[:, 0].astype(np.float64),
                             hand=hand[:len(res.trajectory_times)], length=pb.length, mass=pb.mass,
                             radius=float(self.values[pb.space.index("radius")]), bend_stiffness=None,
                             marker_arclength=np.linspace(0.0, 1.0, pb.n), source="coarse chain")


@dataclass
class Trial:
    index: int
    u: np.ndarray
    terms: dict
    hit: bool
    accepted: bool
    radius: float
    state: crit.CriticalStates
    wall_s: float
    predicted_total: float | None = None
    step_scale: float | None = None
    model_total: float | None = None
    sensitivity: dict = field(default_factory=dict)
    predicted_state: crit.CriticalStates | None = None  # what the plan expected the real rope to do
    model_values: np.ndarray | None = None  # the coarse parameters that made the prediction
    refit: dict | None = None  # renormalise: the refit after this trial (values, losses, trials used)
    trust: dict | None = None  # renormalise: the trust-region verdict from this trial

    @property
    def total(self) -> float:
        return float(self.terms["total"][0])


def correct(real, model: CoarseModel, goal: crit.Target, u0: np.ndarray, max_trials: int = 10,
            tolerance: float = DEFAULT_TOLERANCE, radius: float | None = None, reg: float | None = None,
            fd_step: float = FD_STEP, secant: bool | None = None, method: str = "gn", plan_first: bool = True,
            seed: int = 0, popsize: int | None = None, generations: int | None = None, freeze_place: bool = True,
            progress=None, on_trial=None, refit_offset: bool = True, prior_scale: float | None = None,
            decay: float | None = None, anchored: bool = False, refit_generations: int | None = None,
            min_radius: float | None = None, prior_centre: np.ndarray | None = None, steps: str = "gn",
            max_radius: float | None = None, trust_region: str | None = None,
            linearise_at: str = "matched", first_step: str = "gn", recorded: list | None = None,
            recorded_until: str = "first", velocity_weight: float | None = None,
            secant_locality: float | None = None, first_plan_reg: float | None = None,
            first_plan_offset: tuple | None = None, velocity_modes: int | None = None,
            trust_norm: str | None = None) -> dict:
    """Run trials until the real critical state is within `tolerance` of the goal or trials run out.

    method "gn" (default): trial 1 is the model's own plan (as "plan"); every next command a trust-region
      Gauss-Newton step from the best trial through the chain's sensitivity, measured once (with linearise_at
      "matched" where the chain reproduces the first hit's real state) and corrected by every trial (secant.py).
      first_step "space-mapping": trial 2 (after the planned trial 1, with fixed parameters) is space mapping's step
      (secant.space_mapping_step) instead of the Gauss-Newton step; "gn" keeps every step Gauss-Newton.
      recorded: [(u, CriticalStates)] the real rope's critical states under commands recorded before the trials
      (the start throw): each that hit is one more secant pair for the Gauss-Newton steps (not a trial);
      recorded_until "first": only until the trials give a pair of their own, "every": at every step.
      velocity_weight: the steps' weight on the velocity rows of the residual (the step only; acceptance and the
      reported error are the observable's); left out, secant.VELOCITY_WEIGHT for gn and 1 for renormalise.
      velocity_modes: the steps keep the velocity rows' first this many Legendre modes in arc length per axis
      (secant.velocity_projection; the step only), at most observable.SAMPLES (every mode); left out,
      secant.VELOCITY_MODES for renormalise and every mode for gn.
      trust_norm: "box" (left out), the trust radius bounds each coordinate of the step; "ball", the step's
      Euclidean length over secant.BALL_PER_RADIUS (secant.ball_step). The plan loops' regions are boxes.
      secant_locality: None, every secant pair weighs alike in the ridge fit; a length L (units of u), pairs
      farther than L from the best command fade as (L / distance)^2 (secant.pair_weight).
    first_plan_reg: the weight of |u - u0|^2 in the plan of trial 1 (per unit of u squared); left out,
      secant.FIRST_PLAN_REG where Gauss-Newton steps follow, else the loop's plans' own (`reg` for the plan loop).
    first_plan_offset: (u, CriticalStates) the real rope's critical state under a command recorded before the
      trials (the start throw): trial 1 is planned on the chain plus the rope's offset from it there (output space
      mapping, plan.start_offset); None, on the chain alone. A recorded state that missed gives no offset.
    method "plan": model-offset ILC, every next command a global CMA-ES plan on the
      coarse model plus the offset learned from the real trials (tasks/rope_plan); with
      plan_first, the first real trial is already the model's own plan from u0 ("trial 0").
    method "qp": a linear trust-region step through the coarse model's FD sensitivity.
    secant: learn how the model's error changes with u from pairs of real trials (for "gn" a ridge fit of all
      pairs toward the chain's sensitivity, for "plan" a Broyden term of the offset, for "qp" of F). Default: on
      for "gn" and "plan", off for "qp".
    freeze_place ("plan"): predict the contact place from the trials, not from the coarse chain,
      whose contact jumps between segment pairs (measured: soft rope, 20 links, fitted: stalls at
      0.085 with the model's place, reaches 0.037 in 6 trials with it frozen).
    method "renormalise": after every real trial the model's parameters are refitted to the trials
      so far (renormalise.py; the model's values at the call are the first start, and the prior's
      centre unless `prior_centre` is given), and the next command comes from the refitted model in a
      trust region that follows how well it predicted the last trial: with steps "gn" a Gauss-Newton step
      through the refitted chain's sensitivity, corrected by all trials (secant.py); with steps "plan" a plan
      on the refitted model (with refit_offset plus its remaining offset at the best trial and a Broyden
      term per other trial).
    A trial that does not improve the best error is rejected: the next command is planned again
    around the best one (a real trial is the expensive thing), in half the radius for plan and qp and where
    the trust region adapts. trust_region (gn and renormalise; trust_region_for): "fixed" keeps `radius` at
    every step, "adaptive" follows renormalise.TrustRegion between min_radius and max_radius; left out, fixed
    for gn and adaptive for renormalise.
    on_trial(trial) is called as each trial's record is complete (before the next plan)."""
    from wrenorm.tasks.rope.control import plan as rope_plan

    if method not in ("gn", "plan", "qp", "renormalise"):
        raise InputError("--method", "method", f"{method!r} is not 'gn', 'plan', 'qp' or 'renormalise'")
    if steps not in ("gn", "plan"):
        raise InputError("--method", "steps", f"{steps!r} is not 'gn' or 'plan'")
    if linearise_at not in ("matched", "trial"):
        raise InputError("--linearise-at", "linearise_at", f"{linearise_at!r} is not 'matched' or 'trial'")
    if first_step not in ("gn", "space-mapping"):
        raise InputError("--first-step", "first_step", f"{first_step!r} is not 'gn' or 'space-mapping'")
    gn_steps = takes_gn_steps(method, steps)
    check_first_step(first_step, gn_steps, linearise_at)
    if recorded_until not in ("first", "every"):
        raise InputError("--start-pair", "recorded_until", f"{recorded_until!r} is not 'first' or 'every'")
    if recorded and not gn_steps:
        raise InputError("--start-pair", "recorded", "a recorded pair corrects the Gauss-Newton steps' sensitivity: "
                                                     "it needs --method gn (the plan and qp loops would ignore it)")
    if max_trials < 1:
        raise InputError("--max-trials", "max_trials", f"must be >= 1, got {max_trials}")
    _check_loop_number(first_plan_reg, "--first-plan-reg", "first_plan_reg", False,
                       plans_first(method, steps, plan_first),
                       f"weighs the first plan, and the {method} loop here makes none (qp, or --no-plan-first)")
    if first_plan_offset is not None:
        if not plans_first(method, steps, plan_first):
            raise InputError("--first-plan-offset", "first_plan_offset",
                             f"shifts the first plan, and the {method} loop here makes none (qp, or --no-plan-first)")
        ok = isinstance(first_plan_offset, tuple) and len(first_plan_offset) == 2 and isinstance(
            first_plan_offset[1], crit.CriticalStates) and np.shape(first_plan_offset[0]) == (model.space.dim,)
        if not ok:
            raise InputError("--first-plan-offset", "first_plan_offset", f"must be (a command u of the model's "
                             f"{model.space.dim} dimensions, the real rope's CriticalStates under it)")
    space = model.space
    problems = space.violations(u0)
    if problems:
        raise InputError("command", "start", "; ".join(problems))
    trust = None
    if method in ("gn", "renormalise"):
        trust = trust_region_for(method, steps, trust_region, radius, min_radius, max_radius, space.bound)
    elif trust_region is not None or max_radius is not None or min_radius is not None:
        raise InputError("--trust-region/--min-radius/--max-radius", "trust_region", f"the {method} loop has no "
                                                                                     "trust region of these (--method "
                                                                                     "gn or renormalised runs)")
    _check_loop_number(velocity_weight, "--velocity-weight", "velocity_weight", False, gn_steps,
                       f"weighs Gauss-Newton steps; the {method} loop (steps {steps}) has none")
    _check_loop_number(secant_locality, "--secant-locality", "secant_locality", True, gn_steps,
                       f"weighs the Gauss-Newton steps' secant pairs; the {method} loop (steps {steps}) has none")
    _check_loop_number(velocity_modes, "--velocity-modes", "velocity_modes", True, gn_steps,
                       f"shapes Gauss-Newton steps; the {method} loop (steps {steps}) has none",
                       whole_up_to=crit.SAMPLES)
    if trust_norm is not None:
        if trust_norm not in gauss_newton.TRUST_NORMS:
            raise InputError("--trust-norm", "trust_norm", f"{trust_norm!r} is not one of "
                                                           f"{', '.join(gauss_newton.TRUST_NORMS)}")
        if not gn_steps:
            raise InputError("--trust-norm", "trust_norm", f"shapes Gauss-Newton steps' trust region; the {method} "
                                                           f"loop (steps {steps}) has none")
    if secant_locality is not None and secant is False:
        raise InputError("--secant-locality", "secant_locality", "weighs the secant pairs, and --no-secant uses none")
    if gn_steps:
        if first_plan_reg is None:
            first_plan_reg = gauss_newton.FIRST_PLAN_REG
        if velocity_weight is None:
            velocity_weight = gauss_newton.VELOCITY_WEIGHT if method == "gn" else 1.0
        if velocity_modes is None:
            velocity_modes = crit.SAMPLES if method == "gn" else gauss_newton.VELOCITY_MODES
        trust.norm = trust_norm or "box"
        renorm = None
        if method == "renormalise":
            renorm = _refit_settings(model, prior_centre, prior_scale, decay, refit_generations)
        return _correct_secant(real, model, goal, np.asarray(u0, dtype=np.float64), max_trials, tolerance, radius,
                               reg, seed, popsize, generations, trust, progress, on_trial, renorm,
                               plan_first=plan_first, secant=True if secant is None else bool(secant),
                               linearise_at=linearise_at, first_step=first_step, recorded=recorded,
                               recorded_until=recorded_until, velocity_weight=float(velocity_weight),
                               secant_locality=None if secant_locality is None else float(secant_locality),
                               first_plan_reg=first_plan_reg, first_plan_offset=first_plan_offset,
                               velocity_modes=int(velocity_modes))
    if method == "renormalise":
        return _correct_renormalising(real, model, goal, np.asarray(u0, dtype=np.float64), max_trials, tolerance,
                                      radius, reg, seed, popsize, generations, freeze_place, refit_offset,
                                      prior_scale, decay, anchored, refit_generations, trust, progress,
                                      on_trial, prior_centre, first_plan_reg, first_plan_offset)
    secant = (method == "plan") if secant is None else secant
    radius = (DEFAULT_PLAN_RADIUS if method == "plan" else DEFAULT_RADIUS) if radius is None else radius
    reg = (rope_plan.DEFAULT_REG if method == "plan" else DEFAULT_REG) if reg is None else reg
    plan_opts = {"popsize": popsize or rope_plan.DEFAULT_POPSIZE,
                 "generations": generations or rope_plan.DEFAULT_GENERATIONS, "reg": reg}
    u0 = np.asarray(u0, dtype=np.float64)
    u, planning = u0.copy(), {}
    trials: list[Trial] = []
    best: Trial | None = None
    predicted, scale_used, F_last, F_used = None, None, None, None
    D = np.zeros((goal.dim, space.dim))  # learned correction of the model's sensitivity (qp, secant=True)
    offset, last_plan, first_offset = None, [], None
    if method == "plan" and plan_first:
        p, u, scale_used, planning, first_offset = _first_plan(model, goal, u0, seed, plan_opts, progress,
                                                               first_plan_reg, first_plan_offset)
        predicted, last_plan = p["predicted_total"], [u.copy()]
    for k in range(max_trials):
        t = time.perf_counter()
        st, terms = _measure(real, space, goal, u)
        accepted = best is None or float(terms["total"][0]) < best.total
        trial = Trial(k, u.copy(), terms, bool(st.hit[0]), accepted, radius, st, time.perf_counter() - t,
                      predicted, scale_used, model_values=model.values.copy())
        if method == "plan":
            # trial 1 was predicted with the plan's offset (zero, or the start throw's); later ones with the trials'
            trial.predicted_state = rope_plan.predicted_states(
                model, u[None], offset or first_offset or rope_plan.Offset.zero(space.dim, goal.dim, u))[0]
        trials.append(trial)
        d_new = None
        if method == "plan":
            st_model = model.states(u[None])
            trial.model_total = float(goal.terms(st_model)["total"][0])
            d_new = (rope_plan.state_vector(st) - rope_plan.state_vector(st_model))[0]
            if not np.all(np.isfinite(d_new)):
                d_new = None  # the real rope or the model missed: no offset to learn here
            if d_new is not None and offset is not None and secant:
                d_pair = d_new.copy()
                if offset.model_place is not None:  # the prediction holds the model's place fixed
                    d_pair[-2:] = st.s[0] - offset.model_place
                offset.broyden(u, d_pair)
        elif best is not None and secant:
            # Broyden: make the correction term reproduce the change this trial really made
            du_real = u - best.u
            de_real = goal.residual(st)[0] - goal.residual(best.state)[0]
            if np.all(np.isfinite(de_real)) and du_real @ du_real > 0:
                D += np.outer(de_real - (F_used @ du_real), du_real) / (du_real @ du_real)
        if accepted:
            if best is not None:
                radius = min(2.0 * radius, 2.0 * space.bound)
            best = trial
            if d_new is not None:
                if offset is None:
                    offset = rope_plan.Offset.zero(space.dim, goal.dim)
                offset.recentre(u, d_new)
                if freeze_place:
                    offset.model_place = st_model.s[0].copy()
        else:
            # the step that failed may have been shorter than the radius: halve what was tried
            radius = 0.5 * min(radius, float(np.abs(u - best.u).max()))
        if progress:
            extra = "" if trial.predicted_total is None else f"  predicted {trial.predicted_total:.3f}"
            extra += "" if trial.model_total is None else f", model alone {trial.model_total:.3f}"
            progress(f"  trial {k + 1}/{max_trials}: error {trial.total:.4f}"
                     f"{'' if trial.hit else ' (no self-collision)'}{'' if accepted else ' (rejected)'}"
                     f"{extra}  real {trial.wall_s:.1f} s")
        if on_trial:
            on_trial(trial)
        if best.total <= tolerance or k == max_trials - 1:
            break
        if method == "plan":
            off = offset or rope_plan.Offset.zero(space.dim, goal.dim, best.u)
            p, u, scale_used, radius = _plan_or_look_closer(model, goal, best.u, radius, off, seed + 10 * k,
                                                            last_plan, plan_opts)
            predicted = p["predicted_total"]
            last_plan = [u.copy()]
            trials[-1].sensitivity = {"plan_evaluations": p["evaluations"], "plan_wall_s": p["wall_s"],
                                      "plan_radius": radius, "offset_centre_trial": (
                                          None if offset is None else
                                          next(t.index + 1 for t in trials if np.array_equal(t.u, offset.centre))),
                                      "offset_norm": None if offset is None else float(np.linalg.norm(offset.d))}
            if np.abs(u - best.u).max() < 1e-9:
                if progress:
                    progress("  the plan predicts no better command than the best one; stopping")
                break
            continue
        e_best = goal.residual(best.state)[0]
        F, info = model.sensitivity(best.u, goal, fd_step)
        # Where the coarse chain misses the collision it has no critical state to differentiate;
        # the last trusted sensitivity (same task, nearby command) is the best guess there.
        valid = info["centre_hit"] and info["columns"].count("none") <= len(info["columns"]) // 2
        if valid:
            F_last = F
        elif F_last is not None:
            F = F_last
        info["reused_previous"] = not valid and F_last is not None
        F_used = F + D
        du = qp_step(F_used, e_best, best.u, space, radius, reg)
        u, scale_used = space.limit_step(best.u, du)
        predicted = float(np.linalg.norm(F_used @ (u - best.u) + e_best))
        trials[-1].sensitivity = {"fd_rollouts": info["rollouts"], "fd_wall_s": info["wall_s"],
                                  "coarse_hits_at_centre": info["centre_hit"],
                                  "reused_previous_sensitivity": info["reused_previous"],
                                  "columns_not_central": [space.names[i] for i, c in enumerate(info["columns"])
                                                          if c != "central"],
                                  "singular_values": np.linalg.svd(F, compute_uv=False).tolist()}
        if scale_used == 0.0:
            if progress:
                progress("  no feasible step inside the hand limits; stopping")
            break
    success = best.total <= tolerance
    return {
        "success": bool(success),
        "method": method, "secant": bool(secant), "plan_first": bool(method == "plan" and plan_first),
        "trial0_plan": planning or None,
        "trials_used": len(trials),
        "trials_to_tolerance": (next(t.index + 1 for t in trials if t.total <= tolerance) if success else None),
        "best_error": best.total,
        "best_trial": best.index + 1,
        "best_u": best.u,
        "trials": trials,
    }


def _check_loop_number(value, flag: str, key: str, positive: bool, applies: bool, why_not: str,
                       whole_up_to: int | None = None) -> None:
    """A number option of the loop: only where it `applies` (e.g. the loop takes Gauss-Newton steps), finite
    and >= 0 (> 0 when `positive`); with `whole_up_to`, a whole number in 1..whole_up_to. None (left out) passes."""
    if value is None:
        return
    if not applies:
        raise InputError(flag, key, why_not)
    if whole_up_to is not None:
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or not 1 <= value <= whole_up_to:
            raise InputError(flag, key, f"{value!r} is not a whole number in 1-{whole_up_to}")
        return
    if not (isinstance(value, (int, float)) and not isinstance(value, bool) and np.isfinite(value)
            and (value > 0 if positive else value >= 0)):
        raise InputError(flag, key, f"{value!r} is not a finite number {'> 0' if positive else '>= 0'}")


def plans_first(method: str, steps: str, plan_first: bool) -> bool:
    """Whether correct()'s loop for `method` (and `steps`, for renormalise) plans trial 1 on the chain: qp never
    does, the renormalised plan loop always, the others unless plan_first is off."""
    return (method in ("gn", "plan") and plan_first) or (method == "renormalise" and (plan_first or steps == "plan"))


def takes_gn_steps(method: str, steps: str) -> bool:
    """Whether correct()'s loop for `method` (and `steps`, for renormalise) steps by Gauss-Newton (secant.py)."""
    return method == "gn" or (method == "renormalise" and steps == "gn")


def trust_region_for(method: str, steps: str, rule: str | None, radius: float | None, min_radius: float | None,
                     max_radius: float | None, bound: float):
    """The trust region of the gn and renormalise loops. rule "fixed": every step may go `radius` (GN_RADIUS) from the
    best command, whatever the last prediction did (the fixed-parameter runs' default: README, "A fixed step instead of
    the adaptive trust region"); "adaptive": renormalise.TrustRegion's rule between min_radius (MIN_RADIUS) and
    max_radius (twice the command box's bound), the renormalised runs' default. Left out (None): by the method."""
    from wrenorm.tasks.rope.control import renormalise as rn

    rule = rule or ("fixed" if method == "gn" else "adaptive")
    if rule not in ("fixed", "adaptive"):
        raise InputError("--trust-region", "trust_region", f"{rule!r} is not 'fixed' or 'adaptive'")
    first = radius if radius is not None else (gauss_newton.GN_RADIUS if takes_gn_steps(method, steps)
                                               else DEFAULT_PLAN_RADIUS)
    if rule == "fixed":
        if min_radius is not None or max_radius is not None:
            raise InputError("--min-radius/--max-radius", "trust_region", "bound the adaptive trust region; this run's "
                                                                          f"is fixed at {first:g} (--trust-region "
                                                                          "adaptive to use them)")
        return rn.TrustRegion(first, first, first, rule="fixed")
    # left out, a bound gives way to the initial radius (as before the bounds were options: --radius 0.2 adapts down
    # to 0.2); given, it must hold it
    smallest = min(rn.MIN_RADIUS, first) if min_radius is None else float(min_radius)
    largest = max(2.0 * bound, first) if max_radius is None else float(max_radius)
    if not smallest <= first <= largest:
        raise InputError("--radius/--min-radius/--max-radius", "trust_region", f"the initial radius {first:g} must lie "
                                                                               f"between the smallest {smallest:g} "
                                                                               f"and the largest {largest:g}")
    return rn.TrustRegion(first, largest, smallest)


def check_first_step(first_step: str, gn_steps: bool, linearise_at: str) -> None:
    """Space mapping's step is taken from the match of trial 1, so it needs Gauss-Newton steps and the match."""
    if first_step == "space-mapping" and not (gn_steps and linearise_at == "matched"):
        raise InputError("--first-step", "first_step", "space mapping's step needs Gauss-Newton steps (--method gn) "
                                                       "and the match (--linearise-at matched)")


def _first_plan(model: CoarseModel, goal: crit.Target, u0: np.ndarray, seed: int, plan_opts: dict, progress,
                reg: float | None = None, recorded: tuple | None = None):
    """Trial 0: the model alone picks the first real command, in the whole box around the start, paying `reg`
    (default: the plans' own) per squared unit of u away from it; with `recorded` (u, the real rope's critical state
    there) on the model plus the rope's offset from it there (plan.start_offset).
    Returns (plan, feasible command, its step scale, what the planning did, the offset planned with)."""
    from wrenorm.tasks.rope.control import plan as rope_plan

    space = model.space
    opts = plan_opts if reg is None else plan_opts | {"reg": float(reg)}
    offset, chain_there = None, None
    if recorded is not None:
        offset, chain_there = rope_plan.start_offset(model, recorded[0], recorded[1])
    zero = offset is None
    if zero:
        offset = rope_plan.Offset.zero(space.dim, goal.dim, u0)
    p = rope_plan.plan(model, goal, u0, 2.0 * space.bound, offset, seed=seed, **opts)
    u, scale_used = _feasible(space, u0, p["u"])
    planning = {"model_total_at_start": _model_total(model, goal, u0), "model_total_at_plan": p["model_total"],
                "evaluations": p["evaluations"], "wall_s": p["wall_s"], "reg": opts["reg"],
                "distance_from_start": float(np.linalg.norm(u - u0))}
    miss = None if zero else float(
        crit.Target(recorded[1], goal.length, goal.speed, dict(goal.weights)).terms(chain_there)["total"][0])
    if recorded is not None:  # None: a recording was given and gave no offset
        planning["offset"] = None if zero else {"at_command_u": np.asarray(recorded[0], dtype=np.float64).tolist(),
                                                "chain_error_to_rope_there": miss,
                                                "predicted_total_at_plan": p["predicted_total"]}
    if progress:
        shifted = "" if zero else (f" (+ the rope's offset under the recorded command, where the chain misses the "
                                   f"rope's state by {miss:.3f}: predicted {p['predicted_total']:.3f})")
        progress(f"  plan for trial 1 (on the model {'alone' if zero else 'and offset'}): model error "
                 f"{planning['model_total_at_start']:.3f} at the start -> {p['model_total']:.3f}{shifted} at "
                 f"{planning['distance_from_start']:.2f} from it (Euclidean, units of u; weight {opts['reg']:g} per "
                 f"unit squared), {p['evaluations']} coarse rollouts, {p['wall_s']:.1f} s")
        if recorded is not None and zero:
            progress("  no offset for trial 1: the rope or the chain misses itself under the recorded command")
    return p, u, scale_used, planning, offset


def _measure(real, space: CommandSpace, goal: crit.Target, u: np.ndarray):
    """The real rope's critical state under command u, and its error terms against the goal."""
    st = crit.from_reference(real(space.decode(u)))
    return st, {key: np.asarray(v, dtype=np.float64) for key, v in goal.terms(st).items()}


def _correct_renormalising(real, model: CoarseModel, goal: crit.Target, u0: np.ndarray, max_trials: int,
                           tolerance: float, radius: float | None, reg: float | None, seed: int,
                           popsize: int | None, generations: int | None, freeze_place: bool, refit_offset: bool,
                           prior_scale: float | None, decay: float | None, anchored: bool,
                           refit_generations: int | None, trust, progress, on_trial,
                           prior_centre: np.ndarray | None = None, first_plan_reg: float | None = None,
                           first_plan_offset: tuple | None = None) -> dict:
    """The correction loop with the model renormalised after every trial (see correct(), renormalise.py)."""
    from wrenorm.tasks.rope.control import plan as rope_plan

    space, pspace = model.space, model.problem.space
    settings = _refit_settings(model, prior_centre, prior_scale, decay, refit_generations)
    prior_centre, prior_scale, decay = settings["prior_centre"], settings["prior_scale"], settings["decay"]
    plan_opts = {"popsize": popsize or rope_plan.DEFAULT_POPSIZE,
                 "generations": generations or rope_plan.DEFAULT_GENERATIONS,
                 "reg": rope_plan.DEFAULT_REG if reg is None else reg}
    p, u, scale_used, planning, offset = _first_plan(model, goal, u0, seed, plan_opts, progress, first_plan_reg,
                                                     first_plan_offset)
    last_plan = [u.copy()]
    trials: list[Trial] = []
    hits: list[tuple[int, np.ndarray, crit.CriticalStates]] = []
    best: Trial | None = None
    plan_radius = 2.0 * space.bound
    for k in range(max_trials):
        pred_state, alone = rope_plan.predicted_states(model, u[None], offset)
        predicted = float(goal.terms(pred_state)["total"][0])
        trial = _real_trial(real, model, goal, k, u, best, trust, plan_radius, predicted, scale_used,
                            float(goal.terms(alone)["total"][0]), pred_state)
        trials.append(trial)
        if trial.accepted:
            best = trial
        if trial.hit:
            hits.append((k, u.copy(), trial.state))
        if _reported_and_done(trial, best, max_trials, tolerance, trust.radius, progress, on_trial):
            break
        # renormalise: refit the chain to the trials so far, then plan on it around the best trial
        if hits:
            model = _refit_to_trials(model, hits, goal, trial, settings, best.index, seed + 100 * k, progress,
                                     anchored)
        offset = rope_plan.Offset.zero(space.dim, goal.dim, best.u)
        if refit_offset and best.hit:
            offset = _offset_from_trials(model, trials, best, freeze_place)
        p, u, scale_used, plan_radius = _plan_or_look_closer(model, goal, best.u, trust.radius, offset,
                                                             seed + 10 * k, last_plan, plan_opts)
        trust.look_closer(plan_radius)  # plan_radius: the radius the next trial was planned in, for its record
        last_plan = [u.copy()]
        trial.sensitivity = {"plan_evaluations": p["evaluations"], "plan_wall_s": p["wall_s"],
                             "plan_radius": plan_radius, "offset_at_trial": best.index + 1 if refit_offset else None,
                             "offset_norm": float(np.linalg.norm(offset.d))}
        if on_trial:
            on_trial(trial)
        if np.abs(u - best.u).max() < 1e-9:
            if progress:
                progress("  the plan predicts no better command than the best one; stopping")
            break
    success = best.total <= tolerance
    return {
        "success": bool(success), "method": "renormalise", "secant": False, "plan_first": True,
        "trial0_plan": planning,
        "trials_used": len(trials),
        "trials_to_tolerance": (next(t.index + 1 for t in trials if t.total <= tolerance) if success else None),
        "best_error": best.total, "best_trial": best.index + 1, "best_u": best.u,
        "final_parameters": pspace.as_dict(model.values),
        "renormalise": {"prior_centre": pspace.as_dict(prior_centre), "prior_scale": prior_scale, "decay": decay,
                        "refit_offset": bool(refit_offset), "anchored": bool(anchored), "trust_region": {
                            "good": trust.GOOD, "bad": trust.BAD, "grow": trust.GROW, "shrink": trust.SHRINK,
                            "min_radius": trust.min_radius, "max_radius": trust.max_radius,
                            "rule": trust.rule, "norm": trust.norm}},
        "trials": trials,
    }


def _real_trial(real, model: CoarseModel, goal: crit.Target, k: int, u: np.ndarray, best: Trial | None, trust,
                plan_radius: float, predicted: float, scale_used, model_total: float, pred_state) -> Trial:
    """Trial k at command u on the real rope: its record, accepted when it beats the best so far, and the trust
    region's verdict on the prediction that chose it."""
    t = time.perf_counter()
    st, terms = _measure(real, model.space, goal, u)
    accepted = best is None or float(terms["total"][0]) < best.total
    trial = Trial(k, u.copy(), terms, bool(st.hit[0]), accepted, plan_radius, st, time.perf_counter() - t,
                  predicted, scale_used, model_total, predicted_state=pred_state, model_values=model.values.copy())
    if best is not None:
        trial.trust = trust.update(best.total, predicted, trial.total, trust.length(u - best.u))
    return trial


def _trial_line(trial: Trial, max_trials: int, radius: float) -> str:
    """One trial's progress line in the trust-region loops: error, prediction, the trust verdict."""
    extra = f"  predicted {trial.predicted_total:.3f}, model alone {trial.model_total:.3f}"
    if trial.trust:
        rho = trial.trust["rho"]
        extra += f"; rho {'nan' if rho is None else f'{rho:.2f}'} -> {trial.trust['verdict']} radius {radius:.2f}"
    return (f"  trial {trial.index + 1}/{max_trials}: error {trial.total:.4f}"
            f"{'' if trial.hit else ' (no self-collision)'}{'' if trial.accepted else ' (rejected)'}"
            f"{extra}  real {trial.wall_s:.1f} s")


def _reported_and_done(trial: Trial, best: Trial, max_trials: int, tolerance: float, radius: float, progress,
                       on_trial) -> bool:
    """Say how the trial went; True when the loop ends with it (its record is then handed on here, as no step
    follows to complete it)."""
    if progress:
        progress(_trial_line(trial, max_trials, radius))
    done = best.total <= tolerance or trial.index == max_trials - 1
    if done and on_trial:
        on_trial(trial)
    return done


def _refit_to_trials(model: CoarseModel, hits: list, goal: crit.Target, trial: Trial, settings: dict,
                     best_index: int, seed: int, progress, anchored: bool = False) -> CoarseModel:
    """Renormalise: the chain refitted to the trials that hit so far (renormalise.refit, with the prior and trial
    weights of `settings`); the refit goes into `trial`'s record and the progress line."""
    from wrenorm.tasks.rope.control import renormalise as rn

    pspace, centre = model.problem.space, settings["prior_centre"]
    r = rn.refit(model, hits, goal, model.values, centre, best=best_index, seed=seed,
                 prior_scale=settings["prior_scale"], decay=settings["decay"], anchored=anchored,
                 generations=settings["generations"])
    trial.refit = r.as_dict(pspace)
    if progress:
        moved = ", ".join(f"{n} x{v / centre[i]:.2g}" for i, (n, v) in enumerate(zip(pspace.names, r.values))
                          if pspace.parameters[i].frozen is False and centre[i] > 0)
        progress(f"    refit to {len(hits)} trials: loss {r.loss_start:.3f} -> {r.loss:.3f} "
                 f"({r.evaluations} chains x trials, {r.wall_s:.1f} s); vs the prior's centre: {moved}")
    return CoarseModel(model.problem, r.values, model.space, model.label)


def _refit_settings(model, prior_centre, prior_scale, decay, refit_generations) -> dict:
    from wrenorm.tasks.rope.control import renormalise as rn

    prior_scale = rn.PRIOR_SCALE if prior_scale is None else float(prior_scale)
    decay = rn.DECAY if decay is None else float(decay)
    if not prior_scale > 0 or not 0 < decay <= 1:
        raise InputError("--prior-scale/--decay", "value", f"need prior scale > 0 and decay in (0, 1], got "
                                                           f"{prior_scale:g}, {decay:g}")
    return {"prior_centre": model.values.copy() if prior_centre is None else np.asarray(prior_centre, np.float64),
            "prior_scale": prior_scale, "decay": decay, "generations": refit_generations or rn.REFIT_GENERATIONS}


def _correct_secant(real, model: CoarseModel, goal: crit.Target, u0: np.ndarray, max_trials: int,
                    tolerance: float, radius: float | None, reg: float | None, seed: int, popsize: int | None,
                    generations: int | None, trust, progress, on_trial,
                    renorm: dict | None, plan_first: bool = True, secant: bool = True,
                    linearise_at: str = "matched", first_step: str = "gn", recorded: list | None = None,
                    recorded_until: str = "first", velocity_weight: float = 1.0,
                    secant_locality: float | None = None, first_plan_reg: float | None = None,
                    first_plan_offset: tuple | None = None, velocity_modes: int = crit.SAMPLES) -> dict:
    """The correction loop of Gauss-Newton steps through the chain's sensitivity corrected by the trials
    (secant.py); with `renorm` the chain is refitted to the trials after each one (renormalise.refit). Without
    plan_first the start command is trial 1; without secant the trials do not correct the chain's sensitivity.
    linearise_at "matched" measures the chain's sensitivity where the chain reproduces the first hit's real critical
    state (secant.matched_command), "trial" at that trial's own command. first_step "space-mapping": trial 2 is
    space mapping's step from the match of the planned trial 1 (fixed parameters only: a chain refitted to trial 1
    reproduces it at its own command, so its match would not move). recorded: the real rope's critical states
    under commands recorded before the trials, secant pairs beside the trials' own: with recorded_until "first" only
    while the trials have none (a pair across the ~3 units from the start throw to trial 1 is the mean slope over a
    long stretch: it helps the first step, and once the trials give local pairs it blurs them; README, "The start
    throw as one more secant pair"), with "every" at every step."""
    from wrenorm.tasks.rope.control import plan as rope_plan

    recorded = [(np.asarray(u, dtype=np.float64), st) for u, st in (recorded or []) if st.hit[0]]

    space, pspace = model.space, model.problem.space
    plan_opts = {"popsize": popsize or rope_plan.DEFAULT_POPSIZE,
                 "generations": generations or rope_plan.DEFAULT_GENERATIONS, "reg": rope_plan.DEFAULT_REG}
    reg = gauss_newton.GN_REG if reg is None else float(reg)
    w = gauss_newton.residual_weights(goal)
    rows = gauss_newton.step_row_weights(goal, velocity_weight)
    projection = gauss_newton.velocity_projection(goal, velocity_modes)
    u, scale_used, planning = u0.copy(), None, None
    if plan_first:
        _, u, scale_used, planning, offset = _first_plan(model, goal, u0, seed, plan_opts, progress, first_plan_reg,
                                                         first_plan_offset)
        pred_state = rope_plan.predicted_states(model, u[None], offset)[0]
    else:
        pred_state = model.states(u[None])
    predicted = float(goal.terms(pred_state)["total"][0])
    trials: list[Trial] = []
    best: Trial | None = None
    sens: gauss_newton.Sensitivity | None = None
    plan_radius, stopped, stop_reason = 2.0 * space.bound, None, None
    for k in range(max_trials):
        trial = _real_trial(real, model, goal, k, u, best, trust, plan_radius, predicted, scale_used,
                            _model_total(model, goal, u), pred_state)
        trials.append(trial)
        if trial.accepted:
            best = trial
        if _reported_and_done(trial, best, max_trials, tolerance, trust.radius, progress, on_trial):
            break
        hits = [(tr.index, tr.u, tr.state) for tr in trials if tr.hit]
        if renorm is not None and hits:
            model = _refit_to_trials(model, hits, goal, trial, renorm, best.index, seed + 100 * k, progress)
        if not best.hit:
            # no critical state to step from: the chain plans alone around the best command
            p, u, scale_used, plan_radius = _plan_or_look_closer(
                model, goal, best.u, trust.radius, rope_plan.Offset.zero(space.dim, goal.dim, best.u),
                seed + 10 * k, [], plan_opts)
            trust.look_closer(plan_radius)
            pred_state = model.states(u[None])
            trial.sensitivity = {"plan_evaluations": p["evaluations"], "why": "no critical state to step from"}
        else:
            if renorm is not None or sens is None:
                # one linearisation point for the whole run (the first trial that hit): the chain's sensitivity
                # is rough from point to point, and moving the point swaps that roughness for another's
                first = next(tr for tr in trials if tr.hit)
                match = None
                if linearise_at == "matched":
                    match = gauss_newton.matched_command(model, rope_plan.state_vector(first.state)[0], w, first.u,
                                                         seed)
                sens = gauss_newton.Sensitivity.of_chain(model, first.u if match is None else match.u)
                sens.match = match
                if progress and match is not None:
                    progress(f"    chain's sensitivity measured where it matches trial {first.index + 1}'s real state: "
                             f"misfit {match.misfit_at_trial:.3f} at its command -> {match.misfit:.3f}, "
                             f"{match.distance:.2f} away ({match.chain_rollouts} chains, "
                             f"{match.wall_s:.1f} s)")
            if secant:
                sens.ridge(*gauss_newton.secant_pairs(trials, best, recorded, recorded_until),
                           locality=secant_locality)
            step, e_best = "gauss-newton", goal.residual(best.state)[0]
            if first_step == "space-mapping" and k == 0 and plan_first and renorm is None:
                step = "space mapping"
                u, scale_used = gauss_newton.space_mapping_step(sens.match, space)
                if progress:
                    progress(f"    space mapping's step from trial 1: {np.abs(u - best.u).max():.2f} units of u")
            else:
                u, scale_used = gauss_newton.gn_step(sens.S, w, e_best, best.u, space, trust.radius, reg, rows,
                                                     projection, trust.norm)
            pred_state = gauss_newton.predicted_state(best.state, sens.S, u - best.u)
            floor = gauss_newton.floor_record(goal, best.state, sens.S, best.u,
                                              gauss_newton.model_floor(goal, best.state, sens.S, w, e_best, best.u,
                                                                       space, rows, also=(u,)))
            trial.sensitivity = sens.record() | {"step": step, "model_floor": floor}
        predicted = float(goal.terms(pred_state)["total"][0])
        if best.hit:
            plan_radius = trust.radius
        trial.sensitivity["plan_radius"] = plan_radius
        if on_trial:
            on_trial(trial)
        if np.abs(u - best.u).max() < 1e-9:
            stopped, stop_reason = "the step predicts no better command than the best one", "no_better_command"
            if sens is not None and all(c == "none" for c in sens.columns):
                pb = model.problem
                stop_reason = "chain_never_hits"
                stopped = (f"the coarse chain ({pb.segments} links, dt {pb.dt:g} s) does not hit itself on either side "
                           "of any command direction where it was linearised: it has no critical state to steer by "
                           "at this resolution")
            if progress:
                progress(f"  {stopped}; stopping")
            break
    success = best.total <= tolerance
    out = {
        "success": bool(success), "method": "renormalise" if renorm is not None else "gn", "steps": "gn",
        "secant": bool(secant), "plan_first": bool(plan_first), "trial0_plan": planning, "trials_used": len(trials),
        "trials_to_tolerance": (next(t.index + 1 for t in trials if t.total <= tolerance) if success else None),
        "best_error": best.total, "best_trial": best.index + 1, "best_u": best.u, "stopped": stopped,
        "stop_reason": stop_reason if stopped else None,
        "first_step": (trials[0].sensitivity or {}).get("step"),  # how trial 2 was chosen (None: no trial 2)
        "recorded_pairs": len(recorded) if secant else 0, "recorded_until": recorded_until,
        "gauss_newton": {"fd_step": gauss_newton.GN_FD_STEP, "reg": reg, "velocity_weight": velocity_weight,
                         "velocity_modes": velocity_modes,
                         "ridge": gauss_newton.RIDGE if secant else None,
                         "secant_locality": secant_locality if secant else None,
                         "correction": "ridge over all trials" if secant else "none",
                         "trust_region": {"good": trust.GOOD, "bad": trust.BAD, "grow": trust.GROW,
                                          "shrink": trust.SHRINK, "min_radius": trust.min_radius,
                                          "max_radius": trust.max_radius, "rule": trust.rule,
                                          "norm": trust.norm}},
        "trials": trials,
    }
    if renorm is not None:
        out["final_parameters"] = pspace.as_dict(model.values)
        out["renormalise"] = {"prior_centre": pspace.as_dict(renorm["prior_centre"]),
                              "prior_scale": renorm["prior_scale"], "decay": renorm["decay"]}
    return out


def _offset_from_trials(model: CoarseModel, trials: list[Trial], best: Trial, freeze_place: bool):
    """The refitted model's remaining offset, learned from the trials as the fixed-parameter loop learns it:
    d = Z_real - Z_model at the best trial, then a Broyden update per other trial that hit, oldest first, so
    the latest trials are reproduced most exactly. One rollout for all trials."""
    from wrenorm.tasks.rope.control import plan as rope_plan

    space = model.space
    others = [t for t in trials if t.hit and t is not best]
    st = model.states(np.stack([best.u] + [t.u for t in others]))
    Zm = rope_plan.state_vector(st)
    offset = rope_plan.Offset.zero(space.dim, Zm.shape[1], best.u)
    d = rope_plan.state_vector(best.state)[0] - Zm[0]
    if not np.all(np.isfinite(d)):
        return offset  # the refitted chain misses at the best command: plan on the chain alone
    offset.recentre(best.u, d)
    if freeze_place:
        offset.model_place = st.s[0].copy()
    for j, t in enumerate(others, start=1):
        dk = rope_plan.state_vector(t.state)[0] - Zm[j]
        if freeze_place:
            dk[-2:] = t.state.s[0] - offset.model_place
        offset.broyden(t.u, dk)
    return offset


def _feasible(space: CommandSpace, start: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, float]:
    """target if it is inside the box and the hand limits, else the longest feasible step toward it."""
    return space.limit_step(start, np.asarray(target, dtype=np.float64) - start)


def _model_total(model: CoarseModel, goal: crit.Target, u: np.ndarray) -> float:
    return float(goal.terms(model.states(np.asarray(u, dtype=np.float64)[None]))["total"][0])


def state_record(st: crit.CriticalStates | None) -> dict | None:
    """One critical state as plain numbers: positions and velocities at the observable's arc-length points,
    time from the start of the motion, contact place; a rope that never hit has only its closest approach."""
    if st is None:
        return None
    if not st.hit[0]:
        return {"self_collision": False, "clearance_m": float(st.clearance[0])}
    return {"self_collision": True, "time": float(st.time[0]), "contact_arclength": st.s[0].tolist(),
            "positions": st.pos[0].tolist(), "velocities": st.vel[0].tolist()}


def trial_row(t: Trial, space: CommandSpace, parameter_space=None) -> dict:
    """What one trial did and why: command, predicted and measured critical state, error, the coarse
    parameters that predicted it (and, when renormalising, the refit after it), the trust radius."""
    named = (lambda v: None if v is None else parameter_space.as_dict(v)) if parameter_space is not None else \
        (lambda v: None if v is None else np.asarray(v).tolist())
    return {
        "trial": t.index + 1, "error": t.total, "accepted": t.accepted, "self_collision": t.hit,
        "terms": {k: float(v[0]) for k, v in t.terms.items()},
        "critical_time": float(t.state.time[0]) if t.hit else None,
        "contact_arclength": t.state.s[0].tolist() if t.hit else None,
        "command_u": t.u.tolist(),
        "hand_peak_speed": space.decode(t.u).max_speed(),
        "hand_peak_acceleration": space.decode(t.u).max_acceleration(),
        "trust_radius": t.radius, "step_scale": t.step_scale,
        "predicted_error": t.predicted_total, "model_alone_error": t.model_total,
        "predicted_state": state_record(t.predicted_state), "measured_state": state_record(t.state),
        "model_parameters": named(t.model_values),
        "refit": t.refit, "trust": t.trust,
        "next_step": t.sensitivity or None, "wall_s": t.wall_s,
    }


def trial_rows(trials: list[Trial], space: CommandSpace, parameter_space=None) -> list[dict]:
    return [trial_row(t, space, parameter_space) for t in trials]


# ------------------------------------------------------------------------------ parameters
def parameters_from_file(path, problem) -> np.ndarray:
    """Fitted values from a `wrenorm fit rope` result.json, in the problem's parameter order."""
    import json

    src = str(path)
    p = Path(path)
    if not p.is_file():
        raise InputError(src, "file", "does not exist or is not a file")
    try:
        data = json.loads(p.read_text())
    except (OSError, ValueError) as e:
        raise InputError(src, "file", f"is not readable JSON: {e}") from None
    if not isinstance(data, dict):
        raise InputError(src, "file", "top level must be an object")
    several = isinstance(data.get("runs"), list)
    runs = data["runs"] if several else [data]
    where = [f"runs[{i}]." if several else "" for i in range(len(runs))]
    rope = [(r, w) for r, w in zip(runs, where) if isinstance(r, dict) and r.get("task", "rope") == "rope"]
    for r, w in rope:
        if r.get("resolution") is not None and not isinstance(r["resolution"], dict):
            raise InputError(src, f"{w}resolution", f"must be an object, got {r['resolution']!r}")
    match = [(r, w) for r, w in rope
             if (r.get("resolution") or {}).get("segments", problem.segments) == problem.segments]
    if not match:
        raise InputError(src, "resolution", f"no rope fit at {problem.segments} segments in this file")
    fit, w = match[0]
    # effective parameters belong to the resolution they were fitted at: a chain stepped otherwise is another model
    for key, what in (("dt", "its time step (--dt)"), ("iterations", "its constraint passes (fit rope --iterations)")):
        theirs, ours = (fit.get("resolution") or {}).get(key), problem.resolution[key]
        if theirs is not None and (not isinstance(theirs, (int, float)) or not np.isclose(theirs, ours, rtol=1e-9)):
            raise InputError(src, f"{w}resolution.{key}", f"fitted at {theirs!r}, and this correction's chain runs at "
                                                          f"{ours:g}, {what}: refit at this resolution")
    params = fit.get("parameters")
    if not isinstance(params, dict):
        raise InputError(src, f"{w}parameters", "missing or not an object")
    values = problem.space.measured.copy()
    for i, prm in enumerate(problem.space.parameters):
        entry = params.get(prm.name)
        # the measured values are the rope's mass, thickness and stiffness: a fit of another rope steers this one with
        # that rope's effective values (a fit of the default rope ran the heavy rope's trials without a word)
        theirs = entry.get("measured") if isinstance(entry, dict) else None
        ours = problem.space.measured[i]
        if isinstance(theirs, (int, float)) and not np.isclose(theirs, ours, rtol=1e-6, atol=1e-12):
            raise InputError(src, f"{w}parameters.{prm.name}.measured",
                             f"{theirs:g} there and {ours:g} on the rope this correction steers: a fit of another "
                             "rope; fit this one (fit rope --reference its throws) or use --params fitted")
        if prm.frozen:
            if isinstance(entry, dict) and entry.get("frozen") is False:
                raise InputError(src, f"{w}parameters.{prm.name}", "was fitted there, and the correction's chain holds "
                                                                "it at its measured value: the fitted chain would not "
                                                                "be the one steered")
            continue
        v = entry.get("fitted") if isinstance(entry, dict) else None
        if not isinstance(v, (int, float)) or not np.isfinite(v):
            raise InputError(src, f"{w}parameters.{prm.name}.fitted", "missing or not a finite number")
        if not prm.lower <= v <= prm.upper:
            raise InputError(src, f"{w}parameters.{prm.name}.fitted", f"{v:g} outside [{prm.lower:g}, {prm.upper:g}]")
        values[i] = float(v)
    return values


def fit_parameters(variant: str, segments: int, dt: float, seed: int, generations: int, device: str = "cpu",
                   progress=None, throws: dict | None = None) -> tuple[np.ndarray, dict]:
    """Renormalised parameters: a short CMA-ES fit of RopeProblem to the rope's reference throws, `throws` (name ->
    RopeReference; recorded on the real rope) or, left out, the newton rope's built-in fit throws (cached)."""
    from wrenorm.search import cmaes
    from wrenorm.tasks.rope.problem import RopeProblem
    from wrenorm.tasks.rope.reference.generate import builtin_references
    from wrenorm.tasks.rope.reference.paths import FIT_PATHS

    if throws is None:
        throws = dict(zip(FIT_PATHS, builtin_references("fit", variant, progress=progress)))
    refs, names = list(throws.values()), list(throws)
    problem = RopeProblem(refs, segments=segments, dt=dt, device=device, names=names)
    t = time.perf_counter()
    res = cmaes(problem, seed=seed, generations=generations, quiet=True)
    losses = problem.errors(np.stack([problem.space.measured, res.best_values]), problem.train).mean(1)
    info = {"source": f"CMA-ES fit to {', '.join(names)} ({variant} rope)", "throws": names,
            "generations": len(res.history),
            "evaluations": res.evaluations, "loss_measured": float(losses[0]), "loss_fitted": float(losses[1]),
            "wall_s": time.perf_counter() - t, "reference_throws": len(refs),
            "values": problem.space.as_dict(res.best_values)}
    return res.best_values, info
