"""The culled self-collision test of the fixed-size kernels (fixed.py, one chain per thread, and lanes.py,
one chain per vector lane): one function per chain size, shared by both, so they test pairs identically.

Culling, all of it exact (a skipped pair is one the pair test would call far): chains of up to
TEMPORAL_MAX_NODES nodes cull in time: per pair of blocks of BLOCK segments, the smallest gap at the last
test minus a bound on the relative motion since then; a block pair is tested again only once that bound
could fall to min(clearance, margin). Most steps test a few block pairs near each other, not all pairs.
Longer chains cull in space: block spheres first (temporal culling measured 9 % slower at N = 32 and 3 % at
N = 24), then the segment spheres, then the exact segment distance.

Temporal bound. The distance between two segments changes by at most the largest endpoint displacement of
each, and not at all under a common translation. With u_A the mean displacement of block A's nodes in this
step, D_A = max over its nodes of |dx_i - u_A|_1 (>= the Euclidean norm), a gap between blocks A and B changes
by at most D_A + D_B + |u_A - u_B|_1 (translating by u_A); CP[A, B] sums that bound over the steps of this
launch (x 1.001 and an ulp-sized term per step to dominate rounding). KB[A, B] = (lower bound on every gap of
the block pair when it was last tested) + CP[A, B] then, so every gap is >= KB - CP now. A block pair whose
bound exceeds thr = min(cl, margin) (and 0 before the first hit) by a rounding tolerance holds no pair that
could change cl or be a hit: skipping it is what the pair test does for far pairs. Block-local u keeps the
bound for nearby segments (the small gaps) at their relative motion, not the swing's.
"""
# no `from __future__ import annotations`: the per-size types in collide()'s annotations must be objects
import warp as wp

from wrenorm.kernels.rope.model import ChainState, first_contact, frames_from, seg_closest, spheres_apart

TEMPORAL_MAX_NODES = 20  # temporal culling up to here; spatial block culling for longer chains (N = 32: 9 % faster)
BLOCK = 4  # segments per culling block (N = 32: 10 % faster than no blocks; N = 16: even)
_CACHE: dict = {}
_FINISH: dict = {}


def types(n: int) -> dict:
    """The per-size local types the collision test works on (the kernels declare theirs from these)."""
    nb = (n - 1 + BLOCK - 1) // BLOCK
    return {"Mat": wp.types.matrix(shape=(n, 3), dtype=wp.float32),
            "Flags": wp.types.matrix(shape=(nb, nb), dtype=wp.float32), "NB": nb, "TEMPORAL": n <= TEMPORAL_MAX_NODES}


def collide_func(n: int):
    """collide(P, Q, KB, CP, G, cl, st, two_r, margin, min_sep, cull, link, nm1) for chains of n nodes:
    P, Q the positions at the end and the start of the step; KB, CP, G the temporal culling state (see the
    module docstring); cl the clearance so far; st the chain's status. Returns (best, best_a, best_b, cl,
    KB, CP, G): the first hit's crossing fraction and segment pair (best_a < 0: none this step)."""
    if n in _CACHE:
        return _CACHE[n]
    N = n
    BS = BLOCK
    NB = (n - 1 + BLOCK - 1) // BLOCK
    BLO = [blk * BS for blk in range(NB)]  # nodes of block blk's segments: BLO .. BHI - 1
    BHI = [min(blk * BS + BS, n - 1) + 1 for blk in range(NB)]
    TEMPORAL = n <= TEMPORAL_MAX_NODES
    Mat = wp.types.matrix(shape=(n, 3), dtype=wp.float32)
    Seg = wp.types.matrix(shape=(n, 4), dtype=wp.float32)
    BVec = wp.types.vector(length=NB, dtype=wp.float32)
    Blk = wp.types.matrix(shape=(NB, 4), dtype=wp.float32)
    BMat = wp.types.matrix(shape=(NB, 3), dtype=wp.float32)
    Flags = wp.types.matrix(shape=(NB, NB), dtype=wp.float32)

    def collide(P: Mat, Q: Mat, KB: Flags, CP: Flags, G: float, cl: float, st: int, two_r: float, margin: float,
                min_sep: int, cull: int, link: float, nm1: int):
        S = Seg()  # bounding spheres: midpoint, half length
        CB = Blk()  # block spheres (spatial culling)
        FAR = Flags()  # block pairs skipped this step
        MB = Flags()
        UB = BMat()
        DB = BVec()
        NEED = BVec()
        tol_link = 2.0e-3 * link + 1.0e-5
        chain_len = float(N) * link
        npair_a = nm1 - min_sep
        any_t = int(1)
        if wp.static(TEMPORAL):
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
                    far = spheres_apart(sa, sb, two_r, margin)
                    if cull == 0 or not far:
                        res = seg_closest(P[a], P[a + 1], P[j], P[j + 1])
                        gap = res[0] - two_r
                        if wp.static(TEMPORAL):
                            MB[blk_a, blk] = wp.min(MB[blk_a, blk], gap)
                        if not far:
                            cl = wp.min(cl, wp.min(gap, margin))
                        if gap <= 0.0 and st == 0:
                            best, best_a, best_b = first_contact(gap, Q[a], Q[a + 1], Q[j], Q[j + 1], two_r, a, j, best,
                                                                 best_a, best_b)
                    elif wp.static(TEMPORAL):  # each segment lies in its sphere
                        d = wp.vec3(sa[0] - sb[0], sa[1] - sb[1], sa[2] - sb[2])
                        reach_min = wp.sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2]) - sa[3] - sb[3] - two_r
                        MB[blk_a, blk] = wp.min(MB[blk_a, blk], reach_min)
        if wp.static(TEMPORAL):
            for ba in range(NB):
                for bb in range(ba, NB):
                    if FAR[ba, bb] < 0.5:
                        KB[ba, bb] = MB[ba, bb] + CP[ba, bb]
        return best, best_a, best_b, cl, KB, CP, G

    collide.__name__ = f"collide_{n}"
    func = wp.func(collide, module="unique")
    _CACHE[n] = func
    return func


def finish_func(n: int):
    """finish(state, b, P, V, step, every, end) for chains of n nodes: a chain that stops in `step` (blown up, or at
    its hit) leaves its final positions P and velocities V in the state and its final positions in every trajectory
    frame still to come (frames_from)."""
    if n in _FINISH:
        return _FINISH[n]
    N = n
    Mat = wp.types.matrix(shape=(n, 3), dtype=wp.float32)

    def finish(state: ChainState, b: int, P: Mat, V: Mat, step: int, every: int, end: int):
        for i in range(N):
            state.pos[b, i] = P[i]
            state.vel[b, i] = V[i]
        fr = frames_from(step, every, end)
        for k in range(fr[0], fr[1] + 1):
            for i in range(N):
                state.frames[k, b, i] = P[i]

    finish.__name__ = f"finish_{n}"
    func = wp.func(finish, module="unique")
    _FINISH[n] = func
    return func
