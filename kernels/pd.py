"""A PD-controlled joint simulated at a finite frequency, batched: one thread per slot.

Slot s simulates candidate parameters params[s] = (J, K_P, K_D, K_FF, K_AFF) under command
cond[s]. The controller is sampled and held for one step:
    tau_k = K_P (q_d,k - q_k) + K_D (qd_d,k - v_k) + K_FF qd_d,k + K_AFF qdd_d,k
and integrated with
    SEMI_IMPLICIT (symplectic) Euler: v += dt tau/J; q += dt v     (MuJoCo, Isaac, Bullet)
    EXPLICIT Euler:                   q += dt v;     v += dt tau/J
Float64 throughout: fitted values are compared with O(dt^2) analytic corrections.
"""
from __future__ import annotations

import numpy as np
import warp as wp

SEMI_IMPLICIT = 0
EXPLICIT = 1
INTEGRATORS = {"semi-implicit": SEMI_IMPLICIT, "explicit": EXPLICIT}
# Where in its step each integrator's velocity lives, in steps from the step's start (`_step`): the semi-implicit step
# moves q by dt times the velocity it has just updated, so its v_k is the motion's velocity half a step before t_k;
# explicit Euler moves q by the old velocity, half a step after. A state taken from a measured motion starts there.
VELOCITY_AT = {"semi-implicit": -0.5, "explicit": 0.5}


@wp.func
def _step(integrator: int, dt: wp.float64, J: wp.float64, tau: wp.float64, q: wp.float64, v: wp.float64):
    a = tau / J
    if integrator == 0:
        v_new = v + dt * a
        return q + dt * v_new, v_new
    return q + dt * v, v + dt * a


@wp.kernel
def rollout(
    params: wp.array2d(dtype=wp.float64),
    cond: wp.array(dtype=int),
    q_des: wp.array2d(dtype=wp.float64),
    qd_des: wp.array2d(dtype=wp.float64),
    qdd_des: wp.array2d(dtype=wp.float64),
    q_ref: wp.array2d(dtype=wp.float64),
    ref_scale: wp.array(dtype=wp.float64),
    init: wp.array2d(dtype=wp.float64),
    fit_start: wp.array(dtype=int),
    integrator: int,
    dt: wp.float64,
    n_steps: int,
    record: int,
    record_unit: int,
    offset: int,
    err: wp.array(dtype=wp.float64),
    start_shift: wp.array(dtype=wp.float64),
    traj: wp.array2d(dtype=wp.float64),
    traj_unit: wp.array2d(dtype=wp.float64),
):
    """Slot s's rollout and its error against q_ref, with the start velocity corrected by the shift that minimises the
    misfit where fit_start[cond] (a measured log's noisy start). The joint is linear in its state, so the rollout from
    a shifted start is the one from the given start plus the shift times the unforced response to a unit start
    velocity (hq, hv): both run in this one loop (as fast as the rollout alone: `bench`), and the misfit of every shift
    is a quadratic in it from three sums. record: traj holds the rollout from the given start, and with record_unit
    traj_unit the unit response; the corrected trajectory is traj + start_shift traj_unit."""
    s = wp.tid() + offset
    c = cond[s]
    J = params[s, 0]
    KP = params[s, 1]
    KD = params[s, 2]
    KFF = params[s, 3]
    KAFF = params[s, 4]
    q = init[c, 0]
    v = init[c, 1]
    hq = wp.float64(0.0)
    hv = wp.float64(1.0)
    dd = wp.float64(0.0)
    dh = wp.float64(0.0)
    hh = wp.float64(0.0)
    if record != 0:
        traj[s, 0] = q
    if record_unit != 0:
        traj_unit[s, 0] = hq
    for k in range(n_steps):
        tau = KP * (q_des[c, k] - q) + KD * (qd_des[c, k] - v) + KFF * qd_des[c, k] + KAFF * qdd_des[c, k]
        q, v = _step(integrator, dt, J, tau, q, v)
        hq, hv = _step(integrator, dt, J, -KP * hq - KD * hv, hq, hv)
        d = q - q_ref[c, k + 1]
        dd += d * d
        dh += d * hq
        hh += hq * hq
        if record != 0:
            traj[s, k + 1] = q
        if record_unit != 0:
            traj_unit[s, k + 1] = hq
    shift = wp.float64(0.0)
    sq = dd  # a blown-up rollout keeps its inf here
    if fit_start[c] != 0:
        shift = -dh / hh
        if wp.isfinite(shift):
            sq = wp.max(dd + shift * (wp.float64(2.0) * dh + shift * hh), wp.float64(0.0))
        else:
            shift = wp.float64(0.0)
    start_shift[s] = shift
    err[s] = wp.sqrt(sq / wp.float64(n_steps)) / ref_scale[c]


# --- tape-safe variant: every step writes its own row, so wp.Tape can replay it backwards ---


@wp.func
def _tape_step(k: int, s: int, params: wp.array2d(dtype=wp.float64), cond: wp.array(dtype=int),
               q_des: wp.array2d(dtype=wp.float64), qd_des: wp.array2d(dtype=wp.float64),
               qdd_des: wp.array2d(dtype=wp.float64), integrator: int, dt: wp.float64,
               q: wp.array2d(dtype=wp.float64), v: wp.array2d(dtype=wp.float64)):
    """Step k of slot s: reads row k of q and v, writes row k + 1 (nothing carried in local variables)."""
    c = cond[s]
    tau = (params[s, 1] * (q_des[c, k] - q[k, s]) + params[s, 2] * (qd_des[c, k] - v[k, s])
           + params[s, 3] * qd_des[c, k] + params[s, 4] * qdd_des[c, k])
    qn, vn = _step(integrator, dt, params[s, 0], tau, q[k, s], v[k, s])
    q[k + 1, s] = qn
    v[k + 1, s] = vn


@wp.kernel
def rollout_steps_kernel(
    first: int,
    n_steps: int,
    params: wp.array2d(dtype=wp.float64),
    cond: wp.array(dtype=int),
    q_des: wp.array2d(dtype=wp.float64),
    qd_des: wp.array2d(dtype=wp.float64),
    qdd_des: wp.array2d(dtype=wp.float64),
    integrator: int,
    dt: wp.float64,
    q: wp.array2d(dtype=wp.float64),
    v: wp.array2d(dtype=wp.float64),
):
    """Steps first .. first + n_steps - 1 in one launch (a whole rollout: no host work per step). Its adjoint replays
    the loop backwards, step by step, each step from the rows it read, which are never overwritten: the same gradients
    as one launch per step (n_steps = 1), the form it is tested against."""
    s = wp.tid()
    for k in range(first, first + n_steps):
        _tape_step(k, s, params, cond, q_des, qd_des, qdd_des, integrator, dt, q, v)


@wp.kernel
def init_kernel(cond: wp.array(dtype=int), init: wp.array2d(dtype=wp.float64),
                q: wp.array2d(dtype=wp.float64), v: wp.array2d(dtype=wp.float64)):
    s = wp.tid()
    q[0, s] = init[cond[s], 0]
    v[0, s] = init[cond[s], 1]


@wp.kernel
def sq_error_kernel(q: wp.array2d(dtype=wp.float64), cond: wp.array(dtype=int), q_ref: wp.array2d(dtype=wp.float64),
                    acc: wp.array(dtype=wp.float64)):
    k, s = wp.tid()
    d = q[k + 1, s] - q_ref[cond[s], k + 1]
    wp.atomic_add(acc, s, d * d)


@wp.kernel
def rms_kernel(acc: wp.array(dtype=wp.float64), cond: wp.array(dtype=int), ref_scale: wp.array(dtype=wp.float64),
               n_steps: int, err: wp.array(dtype=wp.float64)):
    s = wp.tid()
    err[s] = wp.sqrt(acc[s] / wp.float64(n_steps)) / ref_scale[cond[s]]


def motion_scale(q_ref: np.ndarray, origin) -> np.ndarray:
    """The scale of each condition's error: the RMS of its q_ref (C, T+1) about its origin (C,), after the start."""
    q_ref = np.atleast_2d(np.asarray(q_ref, np.float64))
    origin = np.asarray(origin, np.float64).reshape(-1)
    return np.maximum(np.sqrt(np.mean((q_ref[:, 1:] - origin[:, None]) ** 2, axis=1)), 1e-12)


class PDCommands:
    """Commands and reference trajectories of C conditions, sampled at the simulator's steps."""

    def __init__(self, q_des, qd_des, qdd_des, q_ref, init, device: str, origin=None):
        # q_des, qd_des, qdd_des: (C, n_steps); q_ref: (C, n_steps + 1); init: (C, 2); origin: (C,) or None (0)
        self.n_cond, self.n_steps = q_des.shape
        self.device = device
        self.q_des = wp.array(q_des, dtype=wp.float64, device=device)
        self.qd_des = wp.array(qd_des, dtype=wp.float64, device=device)
        self.qdd_des = wp.array(qdd_des, dtype=wp.float64, device=device)
        self.q_ref = wp.array(q_ref, dtype=wp.float64, device=device)
        # the motion about each condition's origin: a log's own middle, so that an encoder's zero (a joint working
        # around 2 rad) does not shrink the relative error (it turned a friction log's "expand" into "absorbed");
        # the built-in commands move about q = 0, where this is the RMS of q itself
        origin = np.zeros(len(q_ref)) if origin is None else np.asarray(origin, np.float64)
        self.ref_scale = wp.array(motion_scale(q_ref, origin), dtype=wp.float64, device=device)
        self.init = wp.array(init, dtype=wp.float64, device=device)


def _slots(values: np.ndarray, n_cond: int):
    """Slot s = b * C + c: candidate b under condition c."""
    B = values.shape[0]
    return np.repeat(values, n_cond, axis=0), np.tile(np.arange(n_cond, dtype=np.int32), B)


def simulate(values: np.ndarray, cmds: PDCommands, integrator: int, dt: float, record: bool = False):
    """values (B, 5) -> errors (B, C) [normalised RMS of q - q_ref], and trajectories (B, C, T+1) if record."""
    errors, _, traj = simulate_start_fitted(values, cmds, np.zeros(cmds.n_cond, bool), integrator, dt, record)
    return errors, traj


def simulate_start_fitted(values: np.ndarray, cmds: PDCommands, fit_start, integrator: int, dt: float,
                          record: bool = False):
    """`simulate` with each condition's start velocity shifted to fit (where fit_start (C,) is true): errors (B, C)
    of the corrected rollouts, the shifts (B, C) in rad/s, and the corrected trajectories (B, C, T+1) if record. One
    rollout: the shifted start's response runs beside the logged one."""
    from wrenorm.kernels.launch import launch_sliced

    B, C, T = values.shape[0], cmds.n_cond, cmds.n_steps
    slot_params, cond = _slots(np.asarray(values, np.float64), C)
    S = B * C
    dev = cmds.device
    params = wp.array(slot_params, dtype=wp.float64, device=dev)
    cond_w = wp.array(cond, dtype=int, device=dev)
    fit_w = wp.array(np.asarray(fit_start, bool).astype(np.int32), dtype=int, device=dev)
    err = wp.zeros(S, dtype=wp.float64, device=dev)
    shift = wp.zeros(S, dtype=wp.float64, device=dev)
    record_unit = record and bool(np.any(fit_start))
    traj = wp.zeros((S, T + 1) if record else (1, 1), dtype=wp.float64, device=dev)
    unit = wp.zeros((S, T + 1) if record_unit else (1, 1), dtype=wp.float64, device=dev)

    def launch(offset, count):
        wp.launch(rollout, dim=count, device=dev, inputs=[
            params, cond_w, cmds.q_des, cmds.qd_des, cmds.qdd_des, cmds.q_ref, cmds.ref_scale, cmds.init, fit_w,
            int(integrator), wp.float64(dt), T, int(record), int(record_unit), offset, err, shift, traj, unit])

    launch_sliced(launch, S, dev)
    shifts = shift.numpy().reshape(B, C)
    if not record:
        return err.numpy().reshape(B, C), shifts, None
    corrected = traj.numpy().reshape(B, C, T + 1)
    if record_unit:
        with np.errstate(invalid="ignore", over="ignore"):  # a blown-up candidate's inf shift: NaN, judged upstream
            corrected = corrected + shifts[..., None] * unit.numpy().reshape(B, C, T + 1)
    return err.numpy().reshape(B, C), shifts, corrected


def simulate_with_grad(values: np.ndarray, cmds: PDCommands, integrator: int, dt: float, per_step: bool = False):
    """errors (B, C) and d errors / d params (B, C, P) through wp.Tape: the whole rollout in one launch (per_step:
    one launch per step, the reference it is tested against)."""
    B, C, T = values.shape[0], cmds.n_cond, cmds.n_steps
    slot_params, cond = _slots(np.asarray(values, np.float64), C)
    S = B * C
    dev = cmds.device
    params = wp.array(slot_params, dtype=wp.float64, device=dev, requires_grad=True)
    cond_w = wp.array(cond, dtype=int, device=dev)
    q = wp.zeros((T + 1, S), dtype=wp.float64, device=dev, requires_grad=True)
    v = wp.zeros((T + 1, S), dtype=wp.float64, device=dev, requires_grad=True)
    acc = wp.zeros(S, dtype=wp.float64, device=dev, requires_grad=True)
    err = wp.zeros(S, dtype=wp.float64, device=dev, requires_grad=True)
    tape = wp.Tape()
    with tape:
        wp.launch(init_kernel, dim=S, device=dev, inputs=[cond_w, cmds.init, q, v])
        rest = [params, cond_w, cmds.q_des, cmds.qd_des, cmds.qdd_des, int(integrator), wp.float64(dt), q, v]
        if per_step:
            for k in range(T):
                wp.launch(rollout_steps_kernel, dim=S, device=dev, inputs=[k, 1, *rest])
        else:
            wp.launch(rollout_steps_kernel, dim=S, device=dev, inputs=[0, T, *rest])
        wp.launch(sq_error_kernel, dim=(T, S), device=dev, inputs=[q, cond_w, cmds.q_ref, acc])
        wp.launch(rms_kernel, dim=S, device=dev, inputs=[acc, cond_w, cmds.ref_scale, T, err])
    tape.backward(grads={err: wp.ones(S, dtype=wp.float64, device=dev)})
    grads = params.grad.numpy().reshape(B, C, values.shape[1]).copy()  # numpy() aliases CPU memory
    errors = err.numpy().reshape(B, C).copy()
    tape.zero()
    return errors, grads
