"""The swimmer's command-line options (cheap to import: the CLI builds its parser from them)."""
from __future__ import annotations

import argparse
from pathlib import Path

from wrenorm.options import add_list, add_number

DEFAULT_DT = 0.008  # s; ROS2 there is within ~1 mm/s of 0.5 ms steps (tests/test_swimmer_sim.py)
TAIL_BODIES = 6  # the robot's five plates and the fin (tasks/swimmer/body.py LINKS)
DEFAULT_TRAIN = [1.00, 1.75]  # the published fit's training rates
VISCOSITY = 0.0013  # Pa s, the published model's water
FPS = 60.0  # frames/s of the fishsim marker files (data.py takes it from here)
# feature sets (features.FEATURES); the speed is always first, the headline
FEATURE_SETS = {
    "speed": ("speed",),
    "yaw": ("speed", "yaw_amp", "yaw_phase"),
    "sway": ("speed", "sway_amp", "sway_phase"),
    "surge2": ("speed", "surge2_amp", "surge2_phase"),
    "surge1": ("speed", "surge1_amp", "surge1_phase"),
    "yaw+surge2": ("speed", "yaw_amp", "yaw_phase", "surge2_amp", "surge2_phase"),
    "all": ("speed", "yaw_amp", "yaw_phase", "sway_amp", "sway_phase", "surge2_amp", "surge2_phase",
            "surge1_amp", "surge1_phase"),
}
DEFAULT_FEATURES = "yaw+surge2"  # chosen on the training clips: tasks/swimmer/select.py
DEFAULT_PRIOR_SCALE = 0.5  # e-folds of the Gaussian prior around the published values (0: off); chosen likewise
FREE_VISCOSITY = True  # the viscosity fitted as an effective parameter (--freeze viscosity: the five alone); likewise
FLOW_DT = [0.002, 0.004, 0.008, 0.016]
FLOW_BODIES = [2, 3, 6]


def _label(text: str) -> float:
    from wrenorm.options import number

    return number(0.0, 100.0, lo_open=True)(text)


def add_data_arguments(p: argparse.ArgumentParser) -> None:
    """The clips and the body model: what `select swimmer` studies as well as what a fit fits."""
    p.add_argument("--data", type=Path, default=None, metavar="DIR",
                   help="folder of fishsim markers_f*.csv (rate label from the file name); default: built-in data")
    add_number(p, "--fps", default=FPS, lo=0.0, lo_open=True, hi=100000.0, unit="frames/s",
               help="frame rate of the --data clips (60: the fishsim format; the built-in data carry theirs)")
    add_list(p, "--train", default=list(DEFAULT_TRAIN), item=_label, metavar="HZ", unordered=True,
             help="training motor-rate labels (every other rate validates)")
    p.add_argument("--virtual-mass", action="store_true",
                   help="add the acceleration-dependent added mass (default: MuJoCo's model, velocity terms only)")
    p.add_argument("--gait", choices=["chain", "wave"], default="chain",
                   help="rigid links whose angles follow the markers (chain) or parts placed on the measured wave "
                        "(wave)")


def add_fit_arguments(p: argparse.ArgumentParser) -> None:
    """What a fit matches and how it simulates: `select swimmer` chooses features and prior itself, so it takes
    none of these (accepting them there would ignore them in silence)."""
    # default None, not the set's name: the default drops what head-frame clips cannot measure (said so), a
    # feature asked for by name is refused there instead
    p.add_argument("--features", default=None, metavar="SET|LIST",
                   help=f"trajectory features fitted per training rate, each normalised by its beat-to-beat noise: a "
                        f"set {list(FEATURE_SETS)} or a comma-separated list of {list(FEATURE_SETS['all'])}; the "
                        f"speed is always fitted (default: {DEFAULT_FEATURES}, less yaw and sway where a clip is "
                        f"rotatedMarkers, in the head frame)")
    add_number(p, "--prior-scale", default=DEFAULT_PRIOR_SCALE, lo=0.0, hi=20.0, unit="e-folds",
               help="std of the Gaussian prior on ln(coefficient) around the published values (ln 3 = 1.10: a "
                    "factor of 3); 0: no prior")
    add_number(p, "--speed-weight", default=1.0, lo=0.0, lo_open=True, hi=1000.0,
               help="factor on the speed's normalised residuals (1: each feature by its noise alone)")
    p.add_argument("--integrator", choices=["ros2", "euler"], default="ros2",
                   help="ros2: second-order Rosenbrock (default); euler: linearly implicit Euler, first order")


def add_resolution_arguments(p: argparse.ArgumentParser, flow: bool = False) -> None:
    """flow: both default to None (filled in by flow_problems), so one named on the axis that --resolutions varies
    is seen and refused rather than ignored."""
    held = " when --resolutions varies the other" if flow else ""
    add_number(p, "--dt", default=None if flow else DEFAULT_DT, lo=0.0002, hi=0.02, unit="s",
               default_text=f"{DEFAULT_DT}{held}" if flow else None,
               help="simulation step (fitted to a whole tail beat)")
    add_number(p, "--bodies", default=None if flow else TAIL_BODIES, lo=2, hi=TAIL_BODIES, integer=True,
               default_text=f"{TAIL_BODIES}{held}" if flow else None,
               help="tail bodies (consecutive plates merged; the fin kept)")


def add_common_arguments(p: argparse.ArgumentParser) -> None:
    add_data_arguments(p)
    add_fit_arguments(p)


def add_arguments(p: argparse.ArgumentParser) -> None:
    add_common_arguments(p)
    add_resolution_arguments(p)


def add_flow_arguments(p: argparse.ArgumentParser) -> None:
    add_common_arguments(p)
    p.add_argument("--axis", choices=["dt", "bodies"], default="dt",
                   help="what --resolutions varies: dt, the time step [s]; bodies, the tail's rigid bodies")
    add_resolution_arguments(p, flow=True)
