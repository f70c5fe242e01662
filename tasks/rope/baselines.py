"""numpy and torch implementations of the coarse rope step of kernels/rope.py, vectorised over chains.

They are a peer implementation for the cross-check test and the baselines in the benchmark.
Same arithmetic order as the Warp kernel (Gauss-Seidel along the chain), float32, all pairs
tested every frame (no culling), chains frozen after their first hit or blow-up.
"""
from __future__ import annotations

import numpy as np

from wrenorm.kernels.rope import GRAVITY, VMAX, ChainParams, RolloutResult


class _Np:
    name = "numpy"

    def asarray(self, a):
        return np.asarray(a, dtype=np.float32)

    sqrt = staticmethod(np.sqrt)
    stack = staticmethod(np.stack)
    where = staticmethod(np.where)

    @staticmethod
    def clip(a, lo, hi):
        return np.clip(a, lo, hi)

    @staticmethod
    def numpy(a):
        return np.asarray(a)

    @staticmethod
    def copy(a):
        return a.copy()


class _Torch:
    name = "torch"

    def __init__(self):
        import torch
        self.t = torch

    def asarray(self, a):
        return self.t.as_tensor(np.array(a, dtype=np.float32, copy=True))

    def sqrt(self, a):
        return self.t.sqrt(a)

    def stack(self, a, axis):
        return self.t.stack(a, axis)

    def where(self, c, a, b):
        t = self.t
        a = a if isinstance(a, t.Tensor) else t.tensor(a, dtype=t.float32)
        b = b if isinstance(b, t.Tensor) else t.tensor(b, dtype=t.float32)
        return t.where(c, a, b)

    def clip(self, a, lo, hi):
        return self.t.clamp(a, lo, hi)

    @staticmethod
    def numpy(a):
        return a.numpy()

    @staticmethod
    def copy(a):
        return a.clone()


def _dot(a, b):
    return (a * b).sum(-1)


def seg_closest(xp, p1, q1, p2, q2):
    """Vectorised Ericson closest points; (dist, s, t) with the kernel's branch order."""
    eps = 1.0e-12
    d1, d2, r = q1 - p1, q2 - p2, p1 - p2
    a, e, f = _dot(d1, d1), _dot(d2, d2), _dot(d2, r)
    c = _dot(d1, r)
    bb = _dot(d1, d2)
    a_safe = xp.where(a > eps, a, 1.0)
    e_safe = xp.where(e > eps, e, 1.0)
    denom = a * e - bb * bb
    s_gen = xp.where(denom > 1.0e-10 * a * e, xp.clip((bb * f - c * e) / xp.where(denom > 0, denom, 1.0), 0.0, 1.0),
                     0.0 * a)
    t_gen = (bb * s_gen + f) / e_safe
    s_lo = xp.clip(-c / a_safe, 0.0, 1.0)
    s_hi = xp.clip((bb - c) / a_safe, 0.0, 1.0)
    s_g = xp.where(t_gen < 0.0, s_lo, xp.where(t_gen > 1.0, s_hi, s_gen))
    t_g = xp.clip(t_gen, 0.0, 1.0)
    # degenerate segments
    s = xp.where(a <= eps, 0.0 * a, xp.where(e <= eps, s_lo, s_g))
    t = xp.where(a <= eps, xp.where(e <= eps, 0.0 * a, xp.clip(f / e_safe, 0.0, 1.0)), xp.where(e <= eps, 0.0 * a, t_g))
    c1 = p1 + d1 * s[..., None]
    c2 = p2 + d2 * t[..., None]
    return xp.sqrt(_dot(c1 - c2, c1 - c2)), s, t


def rollout(backend: str, *args, **kwargs) -> RolloutResult:
    """The same step vectorised over the batch in numpy or torch (CPU)."""
    if backend != "torch":
        return _rollout(backend, *args, **kwargs)
    import torch

    # Thousands of small ops per step: torch's intra-op threads only spin against each other
    # (measured on the loaded 2-core machine: 212 chain-steps/s with 2 threads, 8600 with 1).
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        return _rollout(backend, *args, **kwargs)
    finally:
        torch.set_num_threads(threads)


def _rollout(backend: str, pos0, vel0, hand, path_index, params: ChainParams, n: int, link: float, dt: float,
             iterations: int = 4, margin: float | None = None, steps: int = 1, stop_at_hit: bool = True,
             gravity=GRAVITY, t0: float = 0.0, min_sep: int = 2) -> RolloutResult:
    xp = _Np() if backend == "numpy" else _Torch()
    B = params.batch
    margin = float(0.25 * link if margin is None else margin)
    pos = xp.asarray(np.broadcast_to(pos0, (B, n, 3)).copy())
    vel = xp.asarray(np.broadcast_to(vel0, (B, n, 3)).copy())
    handv = xp.asarray(np.asarray(hand)[np.broadcast_to(path_index, (B,))])  # (B, S, 3)
    g = xp.asarray(np.array(gravity, np.float32))
    P = {f: xp.asarray(getattr(params, f)) for f in ChainParams.FIELDS}
    w = 1.0 / P["node_mass"]
    k = xp.where(P["bend_k"] > 1e-12, P["bend_k"], 1e-12)
    alpha_t = (link * link / (k * dt * dt))[:, None]
    gamma = (P["bend_b"] / (k * dt))[:, None]
    two_r = 2.0 * P["radius"]
    zero = 0.0 * w
    node_m = params.node_masses(n).astype(np.float32)
    masses = [None] + [xp.asarray(np.ascontiguousarray(node_m[:, i])) for i in range(1, n)]
    lengths = [None] + [link] * (n - 2) + [0.5 * link]
    W = xp.stack([zero] + [1.0 / mi for mi in masses[1:]], 1)  # (B, N) inverse masses, hand node 0
    pairs = [(a, j) for a in range(n - 1) for j in range(a + max(2, min_sep), n - 1)]
    ia = np.array([p[0] for p in pairs], np.int64)
    ib = np.array([p[1] for p in pairs], np.int64)

    status = np.zeros(B, np.int32)
    hit_frame = np.full(B, -1, np.int32)
    hit_alpha = np.zeros(B, np.float32)
    hit_s = np.zeros((B, 2), np.float32)
    crit_pos = np.zeros((B, n, 3), np.float32)
    crit_vel = np.zeros((B, n, 3), np.float32)
    clearance = np.full(B, margin, np.float32)
    for step in range(steps):
        prev = xp.copy(pos)
        x = xp.copy(pos)
        x[:, 0] = handv[:, step + 1]
        for i in range(1, n):
            vi = vel[:, i]
            speed = xp.sqrt(_dot(vi, vi))
            c = (P["drag_lin"] + P["drag_quad"] * speed) * lengths[i]
            vi = (vi + dt * g) / (1.0 + dt * c / masses[i])[:, None]
            x[:, i] = prev[:, i] + dt * vi
        lam = 0.0 * x
        lam_l = 0.0 * x[..., 0]
        at_s = (P["stretch"] / (dt * dt))[:, None, None]
        for _ in range(iterations):
            for colour in range(3):
                i = np.arange(1 + colour, n - 1, 3)
                if i.size == 0:
                    continue
                w0, w1, w2 = W[:, i - 1, None], W[:, i, None], W[:, i + 1, None]
                x0, x1, x2 = x[:, i - 1], x[:, i], x[:, i + 1]
                cv = x0 - 2.0 * x1 + x2
                dcv = cv - (prev[:, i - 1] - 2.0 * prev[:, i] + prev[:, i + 1])
                dlam = (-cv - alpha_t[:, None] * lam[:, i] - gamma[:, None] * dcv) / (
                    (1.0 + gamma[:, None]) * (w0 + 4.0 * w1 + w2) + alpha_t[:, None])
                lam[:, i] = lam[:, i] + dlam
                x[:, i - 1] = x0 + w0 * dlam
                x[:, i] = x1 - (2.0 * w1) * dlam
                x[:, i + 1] = x2 + w2 * dlam
            for parity in range(2):
                i = np.arange(parity, n - 1, 2)
                wa, wb = W[:, i, None], W[:, i + 1, None]
                xa, xb = x[:, i], x[:, i + 1]
                d = xb - xa
                ln = xp.sqrt(_dot(d, d))[..., None]
                den = wa + wb + at_s
                e = ln - link + at_s * lam_l[:, i, None]
                ok = ln > 1e-9
                corr = xp.where(ok, d * (e / xp.where(ok, ln, 1.0)), 0.0 * d)
                lam_l[:, i] = xp.where(ok, lam_l[:, i, None] - e / den, lam_l[:, i, None])[..., 0]
                x[:, i] = xa + (wa / den) * corr
                x[:, i + 1] = xb - (wb / den) * corr
        v = (x - prev) / dt
        active = (status == 0) | ((status == 1) & (not stop_at_hit))
        vv = xp.numpy(_dot(v, v)).sum(axis=1)
        blown = active & ~(vv < VMAX * VMAX)
        status[blown] = 2
        active &= ~blown
        # collisions on the new state (all pairs)
        pa, pb, qa, qb = x[:, ia], x[:, ia + 1], x[:, ib], x[:, ib + 1]
        dist, _, _ = seg_closest(xp, pa, pb, qa, qb)
        gap = xp.numpy(dist - two_r[:, None])
        mid_a, mid_b = 0.5 * (pa + pb), 0.5 * (qa + qb)
        ha = 0.5 * xp.sqrt(_dot(pb - pa, pb - pa))
        hb = 0.5 * xp.sqrt(_dot(qb - qa, qb - qa))
        reach = xp.numpy((ha + hb + two_r[:, None] + margin) * 1.00001 + 1.0e-6)
        dm = xp.numpy(_dot(mid_a - mid_b, mid_a - mid_b))
        far = dm > reach * reach
        contrib = np.where(far, margin, np.minimum(gap, margin)).min(axis=1)
        clearance = np.where(active, np.minimum(clearance, contrib), clearance).astype(np.float32)
        new_hit = active & (status == 0) & (gap <= 0).any(axis=1)
        if new_hit.any():
            d0, _, _ = seg_closest(xp, prev[:, ia], prev[:, ia + 1], prev[:, ib], prev[:, ib + 1])
            g0 = xp.numpy(d0 - two_r[:, None])
            with np.errstate(divide="ignore", invalid="ignore"):
                al = np.where(g0 > 0, g0 / (g0 - gap), 0.0).astype(np.float32)
            al = np.where(gap <= 0, al, 2.0)
            which = np.argmin(al, axis=1)
            xn, pn, vn, vb = xp.numpy(x), xp.numpy(prev), xp.numpy(v), xp.numpy(vel)
            for bi in np.nonzero(new_hit)[0]:
                p = which[bi]
                a_, b_ = ia[p], ib[p]
                alpha = np.float32(al[bi, p])
                cp = pn[bi] + alpha * (xn[bi] - pn[bi])
                _, s, t = seg_closest(_Np(), xn[bi, a_], xn[bi, a_ + 1], xn[bi, b_], xn[bi, b_ + 1])
                status[bi], hit_frame[bi], hit_alpha[bi] = 1, step + 1, alpha
                hit_s[bi] = ((a_ + float(s)) / (n - 1), (b_ + float(t)) / (n - 1))
                # the velocity at the crossing, from the step's mean and the step before's (model.hit_velocity)
                c = np.float32(2.0) * alpha - np.float32(1.0) if step == 0 else alpha - np.float32(0.5)
                crit_pos[bi], crit_vel[bi] = cp, vn[bi] + c * (vn[bi] - vb[bi])
        keep = xp.asarray(active.astype(np.float32))[:, None, None] > 0
        pos = xp.where(keep, x, pos)
        vel = xp.where(keep, v, vel)
    hit = status == 1
    return RolloutResult(
        status=status, hit_frame=hit_frame, hit_alpha=hit_alpha,
        hit_time=np.where(hit, t0 + (hit_frame - 1 + hit_alpha.astype(np.float64)) * dt, np.nan),
        s_a=np.where(hit, hit_s[:, 0], np.nan), s_b=np.where(hit, hit_s[:, 1], np.nan),
        crit_pos=crit_pos, crit_vel=crit_vel, clearance=clearance,
        final_pos=xp.numpy(pos), final_vel=xp.numpy(vel))
