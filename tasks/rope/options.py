"""The rope system's command-line options (cheap to import: the CLI builds its parser from them)."""
from __future__ import annotations

import argparse

from wrenorm.options import add_list, add_number

ITERATIONS = 4  # constraint passes per step; see tasks/rope/problem.py (2 fits slightly better)
SEGMENTS = (3, 63)  # links of the coarse chain
DT = (1e-3, 0.05)  # s, coarse step. The chain keeps float32 positions in the file's frame: a step's change of a
# coordinate metres from the origin rounds away below about 1 ms (the built-in throw, hand at 1.6 m, against a float64
# copy of the same step: 0.05 mm apart at 5 ms, 1.7 mm at 1 ms, 9 mm at 0.5 ms, 0.3 m at 0.1 ms, where a pendulum's
# period came out 84 % off; review of stop 55)
FLOW_SEGMENTS = [6, 10, 16]
FLOW_DT = [0.0025, 0.005, 0.01]


SEGMENTS_DEFAULT = 10
DT_DEFAULT = 0.005


def add_chain_arguments(p: argparse.ArgumentParser, segments: int = SEGMENTS_DEFAULT, flow: bool = False) -> None:
    """The chain's resolution and solver. flow: --segments and --dt default to None (filled in by flow_problems),
    so one named on the axis that --resolutions varies is seen and refused rather than ignored."""
    held = " when --resolutions varies the other" if flow else ""
    add_number(p, "--segments", default=None if flow else segments, lo=SEGMENTS[0], hi=SEGMENTS[1], integer=True,
               default_text=f"{segments}{held}" if flow else None,
               help="links of the coarse chain; it has segments + 1 point masses (10 = the flying knot's 11)")
    add_number(p, "--dt", default=None if flow else DT_DEFAULT, lo=DT[0], hi=DT[1], unit="s",
               default_text=f"{DT_DEFAULT}{held}" if flow else None, help="coarse step (flying knot: 0.005)")
    add_number(p, "--iterations", default=ITERATIONS, lo=1, hi=64, integer=True,
               help="constraint passes per step (fewer: softer, under-converged links and joints)")


def add_arguments(p: argparse.ArgumentParser) -> None:
    add_list(p, "--reference", default=None, metavar="FILE",
             help="reference rope trajectories (.npz) to fit; default: the built-in fit paths")
    add_list(p, "--validate", default=None, metavar="FILE",
             help="held-out references (.npz); default: built-in held-out paths (without --reference)")
    add_chain_arguments(p)


def add_flow_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--axis", choices=["segments", "dt"], default="segments",
                   help="what --resolutions varies: segments (links of the chain) or dt (step [s])")
    add_chain_arguments(p, flow=True)
