"""Shared swimmer test helper (not a test module)."""
import numpy as np

from wrenorm.tasks.swimmer import body as sb

PUBLISHED = np.array([0.4, 7.79, 2.81, 3.84, 0.27])


def com_drift(rate, dt, bodies=len(sb.LINKS), seconds=4.0):
    """Simulate the fish without water; return (max centre-of-mass drift, max head excursion) in m.

    Without fluid the tail can only shake the head about a fixed centre of mass."""
    g = sb.gait(rate, bodies=bodies)
    prt = sb.parts(sb.merge_links(bodies))
    m = prt["inert"][:, 0]
    sim = sb.build_batch([rate], dt=dt, rho=0.0, mu=0.0, warm_seconds=0.0, meas_seconds=seconds,
                         max_warm_seconds=None, gaits=[g])
    stride = 10
    _, traj, _ = sim.run(PUBLISHED[None], rec_stride=stride, rec_frames=int(sim.steps[0]) // stride)
    period = 1.0 / g["freq"]
    n = int(np.ceil(period / dt))
    tab = sb.part_table(g, np.arange(n) * (period / n), prt)
    com = []
    for X, Y, th, k in traj[0, 0]:
        loc = (m[:, None] * tab[int(k), :, :2]).sum(0) / m.sum()
        c, s = np.cos(th), np.sin(th)
        com.append([X + c * loc[0] - s * loc[1], Y + s * loc[0] + c * loc[1]])
    com = np.array(com)
    return np.abs(com - com[0]).max(), np.abs(traj[0, 0, :, :2]).max()
