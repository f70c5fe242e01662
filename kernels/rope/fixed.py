"""Fixed-size variant of `rope.rollout_kernel`: one kernel per chain size.

Same model, same operation order, same arguments as the generic kernel (kernels/rope.py), and
bit-identical results (tests/test_rope_kernel.py compares it with the generic kernel testing
every pair). What differs is how the CPU executes it:
  - the chain state lives in kernel-local fixed-size matrices for a whole launch instead of
    global arrays; only the final state goes back to memory;
  - the node count is a compile-time constant, so each constraint pass unrolls into
    straight-line code (colour loops with constant bounds, end-node branches folded) and the
    per-node inverse masses and constraint denominators are computed once per launch, not per
    constraint. The pass count and the pair loops stay rolled: unrolling them made the N = 16
    kernel take 50 s to compile for no further gain;
  - culling (all of it exact: a skipped pair is one the pair test would call far):
    chains of up to TEMPORAL_MAX_NODES nodes cull in time: per pair of blocks of BLOCK segments,
    the smallest gap at the last test minus a bound on the relative motion since then (see the
    comment in the kernel); a block pair is tested again only once that bound could fall to
    min(clearance, margin). Most steps test a few block pairs near each other, not all pairs.
    Longer chains cull in space: block spheres first (temporal culling measured 9 % slower at
    N = 32 and 3 % at N = 24). Then the segment spheres, then the exact segment distance.
Measured CPU time per chain-step on one core of this machine (swung ropes, 4 passes, process
time): N = 16: generic kernel 1.15-1.23 us, this one 0.94 us with spatial culling and 0.83 us with
temporal culling; N = 8: 0.45 -> 0.37 us. Collision bookkeeping is about 0.1 us of that.

Each kernel is its own Warp module ("unique"), so building the kernel for a new chain size
never forces the others to recompile.

On the CPU, chains of up to TEMPORAL_MAX_NODES nodes run in kernels/rope_lanes.py instead (16
chains per thread in vector lanes; its per-lane collision test is this kernel's temporal path,
kept in step with it by the same bit-identity tests). This kernel serves CUDA (one chain per
thread) and longer chains.
"""
from __future__ import annotations

import warp as wp

from wrenorm.kernels.rope.model import node_w, seg_closest

_OPTIONS = {"enable_backward": False, "optimization_level": 3, "cpu_compiler_flags": "-march=native",
            "max_unroll": 64}
_CACHE: dict = {}
TEMPORAL_MAX_NODES = 20  # temporal culling above; spatial block culling for longer chains (N = 32: 9 % faster)
BLOCK = 4  # segments per culling block (N = 32: 10 % faster than no blocks; N = 16: even)
MAX_NODES = 64  # beyond this the unrolled code is large; RopeSim falls back to the generic kernel


def fast_kernel(n: int):
    if int(n) not in _CACHE:
        _CACHE[int(n)] = _build(int(n))
    return _CACHE[int(n)]


def _build(n: int):
    N = n
    NM1 = n - 1  # links / segments
    LAST = n - 1
    BEND_ORDER = [i for c in range(3) for i in range(1 + c, n - 1, 3)]
    LINK_ORDER = [i for p in range(2) for i in range(p, n - 1, 2)]
    NBEND = len(BEND_ORDER)
    NLINK = len(LINK_ORDER)
    Mat = wp.types.matrix(shape=(n, 3), dtype=wp.float32)
    Seg = wp.types.matrix(shape=(n, 4), dtype=wp.float32)
    Vec = wp.types.vector(length=n, dtype=wp.float32)
    BS = BLOCK
    NB = (n - 1 + BLOCK - 1) // BLOCK
    BVec = wp.types.vector(length=NB, dtype=wp.float32)
    Blk = wp.types.matrix(shape=(NB, 4), dtype=wp.float32)
    TEMPORAL = n <= TEMPORAL_MAX_NODES
    BLO = [blk * BS for blk in range(NB)]  # nodes of block blk's segments: BLO .. BHI - 1
    BHI = [min(blk * BS + BS, n - 1) + 1 for blk in range(NB)]
    BMat = wp.types.matrix(shape=(NB, 3), dtype=wp.float32)
    Flags = wp.types.matrix(shape=(NB, NB), dtype=wp.float32)

    @wp.kernel(module="unique", module_options=_OPTIONS)
    def rollout_fixed(
        pos: wp.array2d(dtype=wp.vec3),
        vel: wp.array2d(dtype=wp.vec3),
        prev: wp.array2d(dtype=wp.vec3),
        lam: wp.array2d(dtype=wp.vec3),
        lam_link: wp.array2d(dtype=float),
        seg: wp.array2d(dtype=wp.vec4),
        hand: wp.array2d(dtype=wp.vec3),
        path_index: wp.array(dtype=wp.int32),
        node_mass: wp.array(dtype=float),
        lead_mass: wp.array(dtype=float),
        bend_k: wp.array(dtype=float),
        bend_b: wp.array(dtype=float),
        drag_lin: wp.array(dtype=float),
        drag_quad: wp.array(dtype=float),
        radius: wp.array(dtype=float),
        mass_slope: wp.array(dtype=float),
        stretch: wp.array(dtype=float),
        n: int,
        min_sep: int,
        link: float,
        dt: float,
        gravity: wp.vec3,
        iters: int,
        cull: int,
        margin: float,
        vmax: float,
        step0: int,
        nsteps: int,
        stop_at_hit: int,
        status: wp.array(dtype=wp.int32),
        hit_frame: wp.array(dtype=wp.int32),
        hit_alpha: wp.array(dtype=float),
        hit_s: wp.array(dtype=wp.vec2),
        crit_pos: wp.array2d(dtype=wp.vec3),
        crit_vel: wp.array2d(dtype=wp.vec3),
        clearance: wp.array(dtype=float),
        offset: int,
    ):
        b = wp.tid() + offset
        st = status[b]
        if st == 2:
            return
        if st == 1 and stop_at_hit != 0:
            return
        path = path_index[b]
        m = node_mass[b]
        ml = lead_mass[b]
        slope = mass_slope[b]
        k = wp.max(bend_k[b], 1.0e-12)
        alpha_t = link * link / (k * dt * dt)
        gamma = bend_b[b] / (k * dt)
        # per-node inverse masses and the constraint factors built from them, once per launch
        W = Vec()
        for i in range(N):
            W[i] = node_w(i, N, m, ml, slope)
        IB = Vec()  # bending: 1 / ((1 + gamma)(w0 + 4 w1 + w2) + alpha~), by centre node
        for i in range(1, NM1):
            IB[i] = 1.0 / ((1.0 + gamma) * (W[i - 1] + 4.0 * W[i] + W[i + 1]) + alpha_t)
        at_s = stretch[b] / (dt * dt)
        FA = Vec()  # links: mass-weighted split of the correction, by first node
        FB = Vec()
        GL = Vec()  # wa + wb + alpha~, for the link multipliers
        for i in range(NM1):
            den = W[i] + W[i + 1] + at_s
            FA[i] = W[i] / den
            FB[i] = W[i + 1] / den
            GL[i] = den
        LL = Vec()  # link multipliers
        dl = drag_lin[b]
        dq = drag_quad[b]
        r = radius[b]
        two_r = 2.0 * r
        cl = clearance[b]
        vmax2 = vmax * vmax
        inv_dt = 1.0 / dt
        nm1 = n - 1  # runtime bounds keep the pair loops rolled (code size, compile time)
        npair_a = nm1 - min_sep
        P = Mat()
        V = Mat()
        Q = Mat()  # positions at the start of the step
        L = Mat()  # bending multipliers (row i: centre node i)
        CQ = Mat()
        S = Seg()  # bounding spheres: midpoint, half length
        CB = Blk()  # block spheres (spatial culling)
        FAR = Flags()  # block pairs skipped this step
        KB = Flags()  # see the temporal culling below
        MB = Flags()
        for ba in range(NB):
            for bb in range(NB):
                KB[ba, bb] = -1.0e30  # every block pair is tested in the first step of a launch
        CP = Flags()
        UB = BMat()
        DB = BVec()
        NEED = BVec()
        G = float(0.0)
        tol_link = 2.0e-3 * link + 1.0e-5
        chain_len = float(N) * link
        for i in range(N):
            P[i] = pos[b, i]
            V[i] = vel[b, i]
        for step in range(step0, step0 + nsteps):
            Q[0] = P[0]
            P[0] = hand[path, step + 1]
            for i in range(1, N):
                xi = P[i]
                vi = V[i]
                Q[i] = xi
                wi = W[i]
                li = link
                if i == LAST:
                    li = 0.5 * link
                c = (dl + dq * wp.length(vi)) * li
                vi = (vi + dt * gravity) * (1.0 / (1.0 + dt * c * wi))
                P[i] = xi + dt * vi
                L[i] = wp.vec3(0.0)
                LL[i - 1] = 0.0
            # curvature at the start of the step, for the bending damping (the same every pass)
            for i in range(1, NM1):
                CQ[i] = Q[i - 1] - 2.0 * Q[i] + Q[i + 1]
            for it in range(iters):
                # bending in three colours (centre i mod 3), then links in two (even, odd): the
                # generic kernel's order, unrolled; within a colour nothing shares a node
                for kk in range(NBEND):
                    x0 = P[wp.static(BEND_ORDER[kk] - 1)]
                    x1 = P[wp.static(BEND_ORDER[kk])]
                    x2 = P[wp.static(BEND_ORDER[kk] + 1)]
                    cv = x0 - 2.0 * x1 + x2
                    dcv = cv - CQ[wp.static(BEND_ORDER[kk])]
                    lm = L[wp.static(BEND_ORDER[kk])]
                    dlam = (-cv - alpha_t * lm - gamma * dcv) * IB[wp.static(BEND_ORDER[kk])]
                    L[wp.static(BEND_ORDER[kk])] = lm + dlam
                    P[wp.static(BEND_ORDER[kk] - 1)] = x0 + W[wp.static(BEND_ORDER[kk] - 1)] * dlam
                    P[wp.static(BEND_ORDER[kk])] = x1 - (2.0 * W[wp.static(BEND_ORDER[kk])]) * dlam
                    P[wp.static(BEND_ORDER[kk] + 1)] = x2 + W[wp.static(BEND_ORDER[kk] + 1)] * dlam
                for kk in range(NLINK):
                    xa = P[wp.static(LINK_ORDER[kk])]
                    xb = P[wp.static(LINK_ORDER[kk] + 1)]
                    d = xb - xa
                    ln = wp.length(d)
                    ll = LL[wp.static(LINK_ORDER[kk])]
                    e = ln - link + at_s * ll
                    corr = wp.vec3(0.0)
                    if ln > 1.0e-9:
                        corr = d * (e / ln)
                        LL[wp.static(LINK_ORDER[kk])] = ll - e / GL[wp.static(LINK_ORDER[kk])]
                    P[wp.static(LINK_ORDER[kk])] = xa + FA[wp.static(LINK_ORDER[kk])] * corr
                    P[wp.static(LINK_ORDER[kk] + 1)] = xb - FB[wp.static(LINK_ORDER[kk])] * corr
            vv = float(0.0)
            for i in range(N):
                v = (P[i] - Q[i]) * inv_dt
                V[i] = v
                vv = vv + wp.dot(v, v)
            if not (vv < vmax2):
                st = 2
                status[b] = 2
                clearance[b] = cl
                for i in range(N):
                    pos[b, i] = P[i]
                    vel[b, i] = V[i]
                return
            any_t = int(1)
            if wp.static(TEMPORAL):
                # Temporal culling by blocks of BS consecutive segments. The distance between two
                # segments changes by at most the largest endpoint displacement of each, and not at all
                # under a common translation. With u_A the mean displacement of block A's nodes in this
                # step, D_A = max over its nodes of |dx_i - u_A|_1 (>= the Euclidean norm), a gap
                # between blocks A and B changes by at most D_A + D_B + |u_A - u_B|_1 (translating by
                # u_A); CP[A, B] sums that bound over the steps of this launch (x 1.001 and an ulp-sized
                # term per step to dominate rounding). KB[A, B] = (lower bound on every gap of the block
                # pair when it was last tested) + CP[A, B] then, so every gap is >= KB - CP now. A
                # block pair whose bound exceeds thr = min(cl, margin) (and 0 before the first hit) by
                # a rounding tolerance holds no pair that could change cl or be a hit: skipping it is
                # what the pair test does for far pairs. Block-local u keeps the bound for nearby
                # segments (the small gaps) at their relative motion, not the swing's.
                scale = wp.length(P[0]) + chain_len
                if cull != 0:  # all pairs are tested otherwise: no bounds needed
                    for blk in range(NB):
                        su = wp.vec3(0.0)
                        for i in range(wp.static(BLO[blk]), wp.static(BHI[blk])):
                            su = su + (P[i] - Q[i])
                        u = su * wp.static(1.0 / float(BHI[blk] - BLO[blk]))
                        dB = float(0.0)
                        for i in range(wp.static(BLO[blk]), wp.static(BHI[blk])):
                            dr = P[i] - Q[i] - u
                            dB = wp.max(dB, wp.abs(dr[0]) + wp.abs(dr[1]) + wp.abs(dr[2]))
                        UB[blk] = u
                        DB[blk] = dB
                    gmx = float(0.0)
                    for ba in range(NB):
                        for bb in range(ba, NB):
                            du = UB[ba] - UB[bb]
                            inc = (DB[ba] + DB[bb] + wp.abs(du[0]) + wp.abs(du[1]) + wp.abs(du[2])) * 1.001 + 1.0e-6 * scale
                            CP[ba, bb] = CP[ba, bb] + inc
                            gmx = wp.max(gmx, inc)
                    G = G + gmx  # >= the growth of every CP
                thr = wp.min(cl, margin)
                if st == 0:
                    thr = wp.max(thr, 0.0)
                # rounding of seg_closest (~ulps of the link and of the coordinates) and of the sums
                lim = thr + tol_link + 4.0e-6 * scale + 4.0e-6 * G
                any_t = int(0)
                for ba in range(NB):
                    for bb in range(ba, NB):
                        FAR[ba, bb] = 0.0
                        if cull != 0 and KB[ba, bb] - CP[ba, bb] > lim:
                            FAR[ba, bb] = 1.0
                        else:
                            any_t = 1
                            MB[ba, bb] = 1.0e30
                            NEED[ba] = 1.0
                            NEED[bb] = 1.0
                for blk in range(NB):  # segment spheres, of the blocks with a pair to test
                    if NEED[blk] > 0.5:
                        NEED[blk] = 0.0
                        for a in range(wp.static(BLO[blk]), wp.static(BHI[blk] - 1)):
                            pa = P[a]
                            pb = P[a + 1]
                            mid = 0.5 * (pa + pb)
                            S[a] = wp.vec4(mid[0], mid[1], mid[2], 0.5 * wp.length(pb - pa))
            else:
                for a in range(nm1):
                    pa = P[a]
                    pb = P[a + 1]
                    mid = 0.5 * (pa + pb)
                    S[a] = wp.vec4(mid[0], mid[1], mid[2], 0.5 * wp.length(pb - pa))
                # Blocks of BS consecutive segments, each in a sphere holding its segments' spheres
                # (inflated so rounding cannot matter). A block pair farther apart than the sum of
                # radii + 2r + margin (with more slack than the pair test's) holds only pairs the
                # pair test would call far, so skipping it leaves every result unchanged.
                for blk in range(NB):
                    cen = wp.vec3(0.0)
                    cnt = float(0.0)
                    for a in range(blk * BS, wp.min(blk * BS + BS, nm1)):
                        cen = cen + wp.vec3(S[a][0], S[a][1], S[a][2])
                        cnt = cnt + 1.0
                    cen = cen / cnt
                    rad = float(0.0)
                    for a in range(blk * BS, wp.min(blk * BS + BS, nm1)):
                        rad = wp.max(rad, wp.length(wp.vec3(S[a][0], S[a][1], S[a][2]) - cen) + S[a][3])
                    CB[blk] = wp.vec4(cen[0], cen[1], cen[2], rad * 1.00001 + 1.0e-6)
                for ba in range(NB):
                    for bb in range(ba, NB):
                        d = wp.vec3(CB[ba][0] - CB[bb][0], CB[ba][1] - CB[bb][1], CB[ba][2] - CB[bb][2])
                        reach_b = (CB[ba][3] + CB[bb][3] + two_r + margin) * 1.0001 + 1.0e-5
                        FAR[ba, bb] = 0.0
                        if cull != 0 and wp.dot(d, d) > reach_b * reach_b:
                            FAR[ba, bb] = 1.0
            best = float(2.0)
            best_a = int(-1)
            best_b = int(-1)
            # each far pair sets cl = min(cl, margin) and every tested pair leaves cl below that, so
            # with culling the far pairs' share is applied once per step (no loop-carried select)
            if cull != 0 and npair_a > 0 and margin < cl:
                cl = margin
            for a in range(npair_a * any_t):
                sa = S[a]
                blk_a = a // BS
                j_first = a + min_sep
                for blk in range(j_first // BS, NB):
                    if FAR[blk_a, blk] > 0.5:
                        continue
                    for j in range(wp.max(j_first, blk * BS), wp.min(blk * BS + BS, nm1)):
                        sb = S[j]
                        dx = sa[0] - sb[0]
                        dy = sa[1] - sb[1]
                        dz = sa[2] - sb[2]
                        reach = (sa[3] + sb[3] + two_r + margin) * 1.00001 + 1.0e-6
                        far = dx * dx + dy * dy + dz * dz > reach * reach
                        if cull == 0 or not far:
                            res = seg_closest(P[a], P[a + 1], P[j], P[j + 1])
                            gap = res[0] - two_r
                            if wp.static(TEMPORAL):
                                MB[blk_a, blk] = wp.min(MB[blk_a, blk], gap)
                            if not far:
                                cl = wp.min(cl, wp.min(gap, margin))
                            if gap <= 0.0 and st == 0:
                                r0 = seg_closest(Q[a], Q[a + 1], Q[j], Q[j + 1])
                                g0 = r0[0] - two_r
                                al = float(0.0)
                                if g0 > 0.0:
                                    al = g0 / (g0 - gap)
                                if al < best:
                                    best = al
                                    best_a = a
                                    best_b = j
                        elif wp.static(TEMPORAL):  # each segment lies in its sphere
                            MB[blk_a, blk] = wp.min(MB[blk_a, blk], wp.sqrt(dx * dx + dy * dy + dz * dz) - sa[3] - sb[3] - two_r)
            if wp.static(TEMPORAL):
                for ba in range(NB):
                    for bb in range(ba, NB):
                        if FAR[ba, bb] < 0.5:
                            KB[ba, bb] = MB[ba, bb] + CP[ba, bb]
            if best_a >= 0:
                st = 1
                status[b] = 1
                hit_frame[b] = step + 1
                hit_alpha[b] = best
                for i in range(N):
                    p0 = Q[i]
                    crit_pos[b, i] = p0 + best * (P[i] - p0)
                    crit_vel[b, i] = V[i]
                res = seg_closest(P[best_a], P[best_a + 1], P[best_b], P[best_b + 1])
                hit_s[b] = wp.vec2((float(best_a) + res[1]) / float(NM1), (float(best_b) + res[2]) / float(NM1))
                if stop_at_hit != 0:
                    clearance[b] = cl
                    for i in range(N):
                        pos[b, i] = P[i]
                        vel[b, i] = V[i]
                    return
        clearance[b] = cl
        for i in range(N):
            pos[b, i] = P[i]
            vel[b, i] = V[i]

    return rollout_fixed
