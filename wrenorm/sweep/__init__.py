"""Sweeps: many fits (or flow points, or correction campaigns) from one TOML spec, run as Ray tasks.

spec.py      the spec: task, fixed options, axes, seeds; expanded into cells, every cell's options checked with
             the task's own parser before anything runs
cell.py      what one Ray task does: the task's own command (wrenorm.cli.main) into the cell's run folder
run.py       the `sweep` command: run folder and state, Ray start-up, submission, gathering, resume
table.py     one row per cell (axes, fitted values, std, losses, held-out errors, verdict, wall time, host)
progress.py  done / running / failed, elapsed and estimate on one line

Ray is imported only when a sweep runs (extra `sweep`: pip install 'wrenorm[sweep]').
"""
