"""The PD system's command-line options (cheap to import: the CLI builds its parser from them)."""
from __future__ import annotations

import argparse

from wrenorm.options import add_list, add_number, add_numbers

MEASURED = {"J": 0.05, "K_P": 20.0, "K_D": 0.5}
FLOW_F_SIM = [50.0, 100.0, 200.0, 400.0, 800.0]
F_SIM_RANGE = (5.0, 20000.0)  # Hz; 3 s commands, so at most 60 000 steps per condition


def add_arguments(p: argparse.ArgumentParser) -> None:
    add_numbers(p, "--f-sim", default=[100.0], lo=F_SIM_RANGE[0], hi=F_SIM_RANGE[1], unit="Hz", metavar="HZ",
                help="simulation frequency; several: one fit each, result.json holds `runs`")
    p.add_argument("--integrator", default="semi-implicit", choices=["semi-implicit", "explicit"])
    # None until build_problems: a log's joint must name its own (the log fixes J and K_D only relative to K_P)
    own = "the built-in joint's {:g}; with --reference, required: the logged joint's own"
    add_number(p, "--J", default=None, lo=1e-6, hi=1e3, unit="kg m^2", help="measured joint inertia",
               default_text=own.format(MEASURED["J"]))
    add_number(p, "--K-P", dest="K_P", default=None, lo=1e-6, hi=1e6, unit="N m/rad", help="real proportional gain",
               default_text=own.format(MEASURED["K_P"]))
    add_number(p, "--K-D", dest="K_D", default=None, lo=0.0, lo_open=True, hi=1e4, unit="N m s/rad",
               help="real derivative gain", default_text=own.format(MEASURED["K_D"]))
    p.add_argument("--reference", default=None, metavar="FILE.csv",
                   help="measured log (columns time, q, q_d, qd_d) instead of the built-in continuous reference")
    add_list(p, "--validate", default=None, metavar="FILE.csv",
             help="held-out logs of the same joint under other commands, with --reference: each is validated whole, "
                  "beside the reference's last third (which is the same command's, not a new condition)")
    add_number(p, "--controller-rate", default=None, lo=1.0, hi=1e6, unit="Hz", default_text="continuous",
               help="the real servo's own control rate, with --reference: it samples and holds its torque for a "
                    "period, which moves K_D by about -K_P / (2 rate) and J by -K_D / (2 rate); the predictions and "
                    "the gains check then include that shift (the fit is the same)")
    p.add_argument("--arm", action="store_true",
                   help="two-link arm with M(q) and gain matrices: fit the joint-space inertia correction and K_D^sim")


def add_flow_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--integrator", default="semi-implicit", choices=["semi-implicit", "explicit"])
