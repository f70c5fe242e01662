"""The robotic fish: five fluid coefficients fitted to real swimming."""
from wrenorm.tasks.swimmer.problem import (FLOW_GENERATIONS, add_arguments, add_flow_arguments, build_problem,  # noqa: F401
                                           flow_problems)
