"""The PD joint's fit done by a peer tool, MuJoCo's `mujoco.sysid`, as a whole process, for the bench's side-by-
side comparison (`python -m wrenorm.tasks.pd.sysid_peer --f-sim 200` prints one JSON line).

The same job: one hinge with armature J (the body keeps 1e-12 of inertia, which MuJoCo requires), a position
actuator for K_P (frozen, the gauge), a velocity actuator for K_D and two motors for the feed-forward gains K_FF
(on qd_d) and K_AFF (on qdd_d), MuJoCo's Euler at the wrenorm step: a rollout equals wrenorm's semi-implicit
kernel to rounding (MuJoCo applies a velocity actuator's -kv v explicitly). The same commands and the same
references (exact_reference), three training and three held-out. Fitted on the qpos STATE signal: a sysid
rollout's sensors are stamped one step late, and fitting through the position sensor on a correctly stamped log
gives a worse model than no fit. The held-out error is wrenorm's definition (RMS(q_sim - q_ref) / RMS(q_ref),
mean over the held-out commands), from MuJoCo rollouts at the fitted values.
"""
from __future__ import annotations

import argparse
import contextlib
import io
import json
import time

import numpy as np

IZZ = 1e-12  # kg m^2 about the hinge: MuJoCo refuses a moving body without inertia; armature carries the rest


def _model_xml(dt: float, J: float, KP: float, KD: float) -> str:
    return f"""<mujoco model="pd_joint">
  <option timestep="{dt!r}" integrator="Euler" gravity="0 0 0">
    <flag contact="disable" constraint="disable" warmstart="disable"/>
  </option>
  <worldbody><body name="link"><inertial pos="0 0 0" mass="1" diaginertia="1 1 {IZZ!r}"/>
    <joint name="hinge" type="hinge" axis="0 0 1" armature="{J - IZZ!r}"/></body></worldbody>
  <actuator>
    <position name="kp" joint="hinge" kp="{KP!r}"/><velocity name="kd" joint="hinge" kv="{KD!r}"/>
    <motor name="ff" joint="hinge" gear="1" ctrllimited="false"/>
    <motor name="aff" joint="hinge" gear="1" ctrllimited="false"/>
  </actuator>
  <sensor><jointpos name="q_sensor" joint="hinge"/></sensor>
</mujoco>"""


def _set_one(spec, name: str, value: float) -> None:
    """One parameter into a model spec (sysid calls a modifier per parameter)."""
    if name == "J":
        spec.joint("hinge").armature = value - IZZ
    elif name == "K_D":
        kd = spec.actuator("kd")
        kd.gainprm[0], kd.biasprm[2] = value, -value
    else:
        spec.actuator({"K_FF": "ff", "K_AFF": "aff"}[name]).gainprm[0] = value


def run(f_sim: float) -> dict:
    t0 = time.perf_counter()
    import mujoco
    import mujoco.rollout as mj_rollout
    from mujoco import sysid

    from wrenorm.tasks.pd.options import MEASURED
    from wrenorm.tasks.pd.problem import DURATION, HELD_OUT_COMMANDS, TRAIN_COMMANDS, exact_reference

    J, KP, KD = MEASURED["J"], MEASURED["K_P"], MEASURED["K_D"]
    dt = 1.0 / f_sim
    t = np.arange(int(round(DURATION * f_sim)) + 1) * dt
    xml = _model_xml(dt, J, KP, KD)

    def condition(cmd):
        q_d, qd_d, qdd_d = cmd(t)
        return cmd.name, np.stack([q_d, qd_d, qd_d, qdd_d], axis=1), exact_reference(cmd, J, KP, KD, t)

    train, held = [condition(c) for c in TRAIN_COMMANDS], [condition(c) for c in HELD_OUT_COMMANDS]
    spec = mujoco.MjSpec.from_string(xml)
    model = spec.compile()
    init = sysid.create_initial_state(model, np.zeros(1), np.zeros(1))
    sequences = sysid.ModelSequences(
        "pd", spec, [n for n, _, _ in train], [init] * len(train), [sysid.TimeSeries(t, u) for _, u, _ in train],
        [sysid.TimeSeries.from_names(t, q[:, None], model, ["hinge_qpos"]) for _, _, q in train])
    params = sysid.ParameterDict()
    start = {"J": J, "K_D": KD, "K_FF": 0.0, "K_AFF": 0.0}
    bounds = {"J": (J / 5, J * 5), "K_D": (KD / 5, KD * 5), "K_FF": (-3 * KD, 3 * KD), "K_AFF": (-J, J)}
    for name in start:
        params.add(sysid.Parameter(name, start[name], *bounds[name],
                                   modifier=lambda s, p, name=name: _set_one(s, name, p.value[0])))
    residual = sysid.build_residual_fn(models_sequences=[sequences], resample_true=False)
    calls = {"residual_calls": 0, "parameter_points": 0}

    def counted(x, p, **kw):
        calls["residual_calls"] += 1
        calls["parameter_points"] += 1 if np.ndim(x) == 1 else np.shape(x)[1]
        return residual(x, p, **kw)

    t_opt = time.perf_counter()
    with contextlib.redirect_stdout(io.StringIO()):
        fitted_params, _ = sysid.optimize(params, counted, optimizer="mujoco", verbose=False)
    t_opt = time.perf_counter() - t_opt
    fitted = dict(zip(start, (float(v) for v in fitted_params.as_vector())))

    def errors(conds) -> np.ndarray:
        s = mujoco.MjSpec.from_string(xml)
        for name, value in fitted.items():
            _set_one(s, name, value)
        m = s.compile()
        u = np.stack([c[1][:-1] for c in conds])
        state, _ = mj_rollout.rollout(m, mujoco.MjData(m), np.tile(init, (len(conds), 1)), u)
        q_sim, q_ref = state[:, :, 1], np.stack([c[2][1:] for c in conds])
        return np.sqrt(np.mean((q_sim - q_ref) ** 2, axis=1)) / np.sqrt(np.mean(q_ref ** 2, axis=1))

    return {"tool": f"mujoco.sysid {mujoco.__version__}", "f_sim": f_sim, "fitted": fitted | {"K_P": KP},
            "train_loss": float(errors(train).mean()), "held_out_error": float(errors(held).mean()),
            "optimize_s": t_opt, "in_process_s": time.perf_counter() - t0, **calls}


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--f-sim", type=float, default=200.0)
    print(json.dumps(run(ap.parse_args().f_sim)))
