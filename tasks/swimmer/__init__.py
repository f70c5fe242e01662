"""The robotic fish (paper, section 4): five fluid coefficients fitted to real swimming.

problem.py   the fit: SwimmerProblem, one condition per motor rate; elongated-body theory as a baseline
data.py      the real marker tracks (fishsim format) and what is measured from them
features.py  trajectory features of the head over the tail beat, measured alike on markers and simulated bodies
select.py    `select swimmer`: features, prior scale and parameter set chosen on the training clips alone
body.py      the robot's parts, its tail gait from the markers, the simulation batch
bench.py     kernel throughput
"""
from wrenorm.system import ExtraCommand, Flow, SearchDefaults, from_package
from wrenorm.tasks.swimmer import options

SYSTEM = from_package(
    __name__, "a real robotic fish's five stateless fluid coefficients, fitted to its swimming speed and gait features",
    search=SearchDefaults(method="cmaes+least-squares", generations=40, popsize=24, restarts=4),
    flow=Flow(options.add_flow_arguments, "wrenorm.tasks.swimmer.problem:flow_problems",
              "time steps [s] (--axis bodies: tail bodies)", generations=80),
    commands=(ExtraCommand("select", "choose the fit's features, prior scale and parameter set on the training clips",
                           "wrenorm.tasks.swimmer.select:add_arguments", "wrenorm.tasks.swimmer.select:run"),),
    observable="the fish's swimming over each tail beat: head speed, yaw and surge at each tail-motor rate",
    omitted="the fluid field (vortices, added-mass history, wall effects), replaced by stateless per-area force "
            "coefficients and an effective linear drag (viscosity)")
