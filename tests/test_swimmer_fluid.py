"""Peer check: the kernel's planar ellipsoid fluid wrench equals MuJoCo's own (package `mujoco`)."""
import mujoco
import numpy as np

from wrenorm.kernels import swimmer as kern
from wrenorm.tasks.swimmer import body

RHO, MU = 1000.0, 0.0013


def mujoco_wrench(semi, coef, yaw, v_world, wz):
    """World force and z torque MuJoCo applies to a free ellipsoid moving in the plane."""
    xml = f"""
    <mujoco><option density="{RHO}" viscosity="{MU}" gravity="0 0 0"/>
      <worldbody><body><freejoint/>
        <inertial pos="0 0 0" mass="1" diaginertia="0.01 0.01 0.01"/>
        <geom type="ellipsoid" size="{' '.join(repr(float(r)) for r in semi)}" fluidshape="ellipsoid"
              fluidcoef="{' '.join(repr(float(c)) for c in coef)}" contype="0" conaffinity="0"/>
      </body></worldbody></mujoco>"""
    m = mujoco.MjModel.from_xml_string(xml)
    d = mujoco.MjData(m)
    d.qpos[3:7] = [np.cos(yaw / 2), 0.0, 0.0, np.sin(yaw / 2)]
    d.qvel[:] = [v_world[0], v_world[1], 0.0, 0.0, 0.0, wz]
    mujoco.mj_forward(m, d)
    q = np.array(d.qfrc_fluid if hasattr(d, "qfrc_fluid") else d.qfrc_passive)
    return q, m.geom_fluid[0].copy()


def test_virtual_mass_matches_mujoco():
    rng = np.random.default_rng(3)
    for _ in range(6):
        semi = rng.uniform(0.002, 0.2, size=3)
        _, fl = mujoco_wrench(semi, [0.5, 0.25, 1.5, 1.0, 1.0], 0.0, [0.0, 0.0], 0.0)
        vm, vi = body.virtual_mass_inertia(semi)
        np.testing.assert_allclose(vm, fl[6:9], rtol=1e-5)
        np.testing.assert_allclose(vi, fl[9:12], rtol=1e-5)


def test_planar_fluid_wrench_matches_mujoco():
    rng = np.random.default_rng(7)
    n = 40
    cases = []
    for i in range(n):
        semi = np.exp(rng.uniform(np.log(0.002), np.log(0.2), size=3))
        coef = np.exp(rng.uniform(np.log(0.05), np.log(10.0), size=5))
        yaw = rng.uniform(-np.pi, np.pi)
        v = rng.uniform(-1.0, 1.0, size=2)
        wz = rng.uniform(-5.0, 5.0)
        if i == 0:
            wz = 0.0                       # pure translation
        if i == 1:
            v = np.zeros(2)                # pure rotation (Kutta and drag projections at |v| = 0)
        if i == 2:
            yaw, v = 0.0, np.array([0.3, 0.0])   # along an axis: no Kutta circulation
        cases.append((semi, coef, yaw, v, wz))

    local_vel, semis, coefs, amass, expect, scale = [], [], [], [], [], []
    for semi, coef, yaw, v, wz in cases:
        q, _ = mujoco_wrench(semi, coef, yaw, v, wz)
        c, s = np.cos(yaw), np.sin(yaw)
        local_vel.append([c * v[0] + s * v[1], -s * v[0] + c * v[1], wz])
        vm, vi = body.virtual_mass_inertia(semi)
        amass.append([RHO * vm[0], RHO * vm[1], RHO * vi[2]])
        semis.append(semi)
        coefs.append(coef)
        # MuJoCo keeps every term in the plane for planar motion
        assert abs(q[2]) <= 1e-9 * (1 + np.abs(q).max()) and np.abs(q[3:5]).max() <= 1e-9 * (1 + np.abs(q).max())
        expect.append([q[0], q[1], q[5]])
        scale.append(np.abs(q).max())

    got_local = kern.fluid_wrench_local(local_vel, semis, coefs, amass, RHO, MU)
    for (semi, coef, yaw, v, wz), g, e, sc in zip(cases, got_local, expect, scale):
        c, s = np.cos(yaw), np.sin(yaw)
        world = [c * g[0] - s * g[1], s * g[0] + c * g[1], g[2]]
        # float32 kernel against float64 MuJoCo
        np.testing.assert_allclose(world, e, rtol=2e-4, atol=2e-5 * sc + 1e-9,
                                   err_msg=f"semi={semi}, coef={coef}, yaw={yaw}, v={v}, w={wz}")


def test_each_coefficient_matters():
    """Guard against a term silently dropped: changing any coefficient changes MuJoCo's wrench and ours alike."""
    semi = np.array([0.05, 0.004, 0.03])
    base = np.array([0.4, 7.79, 2.81, 3.84, 0.27])
    vm, vi = body.virtual_mass_inertia(semi)
    am = [RHO * vm[0], RHO * vm[1], RHO * vi[2]]
    yaw, v, wz = 0.3, np.array([0.2, -0.15]), 1.7
    c, s = np.cos(yaw), np.sin(yaw)
    lv = [c * v[0] + s * v[1], -s * v[0] + c * v[1], wz]
    ref = kern.fluid_wrench_local([lv], [semi], [base], [am], RHO, MU)[0]
    for i in range(5):
        coef = base.copy()
        coef[i] *= 2.0
        q, _ = mujoco_wrench(semi, coef, yaw, v, wz)
        q0, _ = mujoco_wrench(semi, base, yaw, v, wz)
        g = kern.fluid_wrench_local([lv], [semi], [coef], [am], RHO, MU)[0]
        dm = np.array([q[0] - q0[0], q[1] - q0[1], q[5] - q0[5]])
        dg = g - ref
        dgw = np.array([c * dg[0] - s * dg[1], s * dg[0] + c * dg[1], dg[2]])
        assert np.abs(dm).max() > 1e-6
        np.testing.assert_allclose(dgw, dm, rtol=1e-3, atol=1e-4 * np.abs(dm).max())
