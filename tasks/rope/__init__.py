"""The flying-knot rope: a coarse chain matched to a reference rope at its first self-collision.

problem.py     the fit: RopeProblem, one condition per reference throw
observable.py  the critical state (shape, velocity, time and place of the first self-collision) and its error
reference/     reference ropes: file format, event detection, the fine newton and MuJoCo ropes, hand paths
control/       steering real throws: command space, planning, correction over trials, sensitivity
bench.py       kernel throughput; baselines.py: the numpy / torch peers of the chain step
"""
from wrenorm.system import ExtraCommand, Flow, SearchDefaults, from_package
from wrenorm.tasks.rope import options

SYSTEM = from_package(
    __name__, "a coarse rope chain matched to a reference rope at its first self-collision (the flying knot)",
    search=SearchDefaults(generations=60, restarts=4),
    flow=Flow(options.add_flow_arguments, "wrenorm.tasks.rope.problem:flow_problems",
              "segment counts (--axis dt: steps [s])", generations=60),
    observable="the rope's state at its first self-collision: shape, velocity, time and place of the contact",
    omitted="the continuum: a fine rope's bending modes, internal damping and contact resolved by a chain of few "
            "segments at a coarse time step",
    commands=(
        ExtraCommand("reference", "generate a fine reference rope (.npz) along a hand path",
                     "wrenorm.tasks.rope.reference.generate:add_reference_arguments",
                     "wrenorm.tasks.rope.reference.generate:run_reference"),
        ExtraCommand("inspect", "the critical moment a reference file gives the fit: detected or annotated, "
                                "with its confidence and reasons",
                     "wrenorm.tasks.rope.reference.inspection:add_arguments",
                     "wrenorm.tasks.rope.reference.inspection:run"),
        ExtraCommand("correct", "correct a throw's command over real trials toward a goal critical state",
                     "wrenorm.tasks.rope.control.correct_cli:add_arguments",
                     "wrenorm.tasks.rope.control.correct_cli:run",
                     table_rows="wrenorm.tasks.rope.control.correct_cli:sweep_rows",
                     sweep_summary="wrenorm.tasks.rope.control.correct_cli:sweep_summary",
                     sweep_plot=("trials", "best_error"), sweep_part="arm"),
        ExtraCommand("sensitivity", "how many command / parameter directions move the critical state",
                     "wrenorm.tasks.rope.control.sensitivity:add_arguments",
                     "wrenorm.tasks.rope.control.sensitivity:run"),
    ))
