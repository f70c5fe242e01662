"""MuJoCo's ellipsoid fluid model restricted to the plane (velocity (a, b, 0), angular velocity (0, 0, w) in
a part's frame keep every term of it in the plane, so these planar formulas are MuJoCo's exactly; checked
against the `mujoco` package in tests/test_swimmer_fluid.py)."""
from __future__ import annotations

import numpy as np
import warp as wp

wp.set_module_options({"enable_backward": False})  # forward only, like kernel.py

MINVAL = 1e-15  # mjMINVAL


geo9 = wp.types.vector(length=9, dtype=wp.float32)
wrench5 = wp.types.vector(length=5, dtype=wp.float32)


@wp.func
def fluid_geometry(r0: float, r1: float, r2: float):
    """Shape constants of an ellipsoid for fluid_planar: volume, A_max, I_max, I_D along z,
    Stokes force and torque factors, (r1 r2)^2 and (r2 r0)^2 divided by the larger of the two,
    and the square root of that larger one. The normalisation keeps the projection terms of
    small parts far from float32 underflow and from the MINVAL guards (MuJoCo 4 evaluates the
    Kutta term at these scales without clamping)."""
    pi = 3.14159265358979
    vol = 4.0 / 3.0 * pi * r0 * r1 * r2
    d_max = wp.max(wp.max(r0, r1), r2)
    d_min = wp.min(wp.min(r0, r1), r2)
    d_mid = r0 + r1 + r2 - d_max - d_min
    a_max = pi * d_max * d_mid
    i_max = 8.0 / 15.0 * pi * d_mid * d_max * d_max * d_max * d_max
    rr = wp.max(r0, r1)
    i_z = 8.0 / 15.0 * pi * r2 * rr * rr * rr * rr
    eq_d = 2.0 / 3.0 * (r0 + r1 + r2)
    q12 = (r1 * r2) * (r1 * r2)
    q20 = (r2 * r0) * (r2 * r0)
    qm = wp.max(q12, q20)
    return geo9(vol, a_max, i_max, i_z, 3.0 * pi * eq_d, pi * eq_d * eq_d * eq_d,
                q12 / qm, q20 / qm, wp.sqrt(qm))


@wp.func
def fluid_planar(a: float, b: float, w: float, g: geo9,
                 c_blunt: float, c_slender: float, c_ang: float, c_kutta: float, c_magnus: float,
                 rho: float, mu: float, ma0: float, ma1: float):
    """MuJoCo ellipsoid fluid force (fx, fy) and torque tz in the part frame, planar motion,
    plus the linear and angular drag factors (force = -drag_lin v - ..., torque = -drag_ang w + ...)
    that the integrator treats implicitly.

    (a, b): linear velocity of the ellipsoid centre, w: angular velocity about z, all local;
    g = fluid_geometry(semi-axes); ma0, ma1: virtual masses along local x, y times the density.
    """
    pi = 3.14159265358979
    speed = wp.sqrt(a * a + b * b)

    # Magnus: C_M rho V (w x v)
    mag = c_magnus * rho * g[0] * w
    q12 = g[6]
    q20 = g[7]
    n0 = q12 * a  # non-unit normal of the cross-section generating the projection (scaled)
    n1 = q20 * b
    proj_num = q12 * a * a + q20 * b * b
    proj_denom = q12 * q12 * a * a + q20 * q20 * b * b
    a_proj = pi * g[8] * wp.sqrt(proj_denom / wp.max(MINVAL, proj_num))
    cos_alpha = proj_num / wp.max(MINVAL, speed * proj_denom)
    # Kutta: circulation (n x v) along z, force = circ x v
    circ = (n0 * b - n1 * a) * c_kutta * rho * cos_alpha * a_proj

    mom_z = w * (c_ang * g[3] + c_slender * (g[2] - g[3]))
    drag_lin = mu * g[4] + rho * speed * (a_proj * c_blunt + c_slender * (g[1] - a_proj))
    drag_ang = mu * g[5] + rho * wp.abs(mom_z)

    # velocity-dependent added-mass terms: (m_A v) x w and (m_A v) x v
    fx = -(mag + circ) * b - drag_lin * a + ma1 * b * w
    fy = (mag + circ) * a - drag_lin * b - ma0 * a * w
    tz = -drag_ang * w + (ma0 - ma1) * a * b
    return wrench5(fx, fy, tz, drag_lin, drag_ang)


@wp.kernel
def fluid_planar_kernel(vel: wp.array(dtype=wp.vec3), semi: wp.array(dtype=wp.vec3),
                        coef: wp.array2d(dtype=float), amass: wp.array(dtype=wp.vec3),
                        rho: float, mu: float, out: wp.array(dtype=wp.vec3)):
    """Local fluid wrench for single ellipsoids (the MuJoCo peer test drives this)."""
    i = wp.tid()
    v = vel[i]
    r = semi[i]
    m = amass[i]
    g = fluid_geometry(r[0], r[1], r[2])
    f = fluid_planar(v[0], v[1], v[2], g, coef[i, 0], coef[i, 1], coef[i, 2],
                          coef[i, 3], coef[i, 4], rho, mu, m[0], m[1])
    out[i] = wp.vec3(f[0], f[1], f[2])


@wp.kernel
def fluid_geometry_kernel(semi: wp.array(dtype=wp.vec3), out: wp.array(dtype=geo9)):
    i = wp.tid()
    r = semi[i]
    if r[0] > 0.0:
        out[i] = fluid_geometry(r[0], r[1], r[2])


vec15 = wp.types.vector(length=15, dtype=wp.float32)

def fluid_wrench_local(vel, semi, coef, amass, rho: float, mu: float, device: str = "cpu") -> np.ndarray:
    """Evaluate fluid_planar for N ellipsoids: vel (N,3)=(vx, vy, wz) local -> (N,3) (fx, fy, tz)."""
    n = len(vel)
    out = wp.zeros(n, dtype=wp.vec3, device=device)
    wp.launch(fluid_planar_kernel, dim=n, device=device, inputs=[
        wp.array(np.asarray(vel, np.float32), dtype=wp.vec3, device=device),
        wp.array(np.asarray(semi, np.float32), dtype=wp.vec3, device=device),
        wp.array(np.asarray(coef, np.float32), dtype=float, device=device),
        wp.array(np.asarray(amass, np.float32), dtype=wp.vec3, device=device),
        float(rho), float(mu), out])
    return out.numpy()


