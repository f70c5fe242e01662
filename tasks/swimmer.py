"""Robotic fish (paper section 4): a continuous fluid field replaced by five coefficients.

Observable: the forward cruising speed at each motor rate. Model: the robot's head free in the
plane, its tail following the measured gait, every part carrying MuJoCo's ellipsoid fluid model
with one shared vector of five coefficients (blunt drag, slender drag, angular drag, Kutta lift,
Magnus lift); water density 1000 kg/m^3 and viscosity 0.0013 Pa s fixed. Measured values are the
published fit (Michelis et al.); training rates 1.00 and 1.75 as in that paper, every other rate
is held out. Baseline: elongated-body theory with two constants fitted on the training rates.
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from wrenorm.errors import InputError
from wrenorm.params import Parameter, ParameterSpace
from wrenorm.problem import Condition, Problem, finite_or_inf
from wrenorm.tasks import swimmer_body as body
from wrenorm.tasks import swimmer_data as data

PUBLISHED = {"blunt_drag": 0.4, "slender_drag": 7.79, "angular_drag": 2.81, "kutta_lift": 3.84, "magnus_lift": 0.27}
DEFAULT_TRAIN = "1.00,1.75"
TOLERANCE = 0.02  # m/s


def parameter_space() -> ParameterSpace:
    doc = "MuJoCo ellipsoid fluid coefficient, shared by every body part"
    return ParameterSpace([
        Parameter("blunt_drag", PUBLISHED["blunt_drag"], 0.01, 20.0, "log", doc=doc),
        Parameter("slender_drag", PUBLISHED["slender_drag"], 0.05, 100.0, "log", doc=doc),
        Parameter("angular_drag", PUBLISHED["angular_drag"], 0.05, 100.0, "log", doc=doc),
        Parameter("kutta_lift", PUBLISHED["kutta_lift"], 0.01, 50.0, "log", doc=doc),
        Parameter("magnus_lift", PUBLISHED["magnus_lift"], 0.005, 10.0, "log", doc=doc),
    ])


# --- elongated-body theory baseline ----------------------------------------------------------

def ebt_moments(gait: dict, samples: int = 256) -> tuple[float, float]:
    """<h_t^2> and <h_t h_x> of the tail tip over one beat (head frame, x towards the tail)."""
    t = np.arange(samples) / (samples * gait["freq"])
    _, h_t, h_x = body.tip_motion(gait, t)
    return float(np.mean(h_t ** 2)), float(np.mean(h_t * h_x))


def ebt_speed(c1: float, c2: float, mom: tuple[float, float]) -> float:
    """Lighthill's mean thrust m/2 (<h_t^2> + 2U <h_t h_x>) against drag m (c1 U^2 + c2 U)."""
    ht2, htx = mom
    b = c2 - htx
    if c1 <= 1e-12:
        return 0.5 * ht2 / b if b > 0 else float("inf")
    return float((-b + np.sqrt(b * b + 2.0 * c1 * ht2)) / (2.0 * c1))


def fit_ebt(moments: list, speeds: list) -> tuple[float, float]:
    from scipy.optimize import least_squares

    def res(p):
        return [ebt_speed(p[0], p[1], m) - s for m, s in zip(moments, speeds)]

    best = None
    for c1 in (0.1, 1.0, 10.0):
        for c2 in (0.0, 0.01, 0.1):
            r = least_squares(res, [c1, c2], bounds=([0.0, 0.0], [np.inf, np.inf]))
            if best is None or r.cost < best.cost:
                best = r
    return float(best.x[0]), float(best.x[1])


# --- the problem -----------------------------------------------------------------------------

class SwimmerProblem(Problem):
    task = "swimmer"

    def __init__(self, rates: list, train_labels: list[float], device: str = "cpu", dt: float = 0.004,
                 warm_seconds: float = 2.0, meas_seconds: float = 3.0, virtual_mass: bool = False,
                 gait_mode: str = "chain", source: str = "built-in"):
        self.device = device
        self.space = parameter_space()
        self.tolerance = TOLERANCE
        self.dt, self.warm_seconds, self.meas_seconds, self.virtual_mass = dt, warm_seconds, meas_seconds, virtual_mass
        self.resolution = {"dt": dt, "min_warm_s": warm_seconds, "measure_s": meas_seconds,
                           "virtual_mass": bool(virtual_mass), "gait": gait_mode}
        self.error_doc = ("|v_sim - v_real| in m/s: forward cruising speed, slope of a straight-line fit of the "
                          "head position along the swimming direction against time")
        self.source = source
        self.rates = {r.name: r for r in rates}
        self.gaits = {r.name: body.gait(r, gait_mode) for r in rates}
        conds = [Condition(r.name, data=r, meta={"label": r.label, "speed": r.speed, "tail_freq": r.tail_freq})
                 for r in rates]
        self.train = [c for c in conds if c.meta["label"] in train_labels]
        self.held_out = [c for c in conds if c.meta["label"] not in train_labels]
        self._batches: dict = {}

    def batch(self, conditions):
        key = tuple(c.name for c in conditions)
        if key not in self._batches:
            self._batches[key] = body.build_batch(
                [self.rates[n] for n in key], device=self.device, dt=self.dt, warm_seconds=self.warm_seconds,
                meas_seconds=self.meas_seconds, virtual_mass=self.virtual_mass,
                gaits=[self.gaits[n] for n in key])
        return self._batches[key]

    def speeds(self, values: np.ndarray, conditions) -> np.ndarray:
        values = np.atleast_2d(np.asarray(values, dtype=np.float64))
        return self.batch(conditions).run(values)

    def errors(self, values, conditions):
        real = np.array([c.meta["speed"] for c in conditions])
        with np.errstate(invalid="ignore"):
            return finite_or_inf(np.abs(self.speeds(values, conditions) - real[None, :]))

    # --- reporting ------------------------------------------------------------------------------
    def ebt(self) -> dict:
        mom = {n: ebt_moments(g) for n, g in self.gaits.items()}
        c1, c2 = fit_ebt([mom[c.name] for c in self.train], [c.meta["speed"] for c in self.train])
        return {"c1": c1, "c2": c2, "speeds": {n: ebt_speed(c1, c2, m) for n, m in mom.items()}}

    def report(self, fitted, measured) -> dict:
        conds = self.train + self.held_out
        sp = self.speeds(np.stack([fitted, measured]), conds)
        ebt = self.ebt()
        speeds = {}
        for j, c in enumerate(conds):
            speeds[f"{c.meta['label']:.2f}"] = {
                "real": c.meta["speed"], "fitted": float(sp[0, j]), "measured": float(sp[1, j]),
                "ebt": ebt["speeds"][c.name], "train": c in self.train, "tail_freq": c.meta["tail_freq"]}
        val = [f"{c.meta['label']:.2f}" for c in self.held_out]
        mae = {k: float(np.mean([abs(speeds[v][k] - speeds[v]["real"]) for v in val])) if val else None
               for k in ("fitted", "measured", "ebt")}
        return {"speeds": speeds, "speed_mae": mae, "ebt_constants": {"c1": ebt["c1"], "c2": ebt["c2"]},
                "data_source": self.source,
                "published": {"speed_mae_model": 0.019, "speed_mae_ebt": 0.134,
                              "note": "Michelis et al., eight rates, full MuJoCo model, Bayesian optimisation"}}

    def record(self, recorder, fitted, measured) -> None:
        conds = self.train + self.held_out
        ebt = self.ebt()
        for c in conds:
            rate = self.rates[c.name]
            lab = f"f{rate.label:.2f}"
            t = np.arange(len(rate.markers)) / rate.fps
            step = max(1, len(t) // 300)
            for i in range(0, len(t), step):
                recorder.log_points2d(f"reference/{lab}/markers", t[i], rate.markers[i])
                recorder.log_lines2d(f"reference/{lab}/body", t[i], [rate.markers[i]])
            for tag, vals in (("fitted", fitted), ("measured", measured)):
                for tt, pts in self.simulated_bodies(c, vals, duration=t[-1], every=step / rate.fps):
                    recorder.log_points2d(f"{tag}/{lab}/markers", tt, pts)
                    recorder.log_lines2d(f"{tag}/{lab}/body", tt, [pts])
        sp = self.speeds(np.stack([fitted, measured]), conds)
        for j, c in enumerate(conds):
            x = c.meta["label"]
            recorder.log_scalar("reference/speed", x, c.meta["speed"])
            recorder.log_scalar("fitted/speed", x, sp[0, j])
            recorder.log_scalar("measured/speed", x, sp[1, j])
            recorder.log_scalar("reference/ebt_speed", x, ebt["speeds"][c.name])

    def simulated_bodies(self, cond, values, duration: float, every: float):
        """[(t, (links+3, 2) world points: two head markers, tail joints, fin tip)] of one run,
        placed at the real fish's starting pose."""
        rate = self.rates[cond.name]
        g = self.gaits[cond.name]
        period = 1.0 / g["freq"]
        n = int(np.ceil(period / self.dt))
        dt = period / n
        stride = max(1, int(round(every / dt)))
        steps = int(np.ceil(duration / dt)) + 1
        sim = body.build_batch([rate], device=self.device, dt=self.dt, warm_seconds=0.0, meas_seconds=duration,
                               max_warm_seconds=None,
                               virtual_mass=self.virtual_mass, gaits=[g])
        frames = steps // stride + 2
        _, traj, _ = sim.run(np.atleast_2d(values), rec_stride=stride, rec_frames=frames)
        traj = traj[0, 0]
        m0 = rate.markers[0]
        ex = (m0[1] - m0[0]) / np.linalg.norm(m0[1] - m0[0])
        th0 = np.arctan2(ex[1], ex[0])
        out = []
        for i in range(frames):
            X, Y, th, k = traj[i]
            tt = i * stride * dt
            if tt > duration + 1e-9 or (i > 0 and not np.any(traj[i])):
                break
            local = np.concatenate([[[0.0, 0.0], [body.HEAD_MARKER_X1, 0.0]],
                                    body.tail_points(g, np.array([k * dt]))[0]])
            c, s = np.cos(th + th0), np.sin(th + th0)
            R = np.array([[c, -s], [s, c]])
            origin = m0[0] + np.array([[np.cos(th0), -np.sin(th0)], [np.sin(th0), np.cos(th0)]]) @ [X, Y]
            out.append((tt, origin + local @ R.T))
        return out


# --- CLI -------------------------------------------------------------------------------------

def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--data", type=Path, default=None, metavar="DIR",
                   help="folder of fishsim markers_f*.csv (rate label from the file name); default: built-in data")
    p.add_argument("--train", default=DEFAULT_TRAIN, help="training rate labels, comma separated (others validate)")
    p.add_argument("--dt", type=float, default=0.004, help="simulation step [s] (fitted to a whole tail beat)")
    p.add_argument("--virtual-mass", action="store_true",
                   help="add the acceleration-dependent added mass (default: MuJoCo's model, velocity terms only)")
    p.add_argument("--gait", choices=["chain", "wave"], default="chain",
                   help="rigid links whose angles follow the markers (chain) or parts placed on the measured wave (wave)")
    p.add_argument("--generations", type=int, default=60)
    p.add_argument("--popsize", type=int, default=64)


def build_problem(args, device: str) -> SwimmerProblem:
    if args.data is None:
        rates, source = data.load_builtin(), f"built-in ({data.BUILTIN})"
    else:
        rates, source = data.load_dir(args.data), str(args.data)
    labels = data.parse_labels(args.train, rates)
    dt = float(getattr(args, "dt", 0.004))
    if not (0.0002 <= dt <= 0.02):
        raise InputError("--dt", "dt", f"must be within [0.0002, 0.02] s, got {dt}")
    return SwimmerProblem(rates, labels, device=device, dt=dt,
                          virtual_mass=bool(getattr(args, "virtual_mass", False)),
                          gait_mode=getattr(args, "gait", "chain"), source=source)
