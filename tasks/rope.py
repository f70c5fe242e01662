"""Rope task: effective parameters of a coarse flying-knot chain, fitted to the rope state at
the first self-collision (the "critical point") of a reference rope.

Resolution: `--segments S` links (S + 1 point masses, node 0 on the fingertip; the flying
knot's 11 masses are S = 10) and the step `--dt`. Each condition is one hand path with one
reference trajectory (`--reference FILE ...`, default the built-in newton references).

Error of one condition (dimensionless, weights in WEIGHTS):
  shape    RMS distance between chain and reference at 21 common arc-length points, / rope length
  velocity RMS velocity difference at those points, / the reference's RMS speed there (>= 0.1 m/s)
  time     |t_chain - t_ref| / t_ref (time of the critical point from the start)
  place    mean |s - s_ref| of the two arc-length fractions of the contact
  The reference state at the critical point is interpolated between the frames bracketing the
  interpolated collision time, the same rule the kernel uses (positions linear, velocity of the
  bracketing interval). A chain that never hits itself within the reference horizon costs
  NO_HIT + clearance / margin (finite, and smaller the closer it came); a blow-up costs inf.

Parameter mapping from the reference rope (length L, mass M, radius r, EI) to a chain with link
l = L / S: lumped masses (interior M / S, lead half of that, held node's half goes to the hand),
so the measured lead fraction is 1 / (2 S); bending stiffness per joint k = EI / l; bending
damping per joint b = k * BEND_DAMPING_TIME; quadratic air drag per length 0.5 rho_air C_d 2r;
linear drag 0; collision radius r. Total mass is frozen: scaling mass, k, b and drag together
leaves the motion unchanged, so only the ratios are identifiable.
"""
from __future__ import annotations

import argparse
import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from wrenorm.errors import InputError
from wrenorm.kernels.rope import ChainParams, RopeSim
from wrenorm.params import Parameter, ParameterSpace
from wrenorm.problem import Condition, Problem, finite_or_inf

WEIGHTS = {"shape": 1.0, "velocity": 0.1, "time": 1.0, "place": 0.5}
# 0.1 on the normalised velocity mirrors the flying knot's 5.0 (m) : 0.00375 (m/s) on squared
# errors once shape is divided by ~1 m and velocity by a ~5 m/s speed.
NO_HIT = 5.0  # above any colliding candidate's error (each term is O(1) at worst)
SAMPLES = 21
BEND_DAMPING_TIME = 2e-3  # s: internal friction time of a braided rope (as the newton reference)
RHO_AIR, CD_CYLINDER = 1.2, 1.2
MIN_SPEED = 0.1  # m/s
START_AT_REST_BELOW = 0.05  # m/s


def default_error_weights():
    return dict(WEIGHTS)


# ---------------------------------------------------------------------------- resampling
def resample(points: np.ndarray, arclength: np.ndarray, samples: np.ndarray) -> np.ndarray:
    """Piecewise-linear resampling of (..., M, 3) along `arclength` (M,) at `samples` (K,)."""
    points = np.asarray(points, np.float64)
    idx = np.clip(np.searchsorted(arclength, samples, side="right") - 1, 0, len(arclength) - 2)
    u = (samples - arclength[idx]) / (arclength[idx + 1] - arclength[idx])
    return points[..., idx, :] * (1 - u)[:, None] + points[..., idx + 1, :] * u[:, None]


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
    ref_pos: np.ndarray  # (K, 3) at the critical point
    ref_vel: np.ndarray
    speed: float


def prepare_case(name: str, ref, n_nodes: int, dt: float) -> RopeCase:
    from wrenorm.tasks.rope_reference import first_self_collision

    ev = first_self_collision(ref)
    if ev is None or ev.index == 0:
        raise InputError(name, "markers", "the reference never hits itself after its first frame "
                                          "(no critical point to fit)")
    t = ref.time
    steps = int(math.floor((t[-1] - t[0]) / dt + 1e-9))
    if steps < 2:
        raise InputError(name, "time", f"reference lasts {t[-1] - t[0]:g} s, shorter than two steps of {dt:g} s")
    tk = t[0] + dt * np.arange(steps + 1)
    hand = np.stack([np.interp(tk, t, ref.hand[:, a]) for a in range(3)], 1)
    s_nodes = np.linspace(0.0, 1.0, n_nodes)
    pos0 = resample(ref.markers[0], ref.marker_arclength, s_nodes)
    pos0[0] = hand[0]
    vel0 = resample((ref.markers[1] - ref.markers[0]) / ref.dt, ref.marker_arclength, s_nodes)
    # A forward difference of a rope released at rest reads g dt, not 0; references that start
    # at rest (all built-in paths do) start the chain at rest.
    if np.abs(vel0).max() < START_AT_REST_BELOW:
        vel0[:] = 0.0
    k = ev.index
    frac = (ev.time - t[k - 1]) / (t[k] - t[k - 1])
    crit = ref.markers[k - 1] + frac * (ref.markers[k] - ref.markers[k - 1])
    vel = (ref.markers[k] - ref.markers[k - 1]) / (t[k] - t[k - 1])
    s_k = np.linspace(0.0, 1.0, SAMPLES)
    ref_pos = resample(crit, ref.marker_arclength, s_k)
    ref_vel = resample(vel, ref.marker_arclength, s_k)
    speed = max(float(np.sqrt(np.mean(np.sum(ref_vel ** 2, -1)))), MIN_SPEED)
    return RopeCase(name, ref, ev, hand, pos0.astype(np.float32), vel0.astype(np.float32), steps,
                    ref_pos, ref_vel, speed)


# ------------------------------------------------------------------------------- problem
class RopeProblem(Problem):
    task = "rope"

    def __init__(self, train_refs: Sequence, held_refs: Sequence = (), segments: int = 10, dt: float = 0.005,
                 device: str = "cpu", names: Sequence[str] | None = None, held_names: Sequence[str] | None = None,
                 iterations: int = 4, weights: dict | None = None):
        if not 3 <= segments <= 63:
            raise InputError("--segments", "segments", f"{segments} is outside [3, 63] (links; masses = segments + 1)")
        if not 1e-4 <= dt <= 0.05:
            raise InputError("--dt", "dt", f"{dt:g} s is outside [1e-4, 0.05] s")
        if not train_refs:
            raise InputError("--reference", "reference", "at least one reference is needed")
        self.segments, self.n, self.dt = int(segments), int(segments) + 1, float(dt)
        self.device = device
        self.weights = dict(WEIGHTS if weights is None else weights)
        names = list(names or [f"ref{i}" for i in range(len(train_refs))])
        held_names = list(held_names or [f"held{i}" for i in range(len(held_refs))])
        self.train = [Condition(nm, prepare_case(nm, r, self.n, self.dt)) for nm, r in zip(names, train_refs)]
        self.held_out = [Condition(nm, prepare_case(nm, r, self.n, self.dt)) for nm, r in zip(held_names, held_refs)]
        ref = train_refs[0]
        for other in list(train_refs[1:]) + list(held_refs):
            if abs(other.length - ref.length) > 1e-6 * ref.length or abs(other.mass - ref.mass) > 1e-6 * ref.mass:
                raise InputError("--reference", "length/mass", "all references must be of the same rope")
        self.length, self.mass, self.radius = float(ref.length), float(ref.mass), float(ref.radius)
        self.link = self.length / self.segments
        # Folds shorter than a loop around the rope's own thickness (or one link) are bending,
        # not contact -- the same exclusion the reference detector applies to its markers.
        self.min_sep = 2 + int(math.floor(max(2.0 * math.pi * self.radius / self.link, 1.0) + 1e-9))
        self.margin = 0.5 * self.link
        self.sim = RopeSim(self.n, self.link, self.dt, device, iterations=iterations, margin=self.margin,
                           min_sep=self.min_sep)
        self.space = self._space(ref)
        self.tolerance = 0.15
        self.resolution = {"segments": self.segments, "masses": self.n, "dt": self.dt}
        self.error_doc = ("weighted sum of shape (/length), velocity (/reference speed), time (/critical time) and "
                          "contact-place errors of the rope at its first self-collision, per hand path")

    def _space(self, ref) -> ParameterSpace:
        S, L, M = self.segments, self.length, self.mass
        ei = ref.bend_stiffness if ref.bend_stiffness is not None else 3e-3
        k = ei / self.link
        lead = 1.0 / (2 * S)
        drag = 0.5 * RHO_AIR * CD_CYLINDER * 2.0 * self.radius
        return ParameterSpace([
            Parameter("mass", M, 0.5 * M, 2.0 * M, "log", frozen=True, unit="kg",
                      doc="total rope mass (frozen: only ratios to it are identifiable)"),
            Parameter("lead_fraction", lead, 0.25 * lead, 0.5, "log", unit="",
                      doc="share of the mass in the free-end (lead) node; the rest is spread evenly"),
            Parameter("bend_stiffness", k, k / 30, k * 30, "log", unit="N m/rad",
                      doc="bending stiffness per joint, energy 0.5 k theta^2 (measured EI / link)"),
            Parameter("bend_damping", k * BEND_DAMPING_TIME, k * BEND_DAMPING_TIME * 1e-2,
                      k * BEND_DAMPING_TIME * 1e3, "log", unit="N m s/rad",
                      doc="bending damping per joint, dissipation 0.5 b theta_dot^2"),
            Parameter("drag_quad", drag, drag * 1e-3, drag * 30, "log", unit="N s^2/m^3",
                      doc="quadratic air drag per unit length (0.5 rho C_d diameter)"),
            Parameter("drag_lin", 0.0, 0.0, 2.0 * M / L, "linear", unit="N s/m^2",
                      doc="linear drag per unit length (absorbs the reference's numerical damping)"),
            Parameter("radius", self.radius, 0.25 * self.radius, 4.0 * self.radius, "log", unit="m",
                      doc="collision radius of the straight coarse links"),
        ])

    # ------------------------------------------------------------------ simulation
    def chain_params(self, values: np.ndarray) -> ChainParams:
        v = np.atleast_2d(np.asarray(values, np.float64))
        sp = self.space
        M = v[:, sp.index("mass")]
        f = v[:, sp.index("lead_fraction")]
        return ChainParams(node_mass=(1.0 - f) * M / (self.n - 2), lead_mass=f * M,
                           bend_k=v[:, sp.index("bend_stiffness")], bend_b=v[:, sp.index("bend_damping")],
                           drag_lin=v[:, sp.index("drag_lin")], drag_quad=v[:, sp.index("drag_quad")],
                           radius=v[:, sp.index("radius")])

    def simulate(self, values: np.ndarray, conditions: Sequence[Condition], trajectory_every: int | None = None):
        """Every candidate under every condition in one batch; chain b*C + c is (candidate b, condition c)."""
        values = np.atleast_2d(np.asarray(values, np.float64))
        B, C = values.shape[0], len(conditions)
        cases = [c.data for c in conditions]
        steps = max(cs.steps for cs in cases)
        hand = np.stack([np.concatenate([cs.hand[:steps + 1], np.repeat(cs.hand[-1:], steps + 1 - min(len(cs.hand), steps + 1), 0)])
                         for cs in cases])
        p = self.chain_params(values)
        rep = ChainParams(**{f: np.repeat(getattr(p, f), C) for f in ChainParams.FIELDS})
        pidx = np.tile(np.arange(C, dtype=np.int32), B)
        pos0 = np.stack([cs.pos0 for cs in cases])[pidx]
        vel0 = np.stack([cs.vel0 for cs in cases])[pidx]
        res = self.sim.rollout(pos0, vel0, hand, pidx, rep, steps, t0=float(cases[0].ref.time[0]),
                               stop_at_hit=trajectory_every is None, trajectory_every=trajectory_every)
        # a hit after a shorter condition's horizon does not count
        horizon = np.array([cs.steps for cs in cases])[pidx]
        late = (res.status == 1) & (res.hit_frame > horizon)
        res.status = np.where(late, 0, res.status)
        return res

    def error_terms(self, values: np.ndarray, conditions: Sequence[Condition]) -> dict:
        res = self.simulate(values, conditions)
        B, C = np.atleast_2d(values).shape[0], len(conditions)
        s_nodes = np.linspace(0.0, 1.0, self.n)
        s_k = np.linspace(0.0, 1.0, SAMPLES)
        cases = [c.data for c in conditions]
        ref_pos = np.stack([cs.ref_pos for cs in cases])  # (C, K, 3)
        ref_vel = np.stack([cs.ref_vel for cs in cases])
        pos = resample(res.crit_pos, s_nodes, s_k).reshape(B, C, SAMPLES, 3)
        vel = resample(res.crit_vel, s_nodes, s_k).reshape(B, C, SAMPLES, 3)
        rms = lambda d: np.sqrt(np.mean(np.sum(d ** 2, -1), -1))  # noqa: E731
        t_ref = np.array([cs.event.time - cs.ref.time[0] for cs in cases])
        terms = {
            "shape": rms(pos - ref_pos) / self.length,
            "velocity": rms(vel - ref_vel) / np.array([cs.speed for cs in cases]),
            "time": np.abs(res.hit_time.reshape(B, C) - np.array([cs.event.time for cs in cases])) / t_ref,
            "place": 0.5 * (np.abs(res.s_a.reshape(B, C) - np.array([cs.event.s_a for cs in cases]))
                            + np.abs(res.s_b.reshape(B, C) - np.array([cs.event.s_b for cs in cases]))),
        }
        status = res.status.reshape(B, C)
        total = sum(self.weights[k] * terms[k] for k in terms)
        no_hit = NO_HIT + res.clearance.reshape(B, C) / self.margin
        total = np.where(status == 1, total, np.where(status == 0, no_hit, np.inf))
        terms["total"] = finite_or_inf(total)
        terms["status"] = status
        terms["hit_time"] = res.hit_time.reshape(B, C)
        terms["s_a"], terms["s_b"] = res.s_a.reshape(B, C), res.s_b.reshape(B, C)
        return terms

    def errors(self, values: np.ndarray, conditions: Sequence[Condition]) -> np.ndarray:
        try:
            return self.error_terms(values, conditions)["total"]
        except (FloatingPointError, ValueError):  # a batch that cannot be simulated costs, never raises
            return np.full((np.atleast_2d(values).shape[0], len(conditions)), np.inf)

    # ------------------------------------------------------------------ reporting
    def report(self, fitted: np.ndarray, measured: np.ndarray) -> dict:
        out = {"weights": self.weights, "no_hit_penalty": NO_HIT, "samples": SAMPLES,
               "min_segment_separation": self.min_sep, "critical_points": {}}
        for group in (self.train, self.held_out):
            if not group:
                continue
            terms = self.error_terms(np.stack([measured, fitted]), group)
            for j, c in enumerate(group):
                ev = c.data.event
                row = {"reference": {"time": ev.time, "s_a": ev.s_a, "s_b": ev.s_b, "frame": ev.index},
                       "held_out": group is self.held_out}
                for i, who in enumerate(("measured", "fitted")):
                    hit = terms["status"][i, j] == 1
                    row[who] = {k: (float(terms[k][i, j]) if hit else None) for k in ("hit_time", "s_a", "s_b")}
                    row[who].update({k: float(terms[k][i, j]) for k in ("shape", "velocity", "time", "place", "total")
                                     if hit or k == "total"})
                    row[who]["status"] = ["no_hit", "hit", "blew_up"][int(terms["status"][i, j])]
                out["critical_points"][c.name] = row
        return out

    def record(self, recorder, fitted: np.ndarray, measured: np.ndarray) -> None:
        conds = self.train + self.held_out
        every = max(1, int(round(0.02 / self.dt)))  # 50 frames per simulated second
        res = self.simulate(np.stack([measured, fitted]), conds, trajectory_every=every)
        C = len(conds)
        for j, c in enumerate(conds):
            ref = c.data.ref
            stride = max(1, int(round(0.02 / ref.dt)))
            for f in range(0, len(ref.time), stride):
                recorder.log_lines3d(f"reference/{c.name}/rope", float(ref.time[f]), [ref.markers[f]])
            ev = c.data.event
            recorder.log_points3d(f"reference/{c.name}/critical", float(ev.time), c.data.ref_pos)
            for i, who in enumerate(("measured", "fitted")):
                b = i * C + j
                for f, t in enumerate(res.trajectory_times):
                    recorder.log_lines3d(f"{who}/{c.name}/rope", float(t), [res.trajectory[f, b]])
                if res.status[b] == 1:
                    recorder.log_points3d(f"{who}/{c.name}/critical", float(res.hit_time[b]), res.crit_pos[b])
                    recorder.log_scalar(f"{who}/{c.name}/critical_time", float(res.hit_time[b]), float(res.hit_time[b]))


# ------------------------------------------------------------------------------- CLI
def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--reference", nargs="+", metavar="FILE", default=None,
                        help="reference rope trajectories (.npz) to fit; default: the built-in fit paths")
    parser.add_argument("--validate", nargs="+", metavar="FILE", default=None,
                        help="held-out references (.npz); default: built-in held-out paths (without --reference)")
    parser.add_argument("--segments", type=int, default=10,
                        help="links of the coarse chain; it has segments + 1 point masses (10 = the flying knot's 11)")
    parser.add_argument("--dt", type=float, default=0.005, help="coarse step in seconds (flying knot: 0.005)")


def build_problem(args, device: str) -> Problem:
    from wrenorm.tasks.rope_reference import builtin_references, load_reference
    from wrenorm.tasks.rope_paths import FIT_PATHS, HELD_OUT_PATHS

    if args.reference:
        train = [load_reference(p) for p in args.reference]
        names = [_stem(p) for p in args.reference]
    else:
        train, names = builtin_references("fit"), list(FIT_PATHS)
    if args.validate:
        held = [load_reference(p) for p in args.validate]
        held_names = [_stem(p) for p in args.validate]
    elif args.reference:
        held, held_names = [], []
    else:
        held, held_names = builtin_references("held_out"), list(HELD_OUT_PATHS)
    return RopeProblem(train, held, segments=args.segments, dt=args.dt, device=device, names=names,
                       held_names=held_names)


def _stem(path) -> str:
    from pathlib import Path
    return Path(path).stem
