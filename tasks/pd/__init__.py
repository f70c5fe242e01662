"""PD control at finite simulation frequency (paper, section 2): the joint (problem.py), the two-link arm
(arm.py), measured logs (problem.load_log), options (options.py), throughput (bench.py)."""
from wrenorm.system import Flow, SearchDefaults, System
from wrenorm.tasks.pd import options


def _kernel_modules() -> dict:
    from wrenorm.kernels import arm, pd

    return {"pd": pd, "arm": arm}


SYSTEM = System(
    name="pd",
    help="a PD-controlled joint at finite simulation frequency (K_D, J and feed-forward gains)",
    add_arguments=options.add_arguments,
    build="wrenorm.tasks.pd.problem:build_problems",
    search=SearchDefaults(generations=60, popsize=24, polish=20),
    flow=Flow(options.add_flow_arguments, "wrenorm.tasks.pd.problem:flow_problems", "f_sim [Hz]", generations=80,
              analytic="wrenorm.tasks.pd.problem:flow_analytic"),
    bench="wrenorm.tasks.pd.bench:bench",
    kernel_modules=_kernel_modules,
    parity="wrenorm.tasks.pd.bench:parity",
)
