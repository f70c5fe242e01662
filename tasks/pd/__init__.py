"""PD control at finite simulation frequency (paper, section 2): the joint (problem.py), the two-link arm
(arm.py), measured logs (problem.load_log), options (options.py), throughput (bench.py)."""
from wrenorm.system import Flow, SearchDefaults, from_package
from wrenorm.tasks.pd import options

SYSTEM = from_package(
    __name__, "a PD-controlled joint at finite simulation frequency (K_D, J and feed-forward gains)",
    search=SearchDefaults(method="least-squares", generations=60, popsize=24),
    flow=Flow(options.add_flow_arguments, "wrenorm.tasks.pd.problem:flow_problems", "f_sim [Hz]", generations=80,
              analytic="wrenorm.tasks.pd.problem:flow_analytic"),
    observable="the joint's trajectory under its PD controller, as a continuous-time joint (or a log) gives it",
    omitted="continuous time: the simulator updates the controller and integrates at a finite frequency f_sim")
