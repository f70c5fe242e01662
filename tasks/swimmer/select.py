"""Choosing the swimmer's features, prior and parameter set on the training clips alone.

    python -m wrenorm select swimmer [--data DIR] [--train 1.00,1.75] [--out DIR] [--quick]

Nothing here reads a held-out rate: the clips of the other rates are dropped before any problem is built, and
the noise model is the one the fit uses (per-beat spread pooled over the training clips).

1. information: the Jacobian of the normalised residuals in ln c at the published coefficients (and at the
   chosen fit): singular values, Fisher information and data-only std (e-folds) per coefficient for the speed
   alone, the speed with each feature group, all groups, and all groups but one.
2. reachability: for each group, the best fit of speed + that group on the training rates (no prior): a group
   whose own residuals stay far outside its noise (RMS > REACH_LIMIT sigma) at the model's best is a structural
   misfit of the model, not information about the coefficients, and is left out (it would trade the headline
   speed for a feature the model cannot produce).
3. prediction: leave one training rate out. For each candidate set (reachable groups) and prior scale, fit on one
   training rate and predict the other's speed, every ordered pair of training rates, seeds SEEDS. The choice is
   the set and scale with the smallest mean |error| (ties within TIE m/s: the stronger prior, as the paper's
   procedure moves coefficients from the measured values only as far as the data demand).
4. expansion: fit the chosen set on all training rates. Where a training speed (the headline) stays more than
   SPEED_LIMIT sigma off, the five coefficients cannot reproduce the training observable together with its
   features and the prior: the paper's procedure adds a parameter. Candidate: the viscosity (MuJoCo's linear
   Stokes drag, the model's only drag term not quadratic in the speed). It is kept when the refit brings every
   training speed within SPEED_LIMIT sigma and lowers the objective by more than the BIC penalty ln(residuals).
   One training rate cannot see how the drag scales with the speed, so step 3 cannot test this; step 4 can.
5. variants: the model's switches (virtual mass on, the wave gait) and heavier speed residuals (x3, x10) with the
   chosen set, prior and parameters: training objective and leave-one-rate-out error beside the default's; a model
   switch is turned on only when it lowers both, a speed weight only when it lowers the leave-one-rate-out error
   by more than TIE with the seeds agreeing within TIE.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from wrenorm.errors import InputError

REACH_LIMIT = 5.0  # sigma: RMS of a group's normalised residuals at the best fit of speed + group
PRIOR_SCALES = (None, 2.0, 1.0, 0.5)  # e-folds; None: no prior
SEEDS = (0, 1)
TIE = 0.001  # m/s
SPEED_LIMIT = 2.0  # sigma: a training speed further off asks for a parameter more
GENERATIONS = 100
POPSIZE = 32
GROUPS = {"speed": (), "yaw": ("yaw_amp", "yaw_phase"), "sway": ("sway_amp", "sway_phase"),
          "surge2": ("surge2_amp", "surge2_phase"), "surge1": ("surge1_amp", "surge1_phase")}


def add_arguments(p: argparse.ArgumentParser) -> None:
    from wrenorm.options import add_number
    from wrenorm.tasks.swimmer.options import add_data_arguments

    p.add_argument("--out", type=Path, default=None, help="output folder (default runs/select-swimmer-<time>)")
    p.add_argument("--force", action="store_true", help="overwrite a non-empty --out folder that wrenorm wrote")
    p.add_argument("--quiet", action="store_true")
    p.add_argument("--quick", action="store_true", help="one seed, two prior scales, fewer generations (a smoke run)")
    add_number(p, "--generations", default=GENERATIONS, lo=1, hi=10000, integer=True,
               help="CMA-ES generations per fit (each then polished by Levenberg-Marquardt)")
    add_data_arguments(p)


class Study:
    """The training clips, their noise model, and fits on them."""

    def __init__(self, rates, train_labels, generations=GENERATIONS, virtual_mass=False, gait="chain",
                 quiet=False):
        from wrenorm.tasks.swimmer import features as feat
        from wrenorm.tasks.swimmer import problem as sw

        self.sw = sw
        self.labels = list(train_labels)
        self.rates = [r for r in rates if any(abs(r.label - t) < 1e-6 for t in self.labels)]
        self.generations, self.quiet = int(generations), quiet
        self.model = {"virtual_mass": bool(virtual_mass), "gait_mode": gait}
        # head-frame clips (rotatedMarkers) cannot measure the yaw or sway groups: they are no candidates
        unmeasurable = set(feat.unmeasurable(self.rates))
        self.groups = {g: fs for g, fs in GROUPS.items() if not unmeasurable & set(fs)}
        self.every = ("speed", *[f for fs in self.groups.values() for f in fs])
        every = self.problem(self.labels, self.every, None)
        self.noise, self.warnings = every.noise, list(every.warnings)  # the training clips' flags

    def problem(self, train, features, prior, viscosity=False, **model):
        p = self.sw.SwimmerProblem(self.rates, list(train), features=features, prior_scale=prior,
                                   free_viscosity=viscosity, **(self.model | model))
        if getattr(self, "noise", None) is not None:
            p.noise = self.noise  # the fit's noise model (pooled over all training clips), also in a one-rate fold
        return p

    def fit(self, p, seed=0) -> tuple[np.ndarray, float]:
        from wrenorm import search
        from wrenorm.least_squares import polish_if_better

        r = search.cmaes(p, seed=seed, popsize=POPSIZE, generations=self.generations, quiet=True)
        return polish_if_better(p, r.best_values, r.best_loss)

    def z(self, p, values) -> dict:
        """Every feature's normalised residual per training clip at `values`."""
        from wrenorm.tasks.swimmer import features as feat

        sim = p.simulate(values[None], p.train, features=feat.FEATURES)
        return {c.name: {f: float(feat.feature_difference(sim[f][0, j], c.meta["features"][f], f) / p.sigma(c, f))
                         for f in feat.FEATURES} for j, c in enumerate(p.train)}

    def say(self, msg):
        if not self.quiet:
            print(msg, file=sys.stderr, flush=True)


def information(study: Study, point=None, viscosity: bool = False) -> dict:
    """Singular values, Fisher information diagonal and data-only std [e-folds] of the five coefficients (and the
    viscosity, where it is free) for feature subsets, from one batched Jacobian of every feature's normalised
    residual at `point`."""
    from wrenorm.jacobian import jacobian
    from wrenorm.uncertainty import _std

    p = study.problem(study.labels, study.every, None, viscosity)
    point = p.space.measured if point is None else np.asarray(point, np.float64)
    space = p.space
    u0 = np.clip(space.to_unit(point), 0.0, 1.0)
    jac = jacobian(lambda U: p.residuals(space.from_unit(U), p.train), u0, 1e-3, 0.0, 1.0)
    span = np.array([np.log(q.upper) - np.log(q.lower) for q in space.free])
    J = jac.J / span[None, :]  # d residual / d ln c
    rows = [(c.name, f) for c in p.train for f in p.features]
    names = space.free_names

    def summary(fs):
        idx = [i for i, (_, f) in enumerate(rows) if f in fs]
        Jg = J[idx]
        _, std, JtJ = _std(Jg, 1.0)
        return {"features": list(fs), "singular_values": np.linalg.svd(Jg, compute_uv=False).tolist(),
                "fisher_diagonal": dict(zip(names, np.diag(JtJ).tolist())),
                "data_std_efolds": dict(zip(names, std.tolist()))}

    groups = [g for g, fs in study.groups.items() if fs]
    every = list(study.every)
    out = {"point": space.as_dict(point), "speed": summary(["speed"])}
    for g in groups:
        out[f"speed+{g}"] = summary(["speed", *GROUPS[g]])
    out["all"] = summary(every)
    for g in groups:
        out[f"all-{g}"] = summary([f for f in every if f not in GROUPS[g]])
    return out


def reachability(study: Study) -> dict:
    out = {}
    for g, fs in study.groups.items():
        t0 = time.perf_counter()
        p = study.problem(study.labels, ("speed", *fs), None)
        v, loss = study.fit(p)
        z = study.z(p, v)
        own = [z[c.name][f] for c in p.train for f in (fs or ("speed",))]
        rms = float(np.sqrt(np.mean(np.square(own))))
        out[g] = {"coefficients": p.space.as_dict(v), "normalised_residuals": z, "group_rms": rms,
                  "reachable": rms <= REACH_LIMIT}
        study.say(f"reach {g:7s} group RMS {rms:6.1f} sigma  ({time.perf_counter() - t0:.0f} s)")
    return out


def candidate_sets(reach: dict) -> dict:
    ok = [g for g in reach if GROUPS[g] and reach[g]["reachable"]]
    sets = {"speed": ("speed",)}
    for g in ok:
        sets[g] = ("speed", *GROUPS[g])
    if len(ok) > 1:
        sets["+".join(ok)] = ("speed", *[f for g in ok for f in GROUPS[g]])
    return sets


def leave_one_out(study: Study, sets: dict, priors=PRIOR_SCALES, seeds=SEEDS, viscosity=False, **model) -> list:
    rows = []
    by_label = {r.label: r for r in study.rates}
    pairs = [(a, b) for a in study.labels for b in study.labels if a != b]
    for name, fs in sets.items():
        for prior in priors:
            for fit_on, predict in pairs:
                for seed in seeds:
                    t0 = time.perf_counter()
                    p = study.problem([fit_on], fs, prior, viscosity, **model)
                    v, _ = study.fit(p, seed)
                    other = [c for c in p.held_out if abs(c.meta["label"] - predict) < 1e-6]
                    pred = float(p.speeds(v[None], other)[0, 0])
                    real = by_label[predict].speed
                    rows.append({"features": name, "prior_scale": prior, "fit_on": fit_on, "predict": predict,
                                 "seed": seed, "predicted": pred, "real": real, "error": pred - real,
                                 "coefficients": p.space.as_dict(v)})
                    study.say(f"loo {name:12s} prior {prior!s:5s} {fit_on:.2f}->{predict:.2f} seed {seed}: "
                              f"{pred:.4f} vs {real:.4f} ({time.perf_counter() - t0:.0f} s)")
    return rows


def choose(rows: list, tie: float = TIE) -> dict:
    table = {}
    for r in rows:
        table.setdefault((r["features"], r["prior_scale"]), []).append(abs(r["error"]))
    summary = [{"features": k[0], "prior_scale": k[1], "mean_abs_error": float(np.mean(v)),
                "max_abs_error": float(np.max(v))} for k, v in table.items()]
    best = min(s["mean_abs_error"] for s in summary)
    close = [s for s in summary if s["mean_abs_error"] <= best + tie]
    # among near-ties the stronger prior (move from the measured values only as far as the data demand), then
    # the smaller error
    pick = min(close, key=lambda s: (np.inf if s["prior_scale"] is None else s["prior_scale"], s["mean_abs_error"]))
    return {"table": summary, "chosen": pick, "tie_tolerance": tie}


def two_rate_fit(study: Study, features, prior, viscosity=False, **model) -> dict:
    p = study.problem(study.labels, features, prior, viscosity, **model)
    v, loss = study.fit(p)
    z = study.z(p, v)
    n_res = len(p.train) * len(p.features)
    return {"features": list(p.features), "prior_scale": prior, "viscosity_free": viscosity, "model": model,
            "coefficients": p.space.as_dict(v), "objective": float(loss), "residuals": n_res,
            "free": len(p.space.free), "speed_z": {c.name: z[c.name]["speed"] for c in p.train},
            "normalised_residuals": z}


def expansion(study: Study, features, prior) -> dict:
    """Step 4: the chosen set on all training rates, then with the viscosity freed; the rule's verdict."""
    five = two_rate_fit(study, features, prior)
    worst = max(abs(x) for x in five["speed_z"].values())
    out = {"five": five, "speed_limit_sigma": SPEED_LIMIT, "worst_training_speed_sigma": worst}
    if worst <= SPEED_LIMIT:
        out.update(free_viscosity=False, reason=f"every training speed within {SPEED_LIMIT:g} sigma")
        return out
    six = two_rate_fit(study, features, prior, viscosity=True)
    worst6 = max(abs(x) for x in six["speed_z"].values())
    drop = five["objective"] - six["objective"]
    penalty = float(np.log(five["residuals"]))
    keep = worst6 <= SPEED_LIMIT and drop > penalty
    out.update(six=six, worst_training_speed_sigma_with_viscosity=worst6, objective_drop=drop, bic_penalty=penalty,
               free_viscosity=bool(keep),
               reason=(f"training speed {worst:.1f} sigma off with five coefficients; viscosity freed: "
                       f"{worst6:.1f} sigma, objective {five['objective']:.1f} -> {six['objective']:.1f} "
                       f"(BIC penalty {penalty:.1f})"))
    return out


def variants(study: Study, features, prior, viscosity, seeds=SEEDS) -> dict:
    """Step 5: the model's switches (virtual mass, the wave gait) and heavier speed residuals against the default:
    training objective (the unweighted one) and leave-one-rate-out error with every seed. A model switch is kept
    when it lowers both; a speed weight when it lowers the leave-one-rate-out error by more than TIE with the
    seeds agreeing within TIE on every fold (a weight is no likelihood: it needs a clear, robust gain)."""
    from wrenorm.search import objective

    out = {}
    plain = study.problem(study.labels, features, prior, viscosity)
    switches = (("default", {}), ("virtual_mass", {"virtual_mass": True}), ("wave_gait", {"gait_mode": "wave"}),
                ("speed_weight_3", {"speed_weight": 3.0}), ("speed_weight_10", {"speed_weight": 10.0}))
    for name, model in switches:
        fit = two_rate_fit(study, features, prior, viscosity, **model)
        values = np.array([fit["coefficients"][n] for n in plain.space.names])
        unweighted = (float(objective(plain, values[None])[0]) if "speed_weight" in model else fit["objective"])
        rows = leave_one_out(study, {"chosen": features}, priors=(prior,), seeds=seeds, viscosity=viscosity, **model)
        folds = {}
        for r in rows:
            folds.setdefault((r["fit_on"], r["predict"]), []).append(r["predicted"])
        out[name] = {"objective": unweighted, "speed_z": fit["speed_z"],
                     "loo_mean_abs_error": float(np.mean([abs(r["error"]) for r in rows])),
                     "loo_seed_spread": float(max(np.ptp(v) for v in folds.values())),
                     "loo": [{k: r[k] for k in ("fit_on", "predict", "seed", "predicted", "real", "error")}
                             for r in rows],
                     "coefficients": fit["coefficients"]}
        study.say(f"variant {name:15s} objective {unweighted:7.1f}  LOO {out[name]['loo_mean_abs_error']:.4f} "
                  f"(seed spread {out[name]['loo_seed_spread']:.4f})")
    base = out["default"]
    for name in ("virtual_mass", "wave_gait"):
        v = out[name]
        v["better_than_default"] = bool(v["objective"] < base["objective"]
                                        and v["loo_mean_abs_error"] < base["loo_mean_abs_error"])
    for name in ("speed_weight_3", "speed_weight_10"):
        v = out[name]
        v["better_than_default"] = bool(v["loo_mean_abs_error"] < base["loo_mean_abs_error"] - TIE
                                        and v["loo_seed_spread"] <= TIE)
    return out


def run(args) -> int:
    from wrenorm.results import versions, write_json
    from wrenorm.runfolder import prepare_out
    from wrenorm.tasks.swimmer import data
    from wrenorm.tasks.swimmer.problem import _rates, warn

    rates, source = _rates(args)
    labels = data.parse_labels(args.train, rates)
    if len(labels) < 2:
        raise InputError("--train", ",".join(map(str, args.train)), "the selection needs at least two training rates")
    out = prepare_out(args.out or Path("runs") / f"select-swimmer-{time.strftime('%Y%m%d-%H%M%S')}",
                      force=args.force, command="select swimmer")
    quick = bool(args.quick)
    study = Study(rates, labels, generations=min(args.generations, 30) if quick else args.generations,
                  virtual_mass=args.virtual_mass, gait=args.gait, quiet=args.quiet)
    priors, seeds = ((None, 1.0), (0,)) if quick else (PRIOR_SCALES, SEEDS)
    warn(study)  # the data's flags (a tail beat that points at a wrong frame rate), as fit and flow say them
    t0 = time.perf_counter()
    result = {"train": labels, "data_source": source, "noise": study.noise, "warnings": study.warnings,
              "rules": {"reach_limit_sigma": REACH_LIMIT, "prior_scales": list(priors), "seeds": list(seeds),
                        "tie_m_s": TIE, "speed_limit_sigma": SPEED_LIMIT, "generations": study.generations},
              "information_published": information(study)}
    reach = reachability(study)
    result["reachability"] = reach
    sets = candidate_sets(reach)
    result["candidate_sets"] = {k: list(v) for k, v in sets.items()}
    rows = leave_one_out(study, sets, priors=priors, seeds=seeds)
    result["leave_one_out"] = rows
    choice = choose(rows)
    result["choice"] = choice
    features, prior = sets[choice["chosen"]["features"]], choice["chosen"]["prior_scale"]
    exp = expansion(study, features, prior)
    result["expansion"] = exp
    study.say(f"expansion: {exp['reason']} -> free viscosity: {exp['free_viscosity']}")
    result["variants"] = variants(study, features, prior, exp["free_viscosity"], seeds=seeds)
    fit = exp["six"] if exp["free_viscosity"] else exp["five"]
    point = np.array([fit["coefficients"][n] for n in study.problem(labels, "speed", None).space.names])
    result["information_fit"] = information(study, point, exp["free_viscosity"])
    result["recommended"] = {"features": choice["chosen"]["features"], "feature_list": list(features),
                             "prior_scale": prior, "free_viscosity": exp["free_viscosity"],
                             "virtual_mass": bool(result["variants"]["virtual_mass"]["better_than_default"]),
                             "wave_gait": bool(result["variants"]["wave_gait"]["better_than_default"]),
                             "speed_weight": next((w for w, k in ((10.0, "speed_weight_10"), (3.0, "speed_weight_3"))
                                                   if result["variants"][k]["better_than_default"]), 1.0)}
    result["wall_seconds"] = time.perf_counter() - t0
    result["versions"] = versions()
    write_json(out / "select.json", result)
    for s in sorted(choice["table"], key=lambda s: s["mean_abs_error"]):
        print(f"{s['features']:14s} prior {s['prior_scale']!s:5s} leave-one-rate-out mean |err| "
              f"{s['mean_abs_error']:.4f} max {s['max_abs_error']:.4f}")
    print(f"recommended: {result['recommended']}\nresult: {out / 'select.json'}")
    return 0

