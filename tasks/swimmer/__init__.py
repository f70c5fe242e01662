"""The robotic fish (paper, section 4): five fluid coefficients fitted to real swimming.

problem.py   the fit: SwimmerProblem, one condition per motor rate; elongated-body theory as a baseline
data.py      the real marker tracks (fishsim format) and what is measured from them
body.py      the robot's parts, its tail gait from the markers, the simulation batch
bench.py     kernel throughput
"""
from wrenorm.system import Flow, SearchDefaults, from_package
from wrenorm.tasks.swimmer import options

SYSTEM = from_package(
    __name__, "a real robotic fish's five stateless fluid coefficients, fitted to its swimming speed",
    search=SearchDefaults(generations=150, popsize=32, restarts=4),
    flow=Flow(options.add_flow_arguments, "wrenorm.tasks.swimmer.problem:flow_problems",
              "time steps [s] (--axis bodies: tail bodies)", generations=80),
    observable="the fish's steady swimming speed (and its yaw and surge gait) at each tail-motor rate",
    omitted="the fluid field: vortices, added-mass history and wall effects, replaced by five stateless "
            "per-area force coefficients")
