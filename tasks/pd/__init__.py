"""PD control at finite simulation frequency (paper, section 2)."""
from wrenorm.tasks.pd.problem import (FLOW_GENERATIONS, add_arguments, add_flow_arguments, build_problems,  # noqa: F401
                                      flow_analytic, flow_problems)
