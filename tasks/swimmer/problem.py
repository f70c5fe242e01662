"""Robotic fish (paper section 4): a continuous fluid field replaced by five coefficients.

Observable: the forward cruising speed at each motor rate. Model: the robot's head free in the
plane, its tail following the measured gait, every part carrying MuJoCo's ellipsoid fluid model
with one shared vector of five coefficients (blunt drag, slender drag, angular drag, Kutta lift,
Magnus lift); water density 1000 kg/m^3 and viscosity 0.0013 Pa s fixed. Measured values are the
published fit (Michelis et al.); training rates 1.00 and 1.75 as in that paper, every other rate
is held out. Baseline: elongated-body theory with two constants fitted on the training rates.
"""
from __future__ import annotations

import numpy as np

from wrenorm.errors import InputError
from wrenorm.params import Parameter, ParameterSpace
from wrenorm.problem import Condition, Problem, finite_or_inf
from wrenorm.tasks.swimmer import body, data
from wrenorm.tasks.swimmer.options import FLOW_BODIES, FLOW_DT

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

    def __init__(self, rates: list, train_labels: list[float], device: str = "cpu", dt: float = body.DEFAULT_DT,
                 warm_seconds: float = 2.0, meas_seconds: float = 3.0, virtual_mass: bool = False,
                 gait_mode: str = "chain", source: str = "built-in", yaw_weight: float = 0.0, scheme: int = 2,
                 bodies: int = len(body.LINKS)):
        self.device = device
        self.bodies = int(bodies)
        self.links = body.merge_links(self.bodies)  # the tail's rigid bodies (all: the robot's five plates + fin)
        self.space = parameter_space()
        self.tolerance = TOLERANCE
        self.dt, self.warm_seconds, self.meas_seconds, self.virtual_mass = dt, warm_seconds, meas_seconds, virtual_mass
        self.yaw_weight, self.scheme = float(yaw_weight), int(scheme)
        self.resolution = {"dt": dt, "min_warm_s": warm_seconds, "measure_s": meas_seconds,
                           "virtual_mass": bool(virtual_mass), "gait": gait_mode,
                           "integrator": "ros2" if scheme == 2 else "implicit-euler", "tail_bodies": self.bodies}
        self.error_doc = ("|v_sim - v_real| in m/s: forward cruising speed, slope of a straight-line fit of the "
                          "head position along the swimming direction against time")
        if self.yaw_weight > 0:
            self.error_doc = (f"sqrt(dv^2 + ({self.yaw_weight:g} m/s/rad * dyaw)^2): dv the forward cruising speed "
                              "error [m/s] (slope of a straight-line fit of the head position), dyaw the error [rad] "
                              "in the amplitude of the head's yaw oscillation at the tail-beat frequency")
        self.source = source
        self.rates = {r.name: r for r in rates}
        self.gaits = {r.name: body.gait(r, gait_mode, self.bodies) for r in rates}
        conds = [Condition(r.name, data=r, meta={"label": r.label, "speed": r.speed, "tail_freq": r.tail_freq,
                                                  "yaw_amp": r.yaw_amp})
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
                gaits=[self.gaits[n] for n in key], scheme=self.scheme, bodies=self.bodies)
        return self._batches[key]

    def simulate(self, values: np.ndarray, conditions) -> tuple[np.ndarray, np.ndarray]:
        """Cruising speeds [m/s] and head yaw amplitudes [rad], each (B, C)."""
        values = np.atleast_2d(np.asarray(values, dtype=np.float64))
        sim = self.batch(conditions)
        speed = sim.run(values)
        return speed, sim.last_yaw

    def speeds(self, values: np.ndarray, conditions) -> np.ndarray:
        return self.simulate(values, conditions)[0]

    def residuals(self, values, conditions):
        """Signed residuals (B, R): v_sim - v_real per condition [m/s], then, with a yaw weight,
        yaw_weight * (yaw_sim - yaw_real) per condition (speed-equivalent m/s)."""
        speed, yaw = self.simulate(values, conditions)
        res = speed - np.array([c.meta["speed"] for c in conditions])[None, :]
        if self.yaw_weight > 0:
            dyaw = yaw - np.array([c.meta["yaw_amp"] for c in conditions])[None, :]
            res = np.concatenate([res, self.yaw_weight * dyaw], axis=1)
        return res

    def errors(self, values, conditions):
        r = self.residuals(values, conditions)
        n = len(conditions)
        with np.errstate(invalid="ignore"):
            err = np.abs(r[:, :n]) if self.yaw_weight <= 0 else np.hypot(r[:, :n], r[:, n:])
            return finite_or_inf(err)

    # --- reporting ------------------------------------------------------------------------------
    def ebt(self) -> dict:
        mom = {n: ebt_moments(g) for n, g in self.gaits.items()}
        c1, c2 = fit_ebt([mom[c.name] for c in self.train], [c.meta["speed"] for c in self.train])
        return {"c1": c1, "c2": c2, "speeds": {n: ebt_speed(c1, c2, m) for n, m in mom.items()}}

    def report(self, fitted, measured) -> dict:
        conds = self.train + self.held_out
        sp, yaw = self.simulate(np.stack([fitted, measured]), conds)
        ebt = self.ebt()
        speeds = {}
        for j, c in enumerate(conds):
            speeds[f"{c.meta['label']:.2f}"] = {
                "real": c.meta["speed"], "fitted": float(sp[0, j]), "measured": float(sp[1, j]),
                "ebt": ebt["speeds"][c.name], "train": c in self.train, "tail_freq": c.meta["tail_freq"],
                "yaw_amp_deg": {"real": float(np.degrees(c.meta["yaw_amp"])), "fitted": float(np.degrees(yaw[0, j])),
                                "measured": float(np.degrees(yaw[1, j]))},
                "real_heading": {k: v for k, v in real_heading(self.rates[c.name]).items()
                                 if k != "path_direction_deg"}}
        val = [f"{c.meta['label']:.2f}" for c in self.held_out]
        mae = {k: float(np.mean([abs(speeds[v][k] - speeds[v]["real"]) for v in val])) if val else None
               for k in ("fitted", "measured", "ebt")}
        return {"speeds": speeds, "speed_mae": mae, "ebt_constants": {"c1": ebt["c1"], "c2": ebt["c2"]},
                "data_source": self.source, "yaw_weight": self.yaw_weight,
                "published": {"speed_mae_model": 0.019, "speed_mae_ebt": 0.134,
                              "note": "Michelis et al., eight rates, full MuJoCo model, Bayesian optimisation"}}

    def record(self, recorder, fitted, measured) -> None:
        """Per rate, one 2-D view of the real markers (grey) with the fish simulated with the fitted
        (blue) and the published (orange) coefficients, all started at the real fish's pose; then
        speed against motor rate for real, fitted, published and the EBT baseline (green)."""
        conds = self.train + self.held_out
        for c in sorted(conds, key=lambda c: c.meta["label"]):
            rate = self.rates[c.name]
            lab = f"f{rate.label:.2f}"
            t = np.arange(len(rate.markers)) / rate.fps
            step = max(1, len(t) // 300)
            head = 0.5 * (rate.markers[:, 0] + rate.markers[:, 1])
            recorder.log_lines2d(f"reference/{lab}/head_path", 0.0, [head], radii=0.0015)
            for i in range(0, len(t), step):
                recorder.log_points2d(f"reference/{lab}/markers", t[i], rate.markers[i], radii=0.006)
                recorder.log_lines2d(f"reference/{lab}/body", t[i], [rate.markers[i]], radii=0.003)
            for tag, vals in (("fitted", fitted), ("measured", measured)):
                bodies = self.simulated_bodies(c, vals, duration=t[-1], every=step / rate.fps)
                path = np.array([0.5 * (pts[0] + pts[1]) for _, pts in bodies])
                recorder.log_lines2d(f"{tag}/{lab}/head_path", 0.0, [path], radii=0.0015)
                for tt, pts in bodies:
                    recorder.log_points2d(f"{tag}/{lab}/markers", tt, pts, radii=0.004)
                    recorder.log_lines2d(f"{tag}/{lab}/body", tt, [pts], radii=0.003)
            split = "train" if c in self.train else "held out"
            recorder.add_view(f"{rate.label:.2f} Hz ({split}): real grey, fitted blue, published orange",
                              [f"/{who}/{lab}/**" for who in ("reference", "measured", "fitted")], "spatial2d")
        self._record_speed_plot(recorder, fitted, measured, conds)
        recorder.add_view("speed [m/s] vs motor rate [Hz]", ["/plot/**"], "spatial2d")
        recorder.add_view("summary", ["/summary"], "text")

    def _record_speed_plot(self, recorder, fitted, measured, conds) -> None:
        """A static x-y plot in a 2-D view (image axes: y grows downwards, so speed is drawn as -y);
        one plot unit is 1 Hz across and 0.1 m/s up."""
        conds = sorted(conds, key=lambda c: c.meta["label"])
        sp = self.speeds(np.stack([fitted, measured]), conds)
        ebt = self.ebt()
        x = np.array([c.meta["label"] for c in conds])
        series = {"real": ([c.meta["speed"] for c in conds], (230, 230, 230)),
                  "fitted": (sp[0], (40, 160, 230)),
                  "published coefficients": (sp[1], (230, 120, 40)),
                  "EBT (2 constants)": ([ebt["speeds"][c.name] for c in conds], (80, 200, 80))}
        ys = 10.0 * max(max(np.max(v[0]) for v in series.values()), 0.05)
        y_top = np.ceil(ys) + 0.2
        x_lo, x_hi = 0.0, np.ceil(x.max() * 2) / 2 + 0.25
        axes = [np.array([[x_lo, 0.0], [x_hi, 0.0]]), np.array([[x_lo, 0.0], [x_lo, -y_top]])]
        recorder.log_lines2d("plot/axes", 0.0, axes, colors=(150, 150, 150), radii=0.006)
        ticks_x = np.arange(0.5, x_hi, 0.5)
        ticks_y = np.arange(1.0, y_top, 1.0)
        recorder.log_points2d("plot/ticks", 0.0,
                              np.concatenate([np.stack([ticks_x, np.zeros_like(ticks_x)], 1),
                                              np.stack([np.zeros_like(ticks_y), -ticks_y], 1)]),
                              colors=(150, 150, 150), radii=0.012,
                              labels=[f"{v:.1f} Hz" for v in ticks_x] + [f"{v / 10:.1f} m/s" for v in ticks_y])
        for k, (name, (vals, color)) in enumerate(series.items()):
            pts = np.stack([x, -10.0 * np.asarray(vals, float)], 1)
            key = name.split(" ")[0].lower()
            recorder.log_lines2d(f"plot/{key}/line", 0.0, [pts], colors=color, radii=0.01)
            labels = [("train " if c in self.train else "") + f"{v:.3f}" if name == "real" else ""
                      for c, v in zip(conds, vals)]
            recorder.log_points2d(f"plot/{key}/points", 0.0, pts, colors=color, radii=0.025,
                                  labels=labels if name == "real" else None)
            recorder.log_points2d(f"plot/{key}/legend", 0.0, [[x_lo + 0.7, -y_top + 0.35 * k]], colors=color,
                                  radii=0.03, labels=[name])

    def simulated_bodies(self, cond, values, duration: float, every: float, align_path: bool = True):
        """[(t, (links+3, 2) world points: two head markers, tail joints, fin tip)] of one run,
        started at the real fish's head position.

        align_path: turn the run about its start so that it travels in the real head path's net
        direction (start to end). The real robot turns by up to 16 deg over a clip and its net path
        departs from its mean head axis by up to 27 deg (`real_heading`, in result.json); the model is
        left-right symmetric and swims straight along its mean body axis, so started at the real head pose
        it drifts off the real path by that much, which hides the speed comparison the view is for. Off:
        the real starting head pose."""
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
        if align_path and len(out) > 1:
            real_dir = real_heading(rate)["path_direction_deg"]
            start, end = (0.5 * (out[i][1][0] + out[i][1][1]) for i in (0, -1))
            turn = np.radians(real_dir) - np.arctan2(*(end - start)[::-1])
            c, s = np.cos(turn), np.sin(turn)
            R = np.array([[c, -s], [s, c]])
            out = [(tt, start + (pts - start) @ R.T) for tt, pts in out]
        return out


def real_heading(rate) -> dict:
    """How the real fish's heading behaves over its clip: the head path's net direction, the turn of
    the mean head axis from the first beat to the last, and the crab angle (net path direction
    against the clip's mean head axis, which points tailwards, hence the 180 deg)."""
    head = 0.5 * (rate.markers[:, 0] + rate.markers[:, 1])
    d = head[-1] - head[0]
    axis = rate.markers[:, 1] - rate.markers[:, 0]
    yaw = np.degrees(np.unwrap(np.arctan2(axis[:, 1], axis[:, 0])))
    n = max(1, int(round(rate.fps / rate.tail_freq)))  # one tail beat
    path_dir = float(np.degrees(np.arctan2(d[1], d[0])))
    crab = (path_dir - (float(np.mean(yaw)) + 180.0) + 180.0) % 360.0 - 180.0
    return {"path_direction_deg": path_dir, "turn_deg": float(np.mean(yaw[-n:]) - np.mean(yaw[:n])),
            "crab_deg": crab}


# --- building ---------------------------------------------------------------------------------

def _rates(args):
    if getattr(args, "data", None) is None:
        return data.load_builtin(), f"built-in ({data.BUILTIN})"
    return data.load_dir(args.data), str(args.data)


def _check_dt(dt: float, source: str = "--dt") -> float:
    dt = float(dt)
    if not (0.0002 <= dt <= 0.02):
        raise InputError(source, "dt", f"must be within [0.0002, 0.02] s, got {dt}")
    return dt


def _problem(args, device, rates, source, labels, dt, bodies: int = len(body.LINKS)) -> SwimmerProblem:
    yw = float(getattr(args, "yaw_weight", 0.0))
    if not (np.isfinite(yw) and yw >= 0):
        raise InputError("--yaw-weight", "yaw_weight", f"must be a finite number >= 0, got {yw}")
    return SwimmerProblem(rates, labels, device=device, dt=dt,
                          virtual_mass=bool(getattr(args, "virtual_mass", False)),
                          gait_mode=getattr(args, "gait", "chain"), source=source, yaw_weight=yw,
                          scheme=1 if getattr(args, "integrator", "ros2") == "euler" else 2,
                          bodies=bodies)


def build_problems(args, device: str) -> list[SwimmerProblem]:
    rates, source = _rates(args)
    labels = data.parse_labels(args.train, rates)
    return [_problem(args, device, rates, source, labels, _check_dt(getattr(args, "dt", body.DEFAULT_DT)),
                     _check_bodies(getattr(args, "bodies", len(body.LINKS)), "--bodies"))]


# --- resolution flow ---------------------------------------------------------------------------

def _check_bodies(n, source: str) -> int:
    if not (float(n).is_integer() and 2 <= n <= len(body.LINKS)):
        raise InputError(source, "bodies", f"tail bodies must be whole numbers in [2, {len(body.LINKS)}], got {n:g}")
    return int(n)


def flow_problems(args, device: str) -> list[SwimmerProblem]:
    """One problem per resolution, finest first: time steps [s] (--axis dt, the default) or tail
    body counts (--axis bodies), the other held at --dt / --bodies."""
    rates, source = _rates(args)
    labels = data.parse_labels(args.train, rates)
    if getattr(args, "axis", "dt") == "bodies":
        counts = sorted((_check_bodies(n, "--resolutions") for n in (args.resolutions or FLOW_BODIES)), reverse=True)
        if len(set(counts)) != len(counts):
            raise InputError("--resolutions", "bodies", f"repeated body count in {counts}")
        dt = _check_dt(getattr(args, "dt", body.DEFAULT_DT))
        return [_problem(args, device, rates, source, labels, dt, n) for n in counts]
    bodies = _check_bodies(getattr(args, "bodies", len(body.LINKS)), "--bodies")
    dts = sorted(_check_dt(d, "--resolutions") for d in (args.resolutions or FLOW_DT))
    if len(set(dts)) != len(dts):
        raise InputError("--resolutions", "dt", f"repeated time step in {dts}")
    return [_problem(args, device, rates, source, labels, dt, bodies) for dt in dts]
