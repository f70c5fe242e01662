"""Differentiable chain: tape gradients against central finite differences, and the forward
step against the collision kernel."""
import numpy as np
import pytest

from wrenorm.kernels import rope
from wrenorm.kernels.rope.grad import GRAD_FIELDS, GradRope
from wrenorm.tasks.rope.bench import swing_paths

N, LINK, DT, STEPS = 6, 0.12, 0.005, 40


def _setup(B=1):
    paths = swing_paths(2, STEPS, DT, seed=3)
    p0, v0 = rope.hanging_state(paths[0, 0], N, LINK)
    params = rope.ChainParams(node_mass=np.full(B, 0.03), lead_mass=np.full(B, 0.02), bend_k=np.full(B, 0.02),
                              bend_b=np.full(B, 1e-3), drag_lin=np.full(B, 0.3), drag_quad=np.full(B, 0.3),
                              radius=np.full(B, 0.005), mass_slope=np.full(B, 0.2), stretch=np.full(B, 2e-4))
    w = np.random.default_rng(0).normal(size=(B, N, 3)).astype(np.float32)
    return paths, p0, v0, params, w


def test_forward_matches_the_collision_kernel_without_contacts():
    paths, p0, v0, params, w = _setup()
    g = GradRope(N, LINK, DT)
    _, _, x = g.value_and_grad(p0, v0, paths, [0], params, STEPS, w)
    # min_sep larger than the chain: no pairs, so the collision kernel runs the same smooth step
    ref = rope.RopeSim(N, LINK, DT, min_sep=N).rollout(p0, v0, paths, [0], params, STEPS, stop_at_hit=False)
    assert np.abs(x - ref.final_pos).max() < 2e-5


def test_tape_gradient_equals_central_differences():
    paths, p0, v0, params, w = _setup()
    g = GradRope(N, LINK, DT)
    J, grads, _ = g.value_and_grad(p0, v0, paths, [0], params, STEPS, w)
    for f in GRAD_FIELDS:
        base = float(getattr(params, f)[0])
        # The forward pass is float32, so steps of a few % move J by little more than round-off
        # for the weak parameters (drag, damping). Steps of 20 % and 10 % are far above it;
        # Richardson extrapolation of the two central differences cancels their h^2 error.
        def central(h, f=f, base=base):
            vals = []
            for sgn in (1, -1):
                p = rope.ChainParams(**{k: getattr(params, k).copy() for k in rope.ChainParams.FIELDS})
                getattr(p, f)[0] = base + sgn * h
                vals.append(float(g.value_and_grad(p0, v0, paths, [0], p, STEPS, w)[0][0]))
            return (vals[0] - vals[1]) / (2 * h)

        h = 0.2 * base
        fd = (4.0 * central(h / 2) - central(h)) / 3.0
        assert abs(fd) * h > 1e-5 * abs(J[0]), f"{f}: the setup must make J depend on every parameter"
        assert float(grads[f][0]) == pytest.approx(float(fd), rel=0.04), f


def test_one_launch_rollout_equals_one_launch_per_step():
    """value_and_grad runs every step in one launch (no host work per step on a GPU); J, the gradients and the
    final state are those of the per-step launches, bit for bit."""
    B = 3
    paths, p0, v0, params, w = _setup(B)
    params.bend_k[:] = [0.01, 0.02, 0.05]
    params.stretch[:] = [0.0, 2e-4, 1e-3]
    g = GradRope(N, LINK, DT)
    pidx = np.array([0, 1, 0])
    fused = g.value_and_grad(p0, v0, paths, pidx, params, STEPS, w)
    stepped = g.value_and_grad(p0, v0, paths, pidx, params, STEPS, w, per_step=True)
    assert np.array_equal(fused[0], stepped[0]) and np.array_equal(fused[2], stepped[2])
    for f in GRAD_FIELDS:
        assert np.array_equal(fused[1][f], stepped[1][f]), f
        assert np.all(fused[1][f] != 0), f
