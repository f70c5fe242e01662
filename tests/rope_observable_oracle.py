"""The rope observable in plain numpy, as it was before it moved into Warp kernels (kernels/rope/critical.py):
the test oracle the kernels must equal within float tolerance. Not used by the package."""
import numpy as np

from wrenorm.tasks.rope.observable import NO_HIT, NO_HIT_SCALE, SAMPLES, CriticalStates, resample


def from_rollout(res, n_nodes: int, t0: float = 0.0) -> CriticalStates:
    s_nodes = np.linspace(0.0, 1.0, n_nodes)
    s_k = np.linspace(0.0, 1.0, SAMPLES)
    hit = res.status == 1
    mask = np.where(hit, 1.0, np.nan)[:, None, None]
    clearance = np.where(res.status == 2, np.inf, res.clearance.astype(np.float64))
    return CriticalStates(resample(res.crit_pos, s_nodes, s_k) * mask, resample(res.crit_vel, s_nodes, s_k) * mask,
                          np.where(hit, res.hit_time - t0, np.nan), np.stack([res.s_a, res.s_b], 1),
                          hit, np.where(hit, 0.0, clearance))


def no_hit_cost(clearance, length: float) -> np.ndarray:
    c = np.nan_to_num(np.asarray(clearance, np.float64), nan=np.inf)
    return NO_HIT + np.minimum(np.maximum(c, 0.0), NO_HIT_SCALE * length) / (NO_HIT_SCALE * length)


def residual(target, st: CriticalStates) -> np.ndarray:
    g, w, K = target.state, target.weights, SAMPLES
    B = st.batch
    return np.concatenate([
        (w["shape"] / (target.length * np.sqrt(K))) * (st.pos - g.pos).reshape(B, -1),
        (w["velocity"] / (target.speed * np.sqrt(K))) * (st.vel - g.vel).reshape(B, -1),
        (w["time"] / g.time[0]) * (st.time - g.time)[:, None],
        (0.5 * w["place"]) * (st.s - g.s),
    ], axis=1)


def terms(target, st: CriticalStates) -> dict:
    g, w = target.state, target.weights
    rms = lambda d: np.sqrt(np.mean(np.sum(d ** 2, -1), -1))  # noqa: E731
    with np.errstate(invalid="ignore"):
        t = {
            "shape": rms(st.pos - g.pos) / target.length,
            "velocity": rms(st.vel - g.vel) / target.speed,
            "time": np.abs(st.time - g.time) / g.time[0],
            "place": 0.5 * np.abs(st.s - g.s).sum(-1),
        }
        total = sum(w[k] * t[k] for k in t)
    t["total"] = np.where(st.hit, total, no_hit_cost(st.clearance, target.length))
    return t


def state_error(target, pos, vel, time: float) -> float:
    rms = lambda d: float(np.sqrt(np.mean(np.sum(d ** 2, -1))))  # noqa: E731
    g, w = target.state, target.weights
    return (w["shape"] * rms(pos - g.pos[0]) / target.length + w["velocity"] * rms(vel - g.vel[0]) / target.speed
            + w["time"] * abs(time - g.time[0]) / g.time[0])
