"""Rope task: effective parameters of a coarse flying-knot chain, fitted to the rope state at
the first self-collision (the "critical point") of a reference rope.

Resolution: `--segments S` links (S + 1 point masses, node 0 on the fingertip; the flying
knot's 11 masses are S = 10), the step `--dt` and the constraint passes per step
`--iterations`. Each condition is one hand path with one reference trajectory
(`--reference FILE ...`, default the built-in newton references).

The observable and its error (shape, velocity, time and place of the first self-collision, one
no-hit rule) are defined once in observable.py. report() also scores held-out chains that never hit
by their state at the reference's critical time (no_hit_bound), without the penalty constant.

Parameter mapping from the reference rope (length L, mass M, radius r, EI) to a chain with link
l = L / S: lumped masses (interior M / S, lead half of that, held node's half goes to the hand),
so the measured lead fraction is 1 / (2 S); bending stiffness per joint k = EI / l; bending
damping per joint b = k * BEND_DAMPING_TIME; quadratic air drag per length 0.5 rho_air C_d 2r;
linear drag 0; collision radius r; link compliance l / EA (newton's stretch stiffness). Total
mass is frozen: scaling mass, k, b and drag together leaves the motion unchanged, so only the
ratios are identifiable.

Why this parameter set, and what the coarse model cannot match: README, "Rope: how the parameter set was
chosen".
"""
from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from wrenorm.errors import InputError, warn
from wrenorm.kernels.rope import ChainParams, RopeSim, critical
from wrenorm.params import Parameter, ParameterSpace
from wrenorm.problem import Condition, Problem, finite_or_inf
from wrenorm.tasks.rope.observable import (
    MISS,
    NO_HIT,
    SAMPLES,
    WEIGHTS,
    Target,
    from_rollout,
    reference_critical,
    resample,
    stack_targets,
)
from wrenorm.tasks.rope.options import DT, DT_DEFAULT, FLOW_DT, FLOW_SEGMENTS, ITERATIONS, SEGMENTS_DEFAULT
from wrenorm.tasks.rope.reference.events import start_velocity, starts_at_rest

BEND_DAMPING_TIME = 2e-3  # s: internal friction time of a braided rope (as the newton reference)
RHO_AIR, CD_CYLINDER = 1.2, 1.2
# newton reference: 1e6 N/m per joint of 1.1/64 m, i.e. EA = 1.7e4 N; a link of length l has compliance l / EA
STRETCH_EA = 1e6 * 1.1 / 64
HAND_SPLINE_ABOVE = 0.0051  # s between frames: coarser than 200 Hz (a 200 Hz clock's rounding stays below)


def parameter_space(segments: int, length: float, mass: float, radius: float,
                    bend_stiffness: float | None) -> ParameterSpace:
    """The chain's parameters, measured from the rope (EI 3e-3 N m^2 where the reference does not give it)."""
    S, L, M = segments, length, mass
    link = L / S
    ei = bend_stiffness if bend_stiffness is not None else 3e-3
    k = ei / link
    lead = 1.0 / (2 * S)
    drag = 0.5 * RHO_AIR * CD_CYLINDER * 2.0 * radius
    return ParameterSpace([
        Parameter("mass", M, 0.5 * M, 2.0 * M, "log", frozen=True, unit="kg",
                  doc="total rope mass (frozen: only ratios to it are identifiable)"),
        # Bounds: every fit of the built-in references ran lead_fraction, bend_damping and
        # drag_quad into the original bounds (lead/4, 1e-2, 1e-3 of measured); they were widened
        # until the optimum sat inside or the loss stopped changing (README, "Rope fit").
        Parameter("lead_fraction", lead, lead / 25.0, 0.5, "log", unit="",
                  doc="share of the mass in the free-end (lead) node; the rest is spread evenly"),
        Parameter("bend_stiffness", k, k / 300, k * 30, "log", unit="N m/rad",
                  doc="bending stiffness per joint, energy 0.5 k theta^2 (measured EI / link)"),
        Parameter("bend_damping", k * BEND_DAMPING_TIME, k * BEND_DAMPING_TIME * 1e-4,
                  k * BEND_DAMPING_TIME * 1e3, "log", unit="N m s/rad",
                  doc="bending damping per joint, dissipation 0.5 b theta_dot^2"),
        Parameter("drag_quad", drag, drag * 1e-5, drag * 30, "log", unit="N s^2/m^3",
                  doc="quadratic air drag per unit length (0.5 rho C_d diameter; the newton reference has none)"),
        Parameter("drag_lin", 0.0, 0.0, 2.0 * M / L, "linear", unit="N s/m^2",
                  doc="linear drag per unit length (absorbs the reference's numerical damping)"),
        Parameter("stretch", link / STRETCH_EA, 1e-8, 1e-2, "log", frozen=True, unit="m/N",
                  doc="link compliance (XPBD): stretch of one link per newton of tension (measured l / EA)"),
        Parameter("mass_slope", 0.0, -0.9, 0.9, "linear", frozen=True, unit="",
                  doc="interior mass profile, node mass x (1 + slope (1 - 2u)), u = 0 at the hand, 1 at the "
                      "lead; frozen: it did not lower the built-in fit's loss (README, \"Rope fit\")"),
        Parameter("radius", radius, 0.25 * radius, 4.0 * radius, "log", unit="m",
                  doc="collision radius of the straight coarse links"),
    ])


def parameter_names(args) -> list[str]:
    """The names --free and --freeze may give (the same for every rope and resolution)."""
    return parameter_space(SEGMENTS_DEFAULT, 1.0, 1.0, 0.01, None).names


@dataclass
class RopeCase:
    """One condition prepared for the coarse chain at a given resolution."""

    name: str
    ref: object  # RopeReference
    event: object  # CollisionEvent
    hand: np.ndarray  # (steps + 1, 3) at t0 + k dt
    pos0: np.ndarray  # (N, 3)
    vel0: np.ndarray
    steps: int
    target: Target  # the reference's critical state
    critical: object = None  # events.Critical: where the event came from, its confidence and warnings


def hand_at(ref, tk: np.ndarray) -> np.ndarray:
    """The hand's path at the chain's step times. Between frames coarser than 200 Hz (HAND_SPLINE_ABOVE) a cubic
    spline (continuous acceleration): linear interpolation there gives the held end a velocity that jumps at every
    frame. On the 50 cached throws of the nine ropes cut to 62.5 and 50 Hz the spline put the chain's error nearer the
    250 Hz value in 44 (median 0.0015 against 0.009; linear made one chain miss its contact). At 200 Hz and finer both
    agree within 0.003 and the linear one is kept (the 250 Hz built-in references are read as before)."""
    if ref.dt > HAND_SPLINE_ABOVE:
        from scipy.interpolate import CubicSpline

        return CubicSpline(ref.time, ref.hand, axis=0)(tk)
    return np.stack([np.interp(tk, ref.time, ref.hand[:, a]) for a in range(3)], 1)


def prepare_case(name: str, ref, n_nodes: int, dt: float, weights: dict | None = None) -> RopeCase:
    crit = reference_critical(ref)
    ev = crit.event
    if ev is None or ev.index == 0:
        raise InputError(name, crit.field, crit.problem or "the reference never hits itself after its first frame "
                                                           "(no critical point to fit)")
    t = ref.time
    steps = int(math.floor((t[-1] - t[0]) / dt + 1e-9))
    if steps < 2:
        raise InputError(name, "time", f"reference lasts {t[-1] - t[0]:g} s, shorter than two steps of {dt:g} s")
    tk = t[0] + dt * np.arange(steps + 1)
    hand = hand_at(ref, tk)
    s_nodes = np.linspace(0.0, 1.0, n_nodes)
    pos0 = resample(ref.markers[0], ref.marker_arclength, s_nodes)
    pos0[0] = hand[0]
    vel0 = resample(start_velocity(ref)[0], ref.marker_arclength, s_nodes)
    # a rope at rest starts the chain at rest (events.starts_at_rest), also one whose first step is within its markers'
    # noise: 0.5 mm of it read 0.23-0.48 m/s on a rope at rest, and the chain's error at measured values ran 0.33-5.05
    # over noise draws against 0.41 clean (3 of 8 missed their contact; a probe of stop 46)
    if starts_at_rest(ref):
        vel0[:] = 0.0
    return RopeCase(name, ref, ev, hand, pos0.astype(np.float32), vel0.astype(np.float32), steps,
                    Target.from_reference(ref, ev, weights, source=name), crit)


# ------------------------------------------------------------------------------- problem
class RopeProblem(Problem):
    task = "rope"

    def __init__(self, train_refs: Sequence, held_refs: Sequence = (), segments: int = 10, dt: float = 0.005,
                 device: str = "cpu", names: Sequence[str] | None = None, held_names: Sequence[str] | None = None,
                 iterations: int = ITERATIONS, weights: dict | None = None, screening: Sequence[dict] = ()):
        if not 3 <= segments <= 63:
            raise InputError("--segments", "segments", f"{segments} is outside [3, 63] (links; masses = segments + 1)")
        if not 1 <= iterations <= 64:
            raise InputError("--iterations", "iterations", f"{iterations} is outside [1, 64]")
        if not DT[0] <= dt <= DT[1]:
            raise InputError("--dt", "dt", f"{dt:g} s is outside [{DT[0]:g}, {DT[1]:g}] s")
        if not train_refs:
            raise InputError("--reference", "reference", "at least one reference is needed")
        self.segments, self.n, self.dt = int(segments), int(segments) + 1, float(dt)
        self.device = device
        self.weights = dict(WEIGHTS if weights is None else weights)
        self._targets: dict = {}  # the observable kernel's targets per list of conditions (see _stacked_targets)
        names = list(names or [f"ref{i}" for i in range(len(train_refs))])
        held_names = list(held_names or [f"held{i}" for i in range(len(held_refs))])
        self.train = [Condition(nm, prepare_case(nm, r, self.n, self.dt, self.weights))
                      for nm, r in zip(names, train_refs)]
        self.held_out = [Condition(nm, prepare_case(nm, r, self.n, self.dt, self.weights))
                         for nm, r in zip(held_names, held_refs)]
        ref = train_refs[0]
        # the measured values come from the first reference: every other must be of the same rope, or the fit would
        # change with the order of the files (a stiffer rope's file first: measured EI 0.09 instead of 0.027, the
        # fitted radius 5.6x)
        first = getattr(ref, "file", "") or names[0]
        roles = [("--reference", nm, r) for nm, r in zip(names[1:], train_refs[1:])]
        roles += [("--validate", nm, r) for nm, r in zip(held_names, held_refs)]
        for role, nm, other in roles:
            for field in ("length", "mass", "radius", "bend_stiffness"):
                a, b = getattr(ref, field), getattr(other, field)
                if a is not None and b is not None and abs(b - a) > 1e-6 * abs(a):  # a file may leave EI out
                    raise InputError(getattr(other, "file", "") or nm, field,
                                     f"{b} here, {a} in {first} (the first --reference): all references ({role} "
                                     "among them) must be of the same rope")
        self.length, self.mass, self.radius = float(ref.length), float(ref.mass), float(ref.radius)
        self.link = self.length / self.segments
        # Folds shorter than a loop around the rope's own thickness (or one link) are bending,
        # not contact -- the same exclusion the reference detector applies to its markers.
        self.min_sep = 2 + int(math.floor(max(2.0 * math.pi * self.radius / self.link, 1.0) + 1e-9))
        self.margin = 0.5 * self.link
        self.sim = RopeSim(self.n, self.link, self.dt, device, iterations=iterations, margin=self.margin,
                           min_sep=self.min_sep)
        self.space = parameter_space(self.segments, self.length, self.mass, self.radius, ref.bend_stiffness)
        self.tolerance = 0.15
        self.resolution = {"segments": self.segments, "masses": self.n, "dt": self.dt, "iterations": int(iterations)}
        self.error_doc = ("weighted sum of shape (/length), velocity (/reference speed), time (/critical time) and "
                          "contact-place errors of the rope at its first self-collision, per hand path")
        self.screening = [dict(r) for r in screening]  # every reference file offered, used or left out


    # ------------------------------------------------------------------ simulation
    def chain_params(self, values: np.ndarray) -> ChainParams:
        v = np.atleast_2d(np.asarray(values, np.float64))
        sp = self.space
        M = v[:, sp.index("mass")]
        f = v[:, sp.index("lead_fraction")]
        # the held node's half link rides with the hand: the free chain carries M (1 - 1 / (2 S)), interior nodes
        # M / S at the measured lead fraction (all of M over them had made them (2S - 1) / (2S - 2) too heavy,
        # 5.6 % at 10 links, a resolution trend of its own in the flow; review of stop 55)
        return ChainParams(node_mass=(1.0 - f - 0.5 / self.segments) * M / (self.n - 2), lead_mass=f * M,
                           bend_k=v[:, sp.index("bend_stiffness")], bend_b=v[:, sp.index("bend_damping")],
                           drag_lin=v[:, sp.index("drag_lin")], drag_quad=v[:, sp.index("drag_quad")],
                           radius=v[:, sp.index("radius")],
                           mass_slope=v[:, sp.index("mass_slope")] if "mass_slope" in sp.names else 0.0,
                           stretch=v[:, sp.index("stretch")] if "stretch" in sp.names else 0.0)

    def simulate(self, values: np.ndarray, conditions: Sequence[Condition], trajectory_every: int | None = None,
                 host: bool = True):
        """Every candidate under every condition in one batch; chain b*C + c is (candidate b, condition c).
        host=False: the results stay on the device (for the observable kernels; `late` is their horizon rule)."""
        values = np.atleast_2d(np.asarray(values, np.float64))
        B, C = values.shape[0], len(conditions)
        cases = [c.data for c in conditions]
        steps = max(cs.steps for cs in cases)
        # every condition's hand samples to the longest horizon, the shorter ones held at their last sample
        hand = np.stack([np.concatenate([cs.hand[:steps + 1],
                                         np.repeat(cs.hand[-1:], steps + 1 - min(len(cs.hand), steps + 1), 0)])
                         for cs in cases])
        p = self.chain_params(values)
        rep = ChainParams(**{f: np.repeat(getattr(p, f), C) for f in ChainParams.FIELDS})
        pidx = np.tile(np.arange(C, dtype=np.int32), B)
        pos0 = np.stack([cs.pos0 for cs in cases])[pidx]
        vel0 = np.stack([cs.vel0 for cs in cases])[pidx]
        # times from the start of each reference's motion: references may start their clocks anywhere
        res = self.sim.rollout(pos0, vel0, hand, pidx, rep, steps, t0=0.0,
                               stop_at_hit=trajectory_every is None, trajectory_every=trajectory_every, host=host)
        if not host:
            return res
        # a hit after a shorter condition's horizon does not count
        horizon = np.array([cs.steps for cs in cases])[pidx]
        late = (res.status == 1) & (res.hit_frame > horizon)
        res.status = np.where(late, 0, res.status)
        return res

    def _critical(self, values: np.ndarray, conditions: Sequence[Condition]):
        """Rollout of every candidate under every condition, and the chains' critical states (B * C rows,
        row b * C + c is candidate b under condition c)."""
        res = self.simulate(values, conditions)
        return res, from_rollout(res, self.n, 0.0)

    def _scores(self, values: np.ndarray, conditions: Sequence[Condition], residual: bool = False):
        """The observable on the chains' device (kernels/rope/critical.py): rollouts, critical states and their
        errors stay there; the host gets per chain the terms (and residuals), status, hit time and contact."""
        values = np.atleast_2d(values)
        B, C = values.shape[0], len(conditions)
        res = self.simulate(values, conditions, host=False)
        cond = np.tile(np.arange(C, dtype=np.int32), B)
        states = critical.chain_states(res.events, cond, [c.data.steps for c in conditions], res.dt, res.t0,
                                       SAMPLES)
        terms, r = critical.critical_terms(states, cond, self._stacked_targets(conditions), MISS, residual)
        return terms, r, states

    def _stacked_targets(self, conditions: Sequence[Condition]):
        """The conditions' targets stacked for the observable kernel, cached. An entry holds the targets it was
        built from, so their ids (the key) cannot be reused by other objects while it lives; the cache keeps the
        latest few lists only (a correction's refits make new conditions every trial)."""
        targets = [c.data.target for c in conditions]
        key = tuple(id(t) for t in targets)
        if key not in self._targets:
            if len(self._targets) >= 8:
                self._targets.pop(next(iter(self._targets)))
            self._targets[key] = (targets, stack_targets(targets, self.device))
        return self._targets[key][1]

    def residuals(self, values: np.ndarray, conditions: Sequence[Condition]) -> np.ndarray:
        """(B, C R) signed, weighted residuals of the critical state per condition (observable.Target), for the
        Gauss-Newton uncertainty; NaN where a chain never hits."""
        B = np.atleast_2d(values).shape[0]
        return self._scores(values, conditions, residual=True)[1].reshape(B, -1)

    def error_terms(self, values: np.ndarray, conditions: Sequence[Condition]) -> dict:
        """The observable's error terms per (candidate, condition), (B, C) each; blow-ups cost inf."""
        B, C = np.atleast_2d(values).shape[0], len(conditions)
        scores, _, states = self._scores(values, conditions)
        terms = {k: scores[:, i].reshape(B, C) for i, k in enumerate(critical.TERMS)}
        status = states.status.numpy().reshape(B, C)
        terms["total"] = finite_or_inf(np.where(status == 2, np.inf, terms["total"]))
        terms["status"] = status
        # on each reference's own clock, as its event time
        terms["hit_time"] = states.time.numpy().reshape(B, C) + np.array([float(c.data.ref.time[0])
                                                                          for c in conditions])
        contact = states.s.numpy()
        terms["s_a"], terms["s_b"] = contact[:, 0].reshape(B, C), contact[:, 1].reshape(B, C)
        return terms

    def errors(self, values: np.ndarray, conditions: Sequence[Condition]) -> np.ndarray:
        try:
            return self.error_terms(values, conditions)["total"]
        except (FloatingPointError, ValueError):  # a batch that cannot be simulated costs, never raises
            return np.full((np.atleast_2d(values).shape[0], len(conditions)), np.inf)

    # ------------------------------------------------------------------ reporting
    def report(self, fitted: np.ndarray, measured: np.ndarray) -> dict:
        out = {"weights": self.weights, "no_hit_penalty": f"{NO_HIT:g} + min(closest approach, 0.1 length) / "
                                                          "(0.1 length)", "samples": SAMPLES,
               "min_segment_separation": self.min_sep, "critical_points": {}}
        for group in (self.train, self.held_out):
            if not group:
                continue
            terms = self.error_terms(np.stack([measured, fitted]), group)
            for j, c in enumerate(group):
                ev = c.data.event
                row = {"reference": {"time": ev.time, "s_a": ev.s_a, "s_b": ev.s_b, "frame": ev.index,
                                     "source": ev.source, "confidence": ev.confidence, "reasons": list(ev.reasons)},
                       "held_out": group is self.held_out}
                for i, who in enumerate(("measured", "fitted")):
                    hit = terms["status"][i, j] == 1
                    row[who] = {k: (float(terms[k][i, j]) if hit else None) for k in ("hit_time", "s_a", "s_b")}
                    row[who].update({k: float(terms[k][i, j]) for k in ("shape", "velocity", "time", "place", "total")
                                     if hit or k == "total"})
                    row[who]["status"] = ["no_hit", "hit", "blew_up"][int(terms["status"][i, j])]
                out["critical_points"][c.name] = row
        if self.held_out:
            out["held_out_comparison"] = self.held_out_comparison(fitted, measured)
        out["references"], out["warnings"] = self.reference_report()
        return out

    def fit_warnings(self, fitted: np.ndarray) -> list[str]:
        status = self.error_terms(np.atleast_2d(fitted), self.train)["status"][0]
        chain, n = f"the {self.segments}-link chain (dt {self.dt:g} s) with the fitted values", len(self.train)
        out = []
        for code, what in ((0, "does not hit itself on"), (2, "blows up on")):
            names = [c.name for c, st in zip(self.train, status) if st == code]
            if names:
                out.append(f"{chain} {what} {len(names)} of {n} fit references ({', '.join(names)}): those cost the "
                           "no-hit penalty and say nothing of the parameters"
                           + (" (none hits: the fitted values are not determined by these references)"
                              if len(names) == n else ""))
        return out

    @property
    def warnings(self) -> list[str]:
        """What a fit on these references says of them (files left out, events flagged or annotated otherwise than
        detected): result.json's `warnings`, and a flow's."""
        return self.reference_report()[1]

    def reference_report(self) -> tuple[dict, list]:
        """Which reference files were used and which left out (and why), and the warnings to print: left-out
        files, and events used although uncertain (flagged) or annotated differently from the detection."""
        rows = list(self.screening)
        used = {c.name: c for c in self.train + self.held_out}
        for c in self.train + self.held_out:
            if not any(r.get("name") == c.name for r in rows):
                rows.append({"name": c.name, "file": getattr(c.data.ref, "file", "") or c.name,
                             "role": "validate" if c in self.held_out else "fit", "used": True})
        warnings = []
        for r in rows:
            c = used.get(r.get("name")) if r.get("used") else None
            if c is not None:
                ev, crit = c.data.event, c.data.critical
                r["event"] = {"time": ev.time, "s_a": ev.s_a, "s_b": ev.s_b, "source": ev.source,
                              "confidence": ev.confidence}
                r["flagged"] = ev.flagged
                r["warnings"] = [] if crit is None else list(crit.warnings)
                if ev.flagged:
                    warnings.append(f"{r['file']}: markers: uncertain event at t={ev.time:.4f} s used (flagged): "
                                    + "; ".join(ev.reasons))
                if crit is not None:
                    warnings += [f"{r['file']}: {'critical_time' if 'annotat' in w else 'markers'}: {w}"
                                 for w in crit.warnings if not w.startswith("uncertain event: ")]
                rest = _rest_before_motion(c.data.ref)
                if rest > MAX_REST_BEFORE_MOTION:
                    r["rest_before_motion_s"] = rest
                    warnings.append(f"{r['file']}: hand: rests {rest:.2f} s before it moves: the time error is "
                                    f"relative to the contact's time from the recording's start "
                                    f"({ev.time - float(c.data.ref.time[0]):.2f} s here), so a lead-in weighs it "
                                    "down; trim the recording to start as the hand moves")
            elif not r.get("used"):
                warnings.append(f"{r['file']}: {r['field']}: {r['problem']} (left out of the {r['role']} set)")
        summary = {"files": rows, "used": sum(bool(r.get("used")) for r in rows),
                   "left_out": sum(not r.get("used") for r in rows),
                   "flagged": sum(bool(r.get("flagged")) for r in rows),
                   "annotated": sum(r.get("event", {}).get("source") == "annotated" for r in rows)}
        return summary, warnings

    def validation_errors(self, values: np.ndarray, conditions: Sequence[Condition]):
        """Held-out errors that measure states, not penalties: a chain that hits itself is scored by its critical
        state (shape, velocity, time, place), a chain that never hits by its state at the reference's critical
        time plus the least time error a later hit could have (`no_hit_bound`), so a fitted / measured ratio
        compares like with like; per condition whether each chain hit, and when."""
        values = np.atleast_2d(values)
        terms = self.error_terms(values, conditions)
        errs = self.no_hit_bound(values, conditions, terms)
        names = ["measured", "fitted"] if len(values) == 2 else [f"candidate{i}" for i in range(len(values))]
        details = []
        for j, c in enumerate(conditions):
            row = {"reference_time": float(c.data.event.time)}
            for i, who in enumerate(names):
                hit = bool(terms["status"][i, j] == 1)
                row[f"{who}_hit"] = hit
                row[f"{who}_hit_time"] = float(terms["hit_time"][i, j]) if hit else None
            row["scored"] = ("critical-state error of a chain that hits; a chain that never hits: its shape and "
                             "velocity error at the reference's critical time plus the time error of a hit at the end "
                             "of the horizon, a lower bound that shrinks when the recording is cut short after the "
                             "contact, so such a condition is never within tolerance")
            if len(values) == 2:  # the engine's measured / fitted pair: a chain that misses shows no event
                row["measured_misses"], row["fitted_misses"] = not row["measured_hit"], not row["fitted_hit"]
            details.append(row)
        return errs, details

    def no_hit_bound(self, values: np.ndarray, conditions: Sequence[Condition],
                     terms: dict | None = None) -> np.ndarray:
        """(B, C) error with the no-hit penalty replaced by a penalty-free score: shape and velocity
        of the chain at the reference's critical time, the time error of a hit at the end of the
        horizon (the least a later hit could have), place error 0. Equals the error of chains that hit.
        terms: error_terms(values, conditions) where the caller has them already."""
        values = np.atleast_2d(values)
        terms = self.error_terms(values, conditions) if terms is None else terms
        out = terms["total"].copy()
        miss = terms["status"] == 0
        if not miss.any():
            return out
        res = self.simulate(values, conditions, trajectory_every=1)
        C = len(conditions)
        for i, j in zip(*np.nonzero(miss)):
            cs = conditions[j].data
            pos, vel = self._state_at(res, i * C + j, float(cs.target.state.time[0]))
            out[i, j] = cs.target.state_error(pos, vel, cs.steps * self.dt)
        return out

    def state_at_critical_time(self, values: np.ndarray, conditions: Sequence[Condition]) -> np.ndarray:
        """(B, C) error of every chain's state at the reference's critical time, hit or not: shape and velocity
        at the K points (Target.state_error with no time error). No event enters, so no penalty either: the
        same quantity for a chain that hit itself early, late or never."""
        values = np.atleast_2d(values)
        res = self.simulate(values, conditions, trajectory_every=1)
        B, C = values.shape[0], len(conditions)
        out = np.full((B, C), np.inf)
        for j, c in enumerate(conditions):
            cs = c.data
            t_ref = float(cs.target.state.time[0])
            for i in range(B):
                b = i * C + j
                if res.status[b] == 2:  # blew up
                    continue
                pos, vel = self._state_at(res, b, t_ref)
                if np.all(np.isfinite(pos)) and np.all(np.isfinite(vel)):
                    out[i, j] = cs.target.state_error(pos, vel, t_ref)
        return out

    def _state_at(self, res, b: int, t: float) -> tuple[np.ndarray, np.ndarray]:
        """Chain b's positions and velocities at time t (from the motion's start) at the K points: positions
        interpolated inside the step, velocity that step's difference (the rule of the event kernel); a horizon
        shorter than t gives the last state, never an extrapolation."""
        x = t / self.dt
        k = min(int(np.floor(x)), res.trajectory.shape[0] - 2)
        u = min(x - k, 1.0)
        pos = (1 - u) * res.trajectory[k, b] + u * res.trajectory[k + 1, b]
        vel = (res.trajectory[k + 1, b] - res.trajectory[k, b]) / self.dt
        s_nodes, s_k = np.linspace(0.0, 1.0, self.n), np.linspace(0.0, 1.0, SAMPLES)
        return resample(pos, s_nodes, s_k), resample(vel, s_nodes, s_k)

    def held_out_comparison(self, fitted: np.ndarray, measured: np.ndarray) -> dict:
        """Held-out error ratio fitted / measured: scored as the validation does (no-hit chains by their state at
        the reference's critical time), with the no-hit penalty, and by every chain's state at that time."""
        vals = np.stack([measured, fitted])
        pen = self.errors(vals, self.held_out)
        low = self.no_hit_bound(vals, self.held_out)
        state = self.state_at_critical_time(vals, self.held_out)
        ratio = lambda e: float(np.mean(e[1]) / np.mean(e[0])) if np.mean(e[0]) > 0 else None  # noqa: E731
        return {
            "no_hit_scored_at_reference_time": {"measured": low[0].tolist(), "fitted": low[1].tolist(),
                                                "ratio_of_means": ratio(low)},
            "with_no_hit_penalty": {"measured": pen[0].tolist(), "fitted": pen[1].tolist(),
                                    "ratio_of_means": ratio(pen)},
            "state_at_reference_time": {"measured": state[0].tolist(), "fitted": state[1].tolist(),
                                        "ratio_of_means": ratio(state)},
            "meaning": "ratio of mean held-out errors, fitted / measured parameters. no_hit_scored_at_reference_time "
                       "(the validation verdict's score): the critical-state error, a chain that never hits scored "
                       "by its shape and velocity error at the reference's critical time plus the time error of a hit "
                       "at the end of the horizon (a lower bound), place error 0. with_no_hit_penalty: the training "
                       "error (a chain that never hits pays the penalty). state_at_reference_time: every chain's "
                       "shape and velocity error at the reference's critical time, hit or not (no event alignment)",
        }

    def charts(self, fitted, measured):
        from wrenorm.tasks.rope.report import condition_charts

        return condition_charts(self, fitted, measured)

    def record(self, recorder, fitted: np.ndarray, measured: np.ndarray) -> None:
        """Per hand path, one 3-D view: the reference rope (grey line and its markers), the
        measured-parameter chain (orange) and the fitted chain (blue) as line strips on
        "sim_time" at 50 frames/s, the hand path, and each rope's state at its critical point
        (larger points, logged at the collision time) with the contact point marked."""
        conds = self.train + self.held_out
        every = max(1, int(round(0.02 / self.dt)))
        res = self.simulate(np.stack([measured, fitted]), conds, trajectory_every=every)
        C = len(conds)
        s_nodes = np.linspace(0.0, 1.0, self.n)
        for j, c in enumerate(conds):
            split = "held_out" if j >= len(self.train) else "train"
            name = f"{split}/{c.name}"
            ref, ev = c.data.ref, c.data.event
            recorder.log_lines3d(f"reference/{name}/hand_path", 0.0, [ref.hand], colors=(150, 150, 150))
            stride = max(1, int(round(0.02 / ref.dt)))
            for f in range(0, len(ref.time), stride):
                t = float(ref.time[f])
                recorder.log_lines3d(f"reference/{name}/rope", t, [ref.markers[f]])
                recorder.log_points3d(f"reference/{name}/markers", t, ref.markers[f], radii=0.004)
                recorder.log_points3d(f"reference/{name}/hand", t, ref.hand[f][None], radii=0.015)
            recorder.log_points3d(f"reference/{name}/critical", float(ev.time), c.data.target.state.pos[0], radii=0.008)
            contact = resample(ref.markers[ev.index], ref.marker_arclength, np.array([ev.s_a, ev.s_b]))
            recorder.log_points3d(f"reference/{name}/contact", float(ev.time), contact, radii=0.025,
                                  colors=(255, 255, 255), labels=[f"reference contact {float(ev.time):.3f} s", ""])
            for i, who in enumerate(("measured", "fitted")):
                b = i * C + j
                t_ref0 = float(ref.time[0])
                for f, t in enumerate(res.trajectory_times + t_ref0):
                    recorder.log_lines3d(f"{who}/{name}/rope", float(t), [res.trajectory[f, b]])
                if res.status[b] == 1:
                    t_hit = float(res.hit_time[b]) + t_ref0
                    recorder.log_points3d(f"{who}/{name}/critical", t_hit, res.crit_pos[b], radii=0.01)
                    pts = resample(res.crit_pos[b], s_nodes, np.array([res.s_a[b], res.s_b[b]]))
                    recorder.log_points3d(f"{who}/{name}/contact", t_hit, pts, radii=0.025,
                                          labels=[f"{who} contact {t_hit:.3f} s", ""])
                    recorder.log_scalar(f"{who}/{name}/critical_time", t_hit, t_hit)
                else:  # said on the rope itself: a chain that never touches has no critical state to compare
                    t_end = float(res.trajectory_times[-1]) + t_ref0
                    recorder.log_points3d(f"{who}/{name}/critical", t_end, res.trajectory[-1, b][-1:], radii=0.01,
                                          labels=[f"{who}: no self-collision"])
            recorder.add_view(f"{split}: {c.name}",
                              [f"/{who}/{name}/**" for who in ("reference", "measured", "fitted")], "spatial3d",
                              around=np.concatenate([ref.markers.reshape(-1, 3), ref.hand]))
        recorder.add_view("summary", ["/summary"], "text")
        recorder.show_timeline("sim_time")


# ------------------------------------------------------------------------------- building
def build_problems(args, device: str) -> list[Problem]:
    from wrenorm.tasks.rope.reference.generate import builtin_references
    from wrenorm.tasks.rope.reference.paths import FIT_PATHS, HELD_OUT_PATHS

    screening: list[dict] = []
    if args.reference:
        said: list[str] = []
        train, names = screen_references(args.reference, "fit", screening, warn=said.append)
        if not train and len(args.reference) == 1:  # one file, one line: its own problem is the error
            raise InputError(screening[0]["file"], screening[0]["field"], screening[0]["problem"])
        for message in said:
            warn(message)
        if not train:
            raise InputError("--reference", "reference",
                             f"no usable fit reference remains: all {len(args.reference)} left out (warnings above)")
    else:
        train, names = builtin_references("fit"), list(FIT_PATHS)
    if args.validate:
        held, held_names = screen_references(args.validate, "validate", screening)
    elif args.reference:
        held, held_names = [], []
    else:
        held, held_names = builtin_references("held_out"), list(HELD_OUT_PATHS)
    refuse_repeated_recordings([(r, "--reference") for r in train] + [(r, "--validate") for r in held])
    return [RopeProblem(train, held, segments=args.segments, dt=args.dt, device=device, names=names,
                        held_names=held_names, iterations=args.iterations, screening=screening)]


def refuse_repeated_recordings(refs_and_roles) -> None:
    """One recording given twice (the same file, a copy under another name, or a copy moved in the horizontal) as a
    fit and a validation reference is a validation on the training data ("absorbed" means nothing then); twice among
    the fit references it counts double. Compared by marker content after the loader moves the horizontal origin to
    the hand (generate.same_recording), not by name."""
    from wrenorm.tasks.rope.reference.generate import same_recording

    seen: list = []
    for ref, role in refs_and_roles:
        for first, first_role in seen:
            if same_recording(first, ref):
                where = f"twice among {role}" if role == first_role else f"as {first_role} and as {role}"
                raise InputError(ref.file, "markers", f"the same recording as {first.file} (marker data equal within "
                                                      f"1 um), given {where}: give each recording once")
        seen.append((ref, role))


def screen_references(paths, role: str, rows: list, warn=None) -> tuple[list, list]:
    """Load each reference and find its critical moment; a file that cannot be read, or has no usable event,
    is left out with a one-line warning naming file, field and problem (and a row in `rows`); an uncertain
    (flagged) event is used, and said so. Returns (references, names) of the usable ones."""
    from wrenorm.errors import warn as say_on_stderr
    from wrenorm.tasks.rope.reference.generate import load_reference

    def say(msg):
        (warn or say_on_stderr)(msg)

    refs, names = [], []
    taken = set()
    for p in paths:
        name = _stem(p)
        if name in taken:  # two files with one stem: keep conditions apart
            name = str(p)
        row = {"name": name, "file": str(p), "role": role}
        try:
            ref = load_reference(p)
        except InputError as e:
            row.update(used=False, field=e.field, problem=e.problem)
            rows.append(row)
            say(f"{e.source}: {e.field}: {e.problem} (left out of the {role} set)")
            continue
        crit = reference_critical(ref)
        if crit.event is None or crit.event.index == 0:
            row.update(used=False, field=crit.field, problem=crit.problem or "no critical moment")
            rows.append(row)
            say(f"{p}: {row['field']}: {row['problem']} (left out of the {role} set)")
            continue
        ev = crit.event
        row.update(used=True, critical_time=ev.time, source=ev.source, confidence=ev.confidence)
        if ev.flagged:
            say(f"{p}: markers: uncertain event at t={ev.time:.4f} s, used but flagged: " + "; ".join(ev.reasons))
        for w in crit.warnings:
            if "bridged in time" in w:
                say(f"{p}: markers: {w}")
        rows.append(row)
        refs.append(ref)
        names.append(name)
        taken.add(name)
    return refs, names


def _stem(path) -> str:
    from pathlib import Path
    return Path(path).stem


MAX_REST_BEFORE_MOTION = 0.1  # s; the built-in throws' hands leave 1 mm of their start within 12-35 ms


def _rest_before_motion(ref) -> float:
    """How long the hand stays within 1 mm of where it starts (s): the observable's time error is divided by the
    contact's time from the recording's start, so a rest before the throw scales the time term down."""
    hand = np.asarray(ref.hand, dtype=np.float64)
    moved = np.linalg.norm(hand - hand[0], axis=1) > 1e-3
    return float(ref.time[np.argmax(moved)] - ref.time[0]) if moved.any() else float(ref.time[-1] - ref.time[0])


# ------------------------------------------------------------------------------- flow
def flow_problems(args, device: str) -> list[RopeProblem]:
    """One RopeProblem per resolution on the built-in references: segment counts (--axis segments,
    the default; step --dt) or steps in seconds (--axis dt; --segments links), coarse to fine in
    segments, fine to coarse in dt."""
    from wrenorm.tasks.rope.reference.generate import builtin_references
    from wrenorm.tasks.rope.reference.paths import FIT_PATHS, HELD_OUT_PATHS

    by_dt = getattr(args, "axis", "segments") == "dt"
    segments = getattr(args, "segments", None) or SEGMENTS_DEFAULT
    dt = getattr(args, "dt", None) or DT_DEFAULT
    points = []
    for r in args.resolutions or (FLOW_DT if by_dt else FLOW_SEGMENTS):
        if by_dt and not DT[0] <= r <= DT[1]:
            raise InputError("--resolutions", "dt", f"rope time steps must be in [{DT[0]:g}, {DT[1]:g}] s, got {r:g}")
        if not by_dt and not (float(r).is_integer() and 3 <= r <= 63):
            raise InputError("--resolutions", "resolutions",
                             f"rope resolutions are segment counts in [3, 63], got {r:g}")
        points.append(float(r) if by_dt else int(r))
    if len(set(points)) != len(points):
        raise InputError("--resolutions", "resolutions", f"repeated resolution in {sorted(points)}")
    train, held = builtin_references("fit"), builtin_references("held_out")

    def problem(segments, dt):
        return RopeProblem(train, held, segments=segments, dt=dt, device=device, names=list(FIT_PATHS),
                           held_names=list(HELD_OUT_PATHS), iterations=args.iterations)

    if by_dt:
        return [problem(segments, d) for d in sorted(points)]
    return [problem(s, dt) for s in sorted(points)]
