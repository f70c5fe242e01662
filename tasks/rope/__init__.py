"""The flying-knot rope: a coarse chain matched to a reference rope at its first self-collision."""
from wrenorm.tasks.rope.problem import (FLOW_GENERATIONS, add_arguments, add_flow_arguments, build_problem,  # noqa: F401
                                        flow_problems)
