"""Multi-joint PD at finite frequency: a two-link arm with configuration-dependent M(q).

The appendix's matrix result: the simulator needs M^sim(q) = M(q) + delta_v K_D (a constant,
armature-like joint-space correction) and K_D^sim = K_D + delta_q K_P, with the integrator's
delays delta_q, delta_v (semi-implicit Euler: 0 and dt/2). Fitted: the symmetric correction
A (3 numbers) and the full K_D^sim matrix (4); K_P frozen (the gauge, as for one joint).
"""
from __future__ import annotations

import numpy as np

from wrenorm.errors import InputError
from wrenorm.params import Parameter, ParameterSpace
from wrenorm.problem import Condition, Problem
from wrenorm.tasks.pd.problem import ANALYTIC_DELAY, DURATION, FADE_IN, RAMP, Command

K_P = np.array([[20.0, 3.0], [3.0, 8.0]])
K_D = np.array([[0.6, 0.05], [0.05, 0.25]])
BASE = np.array([0.3, 1.0])  # rad, the posture commands move about (cos q2 varies along them)

# Amplitudes of 0.1-0.35 rad keep joint speeds near 1-2 rad/s. The integrator also delays the
# velocity inside the Coriolis terms, an inertia correction that grows with speed and that no
# constant A absorbs; at 3x these amplitudes it biases A11 by ~20 % (measured, see README).
TRAIN = [
    (Command("sine_0.8Hz", "sine", 0.21, 0.8), Command("sine_1.3Hz", "sine", 0.28, 1.3)),
    (Command("chirp", "chirp", 0.14, 0.2, 3.0), Command("step", "step", 0.32, t0=0.4)),
    (Command("step", "step", -0.25, t0=0.2), Command("chirp", "chirp", 0.18, 0.3, 3.5)),
]
HELD_OUT = [
    (Command("multisine", "multisine", 0.32, 0.5, 1.1), Command("multisine", "multisine", 0.35, 0.7, 1.6)),
    (Command("sine_1.7Hz", "sine", 0.18, 1.7), Command("step", "step", -0.35, t0=0.6)),
]


def _name(pair):
    return f"{pair[0].name}+{pair[1].name}"


def _rel(fit, pred, scale):
    return float(np.linalg.norm(fit - pred) / np.linalg.norm(scale))


def arm_parameter_space(m22: float) -> ParameterSpace:
    """The arm's joint-space inertia correction (within 30 % of the distal joint's inertia m22) and gain matrices."""
    ps = [Parameter(n, 0.0, -0.3 * m22, 0.3 * m22, unit="kg m^2", doc="joint-space inertia correction")
          for n in ("A11", "A12", "A22")]
    for (i, j) in ((0, 0), (0, 1), (1, 0), (1, 1)):
        kd, span = K_D[i, j], max(abs(K_D[i, j]), 0.2 * K_D[j, j])
        ps.append(Parameter(f"KD{i+1}{j+1}", kd, kd - 2 * span, kd + 2 * span, unit="N m s/rad"))
    for (i, j) in ((0, 0), (0, 1), (1, 0), (1, 1)):
        kp = K_P[i, j]
        ps.append(Parameter(f"KP{i+1}{j+1}", kp, kp - abs(kp) - 1, kp + abs(kp) + 1, frozen=True, unit="N m/rad",
                            doc="frozen: fixes the gauge"))
    return ParameterSpace(ps)


class ArmProblem(Problem):
    task = "pd"
    least_squares = True  # the trajectory residuals are the observable: fit their sum of squares
    error_doc = "mean over the two joints of RMS(q_sim - q_ref) / RMS(q_ref) (per condition)"

    def __init__(self, f_sim: float, device: str = "cpu", tolerance: float = 0.02):
        from wrenorm.kernels import arm

        if not (np.isfinite(f_sim) and f_sim > 0):
            raise InputError("--f-sim", "f_sim", f"must be a positive frequency, got {f_sim!r}")
        self.arm = arm
        self.geo = arm.geometry()
        self.f_sim, self.dt = float(f_sim), 1.0 / float(f_sim)
        self.device = device
        self.tolerance = tolerance
        self.resolution = {"f_sim": self.f_sim, "dt": self.dt, "integrator": "semi-implicit", "joints": 2}
        self.space = arm_parameter_space(float(arm.mass_matrix(self.geo, np.array([0.0]))[0, 1, 1]))
        self.train = [self._condition(p) for p in TRAIN]
        self.held_out = [self._condition(p) for p in HELD_OUT]

    def _condition(self, pair) -> Condition:
        n = int(round(DURATION * self.f_sim))
        t = np.arange(n + 1) * self.dt
        cmds = [c(t) for c in pair]
        q_d = np.stack([BASE[j] + cmds[j][0] for j in range(2)], -1)
        qd_d = np.stack([cmds[j][1] for j in range(2)], -1)
        q_ref = self._reference(pair, t)
        return Condition(_name(pair), {"t": t, "q_d": q_d[:-1], "qd_d": qd_d[:-1], "q_ref": q_ref})

    def _reference(self, pair, t):
        from scipy.integrate import solve_ivp

        geo = self.geo

        def rhs(tt, y):
            q, v = y[:2], y[2:]
            cmd = [c(np.array([tt])) for c in pair]
            qd = BASE + np.array([cmd[0][0][0], cmd[1][0][0]])
            vd = np.array([cmd[0][1][0], cmd[1][1][0]])
            tau = K_P @ (qd - q) + K_D @ (vd - v) - self.arm.bias_force(geo, q[1], v[0], v[1])
            M = self.arm.mass_matrix(geo, np.array([q[1]]))[0]
            return np.concatenate([v, np.linalg.solve(M, tau)])

        kinks = sorted({x for c in pair for x in ([c.t0, c.t0 + RAMP] if c.kind == "step" else [FADE_IN])})
        breaks = [0.0] + [k for k in kinks if 0 < k < t[-1]] + [float(t[-1])]
        y = np.concatenate([BASE, [0.0, 0.0]])
        out = np.empty((len(t), 2))
        for a, b in zip(breaks[:-1], breaks[1:]):
            sel = (t >= a) & ((t < b) if b < t[-1] else (t <= b))
            sol = solve_ivp(rhs, (a, b), y, method="DOP853", rtol=1e-10, atol=1e-12, dense_output=True)
            out[sel] = sol.sol(t[sel])[:2].T
            y = sol.y[:, -1]
        return out

    def _arrays(self, conditions):
        n = min(len(c.data["q_d"]) for c in conditions)
        return (np.stack([c.data["q_d"][:n] for c in conditions]), np.stack([c.data["qd_d"][:n] for c in conditions]),
                np.stack([c.data["q_ref"][:n + 1] for c in conditions]))

    def errors(self, values, conditions):
        return self.arm.simulate(values, *self._arrays(conditions), self.geo, self.dt, self.device)

    def residuals(self, values, conditions):
        q_des, qd_des, q_ref = self._arrays(conditions)
        _, tr = self.arm.simulate(values, q_des, qd_des, q_ref, self.geo, self.dt, self.device, record=True)
        scale = np.sqrt(np.mean(q_ref[:, 1:] ** 2, axis=1)) * np.sqrt(q_ref.shape[1] - 1)
        return ((tr[:, :, 1:] - q_ref[None, :, 1:]) / scale[None, :, None, :]).reshape(len(values), -1)

    def analytic(self, fitted: dict) -> dict:
        c = ANALYTIC_DELAY["semi-implicit"]
        d = c["J"] * self.dt
        A_pred = d * K_D
        A_second = A_pred + d * d * K_P / 2
        KD_pred = K_D + c["K_D"] * self.dt * K_P
        A_fit = np.array([[fitted["A11"], fitted["A12"]], [fitted["A12"], fitted["A22"]]])
        KD_fit = np.array([[fitted["KD11"], fitted["KD12"]], [fitted["KD21"], fitted["KD22"]]])
        return {
            "dt": self.dt,
            "formula": "M^sim(q) = M(q) + (dt/2) K_D (symmetrised), K_D^sim = K_D (semi-implicit Euler)",
            "A_first_order": ((A_pred + A_pred.T) / 2).tolist(),
            "A_second_order": ((A_second + A_second.T) / 2).tolist(),
            "K_D_sim_first_order": KD_pred.tolist(),
            "A_fitted": A_fit.tolist(),
            "K_D_sim_fitted": KD_fit.tolist(),
            "A_relative_error_first_order": _rel(A_fit, (A_pred + A_pred.T) / 2, A_pred),
            "A_relative_error_second_order": _rel(A_fit, (A_second + A_second.T) / 2, A_second),
        }

    def report(self, fitted, measured):
        return {"analytic": self.analytic(self.space.as_dict(fitted)), "f_sim": self.f_sim}

    def record(self, rec, fitted, measured):
        for split, group in (("train", self.train), ("held_out", self.held_out)):
            q_des, qd_des, q_ref = self._arrays(group)
            _, tr = self.arm.simulate(np.stack([measured, fitted]), q_des, qd_des, q_ref, self.geo, self.dt,
                                      self.device, record=True)
            for j, c in enumerate(group):
                t = c.data["t"][: tr.shape[2]]
                for k in range(2):
                    rec.log_series(f"reference/{split}/{c.name}/q{k+1}", t, q_ref[j, :, k])
                    rec.log_series(f"measured/{split}/{c.name}/q{k+1}", t, tr[0, j, :, k])
                    rec.log_series(f"fitted/{split}/{c.name}/q{k+1}", t, tr[1, j, :, k])
                    rec.add_view(f"{split}: {c.name} q{k+1}",
                                 [f"/{who}/{split}/{c.name}/q{k+1}" for who in ("reference", "measured", "fitted")])
        rec.add_view("summary", ["/summary"], "text")
