"""`python -m wrenorm sensitivity rope`: how many independent command changes (and parameter
changes) can move the rope's critical state above the noise, and what that implies for the
number of real trials (and identification experiments).

Sensitivities are central differences of the weighted critical-state residual e (tasks/
observable; |e| is the correction's objective), all perturbations in one batched rollout:
  command     F_u = de/du at u = 0 of the command space around --path (units of u)
  parameters  F_p = de/dx per condition, x = the free parameters' normalised [0, 1] coordinates
Noise, projected on each left singular vector U_i (n_i = sqrt(U_i^T C U_i)), is the sum of
  model roughness  e(u + d) - e(u) - F d over tiny random command offsets d (size --noise-size):
                   what the event map does that no linear map can (float32 rounding amplified by
                   the whip, contact-pair switches); it is the floor any FD sensitivity sees;
  measurement      marker noise --marker-noise (m, per coordinate; velocities are frame
                   differences, so sqrt(2) sigma / frame time), collision time --time-noise (s),
                   contact place sigma / length;
  real repeats     optional: --real-repeats newton runs at tiny command offsets (spread of e).
A direction "stands above the noise" when the change one step can make along it beats the noise:
sigma_i * step >= snr * n_i, with step = --command-step units of u (the correction's initial
trust radius) and --param-step of a normalised parameter range (0.1 = a tenth of its log range).
Implications: a correction that learned the local map from real trials alone needs r + 1 trials
(one base trial and one per resolvable direction); a model that supplies F can need fewer, only
as far as its F is right. For parameters: the fewest built-in throws whose stacked sensitivity
resolves as many parameter directions as all throws together.
"""
from __future__ import annotations

import argparse
import itertools
import sys
import time
from pathlib import Path

import numpy as np

from wrenorm.errors import InputError
from wrenorm.jacobian import jacobian
from wrenorm.options import add_number
from wrenorm.tasks.rope.control.command import DEFAULT_BOUND
from wrenorm.tasks.rope.options import DT, DT_DEFAULT, SEGMENTS

SYSTEM = "rope"
FRAME_TIME = 1.0 / 250.0  # s, the reference's (motion capture's) frame time


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--out", type=Path, default=None, help="output folder (default runs/sensitivity-rope-<time>)")
    add_number(p, "--seed", default=0, lo=0, integer=True)
    p.add_argument("--device", choices=["cpu", "cuda"], default="cpu")
    p.add_argument("--force", action="store_true")
    p.add_argument("--quiet", action="store_true")
    p.add_argument("--no-record", action="store_true")
    p.add_argument("--variant", default="default", help="rope material of the references (correct rope's --variant)")
    p.add_argument("--path", default="flick", help="built-in hand path around which the command is varied")
    p.add_argument("--params", default="measured", metavar="measured|fitted|FILE", help="coarse-model parameters")
    add_number(p, "--segments", default=20, lo=SEGMENTS[0], hi=SEGMENTS[1], integer=True,
               help="links of the coarse chain (correct rope steers with 10 by default)")
    add_number(p, "--dt", default=DT_DEFAULT, lo=DT[0], hi=DT[1], unit="s", help="coarse step")
    positive = {"lo": 0.0, "lo_open": True}
    box = 2 * DEFAULT_BOUND  # the command box's width (units of u): no step or offset is longer (1e300 had been
    # answered with a confident count and overflow warnings; review of stop 54)
    add_number(p, "--fd-step", default=0.1, **positive, hi=box, help="command FD step (units of u)")
    add_number(p, "--param-fd-step", default=0.01, **positive, hi=1.0,
               help="parameter FD step (normalised coordinates)")
    add_number(p, "--noise-samples", default=32, lo=2, hi=10000, integer=True)
    add_number(p, "--noise-size", default=1e-3, **positive, hi=0.1, help="tiny command offsets (units of u)")
    add_number(p, "--marker-noise", default=0.003, lo=0.0, hi=0.1, unit="m", help="marker position noise")
    add_number(p, "--time-noise", default=0.002, lo=0.0, hi=1.0, unit="s", help="collision time noise")
    add_number(p, "--real-repeats", default=0, lo=0, hi=1000, integer=True,
               help="newton runs at tiny offsets to measure repeat spread")
    add_number(p, "--command-step", default=1.0, **positive, hi=box)
    add_number(p, "--param-step", default=0.1, **positive, hi=1.0)
    add_number(p, "--snr", default=3.0, **positive, hi=1e3)
    add_number(p, "--fit-generations", default=30, lo=1, hi=1000, integer=True)


# ------------------------------------------------------------------------------ building blocks
def measurement_covariance(goal, marker_noise: float, time_noise: float, frame_time: float = FRAME_TIME):
    """Diagonal covariance of e from marker and timing noise (documented model, see module doc)."""
    from wrenorm.tasks.rope.observable import SAMPLES

    K, w = SAMPLES, goal.weights
    sig_v = np.sqrt(2.0) * marker_noise / frame_time
    var = np.concatenate([
        np.full(3 * K, (w["shape"] * marker_noise / (goal.length * np.sqrt(K))) ** 2),
        np.full(3 * K, (w["velocity"] * sig_v / (goal.speed * np.sqrt(K))) ** 2),
        [(w["time"] * time_noise / goal.state.time[0]) ** 2],
        np.full(2, (0.5 * w["place"] * marker_noise / goal.length) ** 2),
    ])
    return np.diag(var)


def resolvable(sv: np.ndarray, U: np.ndarray, cov: np.ndarray, step: float, snr: float):
    """Per singular direction: noise n_i = sqrt(U_i^T C U_i), and whether sigma_i step >= snr n_i."""
    noise = np.sqrt(np.maximum(np.einsum("mi,mk,ki->i", U, cov, U), 0.0))
    return noise, sv * step >= snr * noise


def fewest_experiments(blocks: list[np.ndarray], covs: list[np.ndarray], step: float, snr: float):
    """Smallest subset of conditions whose stacked sensitivity resolves as many directions as all."""
    def count(idx):
        J = np.concatenate([blocks[i] for i in idx])
        C = np.zeros((J.shape[0], J.shape[0]))
        o = 0
        for i in idx:
            m = blocks[i].shape[0]
            C[o:o + m, o:o + m] = covs[i]
            o += m
        Uf, sv, _ = np.linalg.svd(J, full_matrices=False)
        return int(resolvable(sv, Uf, C, step, snr)[1].sum())

    full = count(range(len(blocks)))
    if full == 0:
        return 0, []
    for k in range(1, len(blocks) + 1):
        for idx in itertools.combinations(range(len(blocks)), k):
            if count(idx) >= full:
                return full, list(idx)
    return full, list(range(len(blocks)))


# ------------------------------------------------------------------------------ analysis
def command_analysis(model, goal, fd_step: float, noise_samples: int, noise_size: float, seed: int,
                     marker_noise: float, time_noise: float, step: float, snr: float, extra_cov=None) -> dict:
    space = model.space
    u0 = np.zeros(space.dim)
    f = lambda U: goal.residual(model.states(U))  # noqa: E731
    t = time.perf_counter()
    jac = jacobian(f, u0, fd_step, space.lower, space.upper)
    F, e0, kinds = jac.J, jac.f0, jac.kinds
    fd_wall = time.perf_counter() - t
    if not np.all(np.isfinite(e0)):
        raise InputError("--path", "path", "the coarse chain never hits itself under this command; "
                                           "no critical state to differentiate (try --params fitted or another path)")
    d = np.random.default_rng(seed).normal(size=(noise_samples, space.dim)) * noise_size
    eb = f(np.concatenate([u0[None], d]))
    rough = eb[1:] - eb[0] - d @ F.T
    rough = rough[np.all(np.isfinite(rough), axis=1)]
    cov_model = np.cov(rough.T) if len(rough) > 1 else np.zeros((F.shape[0], F.shape[0]))
    cov_meas = measurement_covariance(goal, marker_noise, time_noise)
    cov = cov_model + cov_meas + (0 if extra_cov is None else extra_cov)
    Uf, sv, Vt = np.linalg.svd(F, full_matrices=False)
    noise, ok = resolvable(sv, Uf, cov, step, snr)
    n_model = np.sqrt(np.maximum(np.einsum("mi,mk,ki->i", Uf, cov_model, Uf), 0))
    n_meas = np.sqrt(np.einsum("mi,mk,ki->i", Uf, cov_meas, Uf))
    r = int(ok.sum())
    return {
        "F": F, "e0": e0, "singular_values": sv, "right_vectors": Vt, "left_vectors": Uf,
        "noise": noise, "noise_model": n_model, "noise_measurement": n_meas, "above_noise": ok,
        "count_above_noise": r, "dim": space.dim, "names": space.names, "fd_kinds": kinds,
        "fd_rollouts": 2 * space.dim + 1, "fd_wall_s": fd_wall, "roughness_samples": int(len(rough)),
        "min_trials_model_free": r + 1,
    }


def parameter_analysis(problem, values, goals, names, h: float, step: float, snr: float,
                       marker_noise: float, time_noise: float) -> dict:
    from wrenorm.tasks.rope import observable as crit

    sp = problem.space
    # only throws the coarse chain completes with a collision have a critical state to differentiate
    res0 = problem.simulate(np.asarray(values, np.float64)[None], problem.train)
    hits = res0.status == 1
    conds = [c for c, h in zip(problem.train, hits) if h]
    names_all = names
    goals, names = [g for g, h in zip(goals, hits) if h], [n for n, h in zip(names, hits) if h]
    C = len(conds)
    if C == 0:
        return {"names": sp.free_names, "per_condition": {n: {"coarse_hits": False} for n in names_all},
                "conditions_used": [], "fd_kinds": []}

    def f(X):
        res = problem.simulate(sp.from_unit(X), conds)  # frozen parameters keep their measured values
        st = crit.from_rollout(res, problem.n, 0.0)
        B = len(X)
        out = []
        for c in range(C):
            rows = np.arange(B) * C + c
            sub = crit.CriticalStates(st.pos[rows], st.vel[rows], st.time[rows], st.s[rows], st.hit[rows],
                                      st.clearance[rows])
            out.append(goals[c].residual(sub))
        return np.concatenate(out, axis=1)

    x_free = sp.to_unit(values)
    jac = jacobian(f, x_free, h, 0.0, 1.0)
    J, e0, kinds = jac.J, jac.f0, jac.kinds
    m = goals[0].dim
    blocks, covs = [], []
    per = {n: {"coarse_hits": False} for n in names_all}
    for c in range(C):
        Jc = J[c * m:(c + 1) * m]
        hit = bool(np.all(np.isfinite(e0[c * m:(c + 1) * m])))
        cov = measurement_covariance(goals[c], marker_noise, time_noise)
        Uf, sv, Vt = np.linalg.svd(Jc, full_matrices=False)
        noise, ok = resolvable(sv, Uf, cov, step, snr)
        per[names[c]] = {"coarse_hits": hit, "singular_values": sv, "noise": noise,
                         "right_vectors": np.round(Vt, 4), "count_above_noise_alone": int(ok.sum()) if hit else 0}
        if hit:
            blocks.append(Jc)
            covs.append(cov)
    used = [n for n in names if per[n]["coarse_hits"]]
    out = {"names": sp.free_names, "per_condition": per, "conditions_used": used,
           "fd_kinds": kinds}
    if blocks:
        J_all = np.concatenate(blocks)
        Uf, sv, Vt = np.linalg.svd(J_all, full_matrices=False)
        C_all = np.zeros((J_all.shape[0],) * 2)
        o = 0
        for cv in covs:
            C_all[o:o + m, o:o + m] = cv
            o += m
        noise, ok = resolvable(sv, Uf, C_all, step, snr)
        full, idx = fewest_experiments(blocks, covs, step, snr)
        out.update({"stacked_singular_values": sv, "stacked_noise": noise, "stacked_right_vectors": Vt,
                    "stacked_above_noise": ok,
                    "count_above_noise": int(ok.sum()), "min_experiments": len(idx),
                    "min_experiment_set": [used[i] for i in idx]})
    return out


# ------------------------------------------------------------------------------ CLI
def run(args) -> int:
    from wrenorm.cli import _device
    from wrenorm.results import versions, write_json
    from wrenorm.runfolder import prepare_out
    from wrenorm.tasks.rope import observable as crit
    from wrenorm.tasks.rope.control.command import CommandSpace
    from wrenorm.tasks.rope.control.correct import CoarseModel, NewtonRope, fit_parameters, parameters_from_file
    from wrenorm.tasks.rope.control.correct_cli import _builtin_reference
    from wrenorm.tasks.rope.problem import RopeProblem
    from wrenorm.tasks.rope.reference.materials import get_variant
    from wrenorm.tasks.rope.reference.paths import FIT_PATHS, HELD_OUT_PATHS, get_hand_path

    def progress(msg):
        if not args.quiet:
            print(msg, file=sys.stderr, flush=True)

    get_variant(args.variant)
    device = _device(args.device)
    path = get_hand_path(args.path, "--path")
    out = prepare_out(args.out or Path("runs") / f"sensitivity-rope-{time.strftime('%Y%m%d-%H%M%S')}",
                      resume=False, force=args.force)
    t_all = time.perf_counter()
    ref = _builtin_reference(args.path, args.variant, progress)
    problem = RopeProblem([ref], segments=args.segments, dt=args.dt, device=device, names=[args.path])
    fit_info = None
    if args.params == "measured":
        values = problem.space.measured
    elif args.params == "fitted":
        values, fit_info = fit_parameters(args.variant, args.segments, args.dt, args.seed, args.fit_generations,
                                          device, progress)
    else:
        values = parameters_from_file(args.params, problem)
    space = CommandSpace(path)
    goal = crit.Target.from_reference(ref)
    model = CoarseModel(problem, values, space, args.params)

    extra_cov, real_info = None, None
    if args.real_repeats:
        progress(f"measuring repeat spread: {args.real_repeats} newton runs at tiny command offsets")
        real = NewtonRope(args.variant, duration=min(float(ref.time[-1]), float(goal.state.time[0]) + 0.3),
                          device=device)
        rng = np.random.default_rng(args.seed + 1)
        offsets = rng.normal(size=(args.real_repeats, space.dim)) * args.noise_size
        es = np.stack([goal.residual(crit.from_reference(real(space.decode(d))))[0] for d in offsets])
        es = es[np.all(np.isfinite(es), axis=1)]
        if len(es) >= 2:
            extra_cov = np.cov(es.T)
        real_info = {"runs": real.runs, "wall_s": real.wall_s, "hits": int(len(es)),
                     "spread_norm": float(np.sqrt(np.trace(extra_cov))) if extra_cov is not None else None}
    progress("command sensitivity")
    cmd = command_analysis(model, goal, args.fd_step, args.noise_samples, args.noise_size, args.seed,
                           args.marker_noise, args.time_noise, args.command_step, args.snr, extra_cov)
    progress("parameter sensitivity over the built-in throws")
    names = list(FIT_PATHS) + list(HELD_OUT_PATHS)
    refs = [_builtin_reference(n, args.variant, progress) for n in names]
    pproblem = RopeProblem(refs, segments=args.segments, dt=args.dt, device=device, names=names)
    par = parameter_analysis(pproblem, values, [crit.Target.from_reference(r) for r in refs], names,
                             args.param_fd_step, args.param_step, args.snr, args.marker_noise, args.time_noise)

    top = [{"singular_value": float(cmd["singular_values"][i]), "noise": float(cmd["noise"][i]),
            "direction": dict(zip(space.names, np.round(cmd["right_vectors"][i], 4).tolist()))}
           for i in range(space.dim)]
    result = {
        "schema": "wrenorm.sensitivity/1", "system": SYSTEM, "variant": args.variant, "path": args.path,
        "params": args.params, "parameter_values": problem.space.as_dict(values), "fit": fit_info,
        "meaning": __doc__,
        "noise_model": {"marker_noise_m": args.marker_noise, "time_noise_s": args.time_noise,
                        "frame_time_s": FRAME_TIME, "tiny_command_offsets": args.noise_size,
                        "samples": args.noise_samples, "real_repeats": real_info,
                        "snr": args.snr, "command_step": args.command_step, "param_step": args.param_step},
        "command": {
            "names": space.names, "singular_values": cmd["singular_values"], "noise": cmd["noise"],
            "noise_model_roughness": cmd["noise_model"], "noise_measurement": cmd["noise_measurement"],
            "above_noise": cmd["above_noise"], "count_above_noise": cmd["count_above_noise"], "dim": space.dim,
            "min_trials_model_free": cmd["min_trials_model_free"], "directions": top,
            "fd": {"rollouts_in_one_batch": cmd["fd_rollouts"], "wall_s": cmd["fd_wall_s"], "kinds": cmd["fd_kinds"]},
        },
        "parameters": {k: v for k, v in par.items() if k != "stacked_right_vectors"},
        "wall_seconds": time.perf_counter() - t_all, "versions": versions(),
    }
    from wrenorm.cli import command_line

    result["command_line"] = command_line(args)
    result["device"] = device
    write_json(out / "sensitivity.json", result)
    _plot(out / "sensitivity.png", cmd, par, args)
    from wrenorm.fit import write_report_or_warn

    write_report_or_warn(out, result, args.quiet)
    if not args.no_record:
        _record(out / "recording.rrd", model, cmd, par, goal, args)
    print(f"command: {cmd['count_above_noise']} of {space.dim} directions above the noise "
          f"(singular values {np.array2string(cmd['singular_values'], precision=3)}); "
          f"model-free correction needs >= {cmd['min_trials_model_free']} trials")
    if "count_above_noise" in par:
        print(f"parameters: {par['count_above_noise']} of {len(par['names'])} directions above the noise over "
              f"{len(par['conditions_used'])} throws; {par['min_experiments']} throws suffice "
              f"({', '.join(par['min_experiment_set'])})")
    print(f"\nresult: {out / 'sensitivity.json'}  plot: {out / 'sensitivity.png'}")
    return 0


def _plot(path: Path, cmd: dict, par: dict, args) -> None:
    from wrenorm.viz.plots import _figure, save_figure

    plt = _figure()
    fig, (a0, a1) = plt.subplots(1, 2, figsize=(10, 3.8))
    i = np.arange(1, len(cmd["singular_values"]) + 1)
    a0.semilogy(i, cmd["singular_values"], "o-", label="singular value of de/du")
    a0.semilogy(i, args.snr * cmd["noise"] / args.command_step, "k--", label=f"{args.snr:g} x noise / step")
    a0.set_xlabel("command direction")
    a0.set_title(f"command ({cmd['count_above_noise']} of {len(i)} above noise)")
    a0.legend(fontsize=8)
    for name, row in par["per_condition"].items():
        if row["coarse_hits"]:
            a1.semilogy(np.arange(1, len(row["singular_values"]) + 1), row["singular_values"], ".-", alpha=0.6,
                        label=name)
    if "stacked_singular_values" in par:
        j = np.arange(1, len(par["stacked_singular_values"]) + 1)
        a1.semilogy(j, par["stacked_singular_values"], "ko-", label="all throws")
        a1.semilogy(j, args.snr * par["stacked_noise"] / args.param_step, "k--", label="noise floor")
    a1.set_xlabel("parameter direction")
    a1.set_title(f"parameters ({par.get('count_above_noise', 0)} of {len(par['names'])} above noise)")
    a1.legend(fontsize=7)
    save_figure(fig, path)
    plt.close(fig)


def _record(path: Path, model, cmd: dict, par: dict, goal, args) -> None:
    """Singular values, and the coarse rope at its critical point moved along the top directions."""
    from wrenorm.viz.record import Recorder, rerun_available

    if not rerun_available():
        return
    import rerun as rr

    rec = Recorder(path, application_id="wrenorm-sensitivity")
    s = rec.stream
    try:
        for i, (sv, nz) in enumerate(zip(cmd["singular_values"], cmd["noise"])):
            s.set_time("direction", sequence=i + 1)
            s.log("command/singular_value", rr.Scalars(float(sv)))
            s.log("command/noise_floor", rr.Scalars(float(args.snr * nz / args.command_step)))
        for i, (sv, nz) in enumerate(zip(par.get("stacked_singular_values", []), par.get("stacked_noise", []))):
            s.set_time("direction", sequence=i + 1)
            s.log("parameters/singular_value", rr.Scalars(float(sv)))
            s.log("parameters/noise_floor", rr.Scalars(float(args.snr * nz / args.param_step)))
        # views of their own: the two "singular_value" panels had looked alike, each apart from its noise floor,
        # and the ropes' colours had no key (review of stop 55)
        for who, step in (("command", args.command_step), ("parameters", args.param_step)):
            for entity, color in (("singular_value", (230, 230, 230)), ("noise_floor", (230, 80, 80))):
                s.log(f"{who}/{entity}", rr.SeriesLines(colors=[color], names=[entity.replace("_", " ")]),
                      static=True)
            rec.add_view(f"(timeline direction) {who}: singular value (white) against {args.snr:g} x noise / step "
                         f"{step:g} (red): a direction above its floor moves the critical state past the noise",
                         [f"/{who}/singular_value", f"/{who}/noise_floor"])
        top = min(3, cmd["dim"])
        V = cmd["right_vectors"][:top]
        U = np.concatenate([np.zeros((1, cmd["dim"])), args.command_step * V, -args.command_step * V])
        st = model.states(np.clip(U, model.space.lower, model.space.upper))
        s.log("goal/critical", rr.LineStrips3D([goal.state.pos[0].astype(np.float32)], colors=[(90, 200, 90)]),
              static=True)
        for k in range(top):
            s.set_time("direction", sequence=k + 1)
            strips = [st.pos[j].astype(np.float32) for j in (0, 1 + k, 1 + top + k) if st.hit[j]]
            s.log("command/critical_along_direction", rr.LineStrips3D(
                strips, colors=[(200, 200, 200), (170, 90, 220), (220, 200, 40)][:len(strips)]))
        rec.add_view(f"(timeline direction) the coarse rope at its first self-collision: the goal green, the start "
                     f"command grey, moved +{args.command_step:g} along direction k purple, -{args.command_step:g} "
                     "yellow", ["/goal/**", "/command/critical_along_direction"], "spatial3d",
                     around=np.concatenate([goal.state.pos[0]] + [p for p, h in zip(st.pos, st.hit) if h]))
        rec.close()
    except BaseException:
        rec.abort()
        raise
