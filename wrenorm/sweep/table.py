"""A sweep's table: one row per cell (one per resolution when a cell fits several), flat enough for a
spreadsheet.

Columns: cell, the axes, seed, status, resolution; per parameter its fitted value (`J`) and standard deviation
(`J_std`), as `fitted_J` and `fitted_J_std` where an axis is named `J` too (the axis column keeps the swept value);
loss_measured, loss_fitted; warnings (the fit's own, joined by "; "); per held-out condition
heldout_<name>_measured / _fitted, heldout_mean_fitted, verdict; error; then the columns that differ from run to run
of the same cell (VOLATILE): the fit's own wall_seconds, the cell's cell_seconds (as the worker saw it), host,
started, finished. A command beyond fit and flow gives the rows its system says (ExtraCommand.table_rows: a
correction's one per arm), else its result's top-level numbers and strings.
"""
from __future__ import annotations

import csv
import io

from wrenorm.results import flow_point_std, write_atomic

LEADING = ("cell", "seed", "status", "resolution")
VOLATILE = ("wall_seconds", "cell_seconds", "host", "started", "finished")


def _text(value) -> str:
    if isinstance(value, list):
        return " ".join(map(_text, value))
    if isinstance(value, dict):
        return ";".join(f"{k}={_text(v)}" for k, v in value.items())
    return str(value)


def parameter_column(name: str, axes) -> str:
    """A fitted parameter's column: its name, or fitted_<name> where an axis has that name (an axis `J` is the
    value the cell was given, the fitted J another number: neither may overwrite the other)."""
    return f"fitted_{name}" if name in axes else name


def _fitted_columns(point: dict, std_of, axes) -> dict:
    """resolution, each parameter's fitted value and spread, and the training loss of one fit or flow point."""
    row = {"resolution": _text(point.get("resolution", ""))}
    for name, p in point.get("parameters", {}).items():
        col = parameter_column(name, axes)
        row[col] = p.get("fitted")
        row[f"{col}_std"] = std_of(p)
    loss = point.get("loss", {})
    row["loss_measured"], row["loss_fitted"] = loss.get("measured"), loss.get("fitted")
    # what the fit said of its own result (a diverged coarse model, a search that found nothing better) travels with
    # its numbers: a summary without it showed a blown-up cell as "done" beside the others
    said = list(point.get("warnings") or []) + ([point["warning"]] if point.get("warning") else [])  # a flow point's
    row["warnings"] = "; ".join(map(str, said))
    return row


def _fit_rows(r: dict, axes) -> list[dict]:
    rows = []
    for run in r.get("runs", [r]):
        row = _fitted_columns(run, lambda p: p.get("std"), axes)
        v = run.get("validation", {})
        for cond, c in v.get("conditions", {}).items():
            row[f"heldout_{cond}_measured"] = c.get("measured_error")
            row[f"heldout_{cond}_fitted"] = c.get("fitted_error")
        row["heldout_mean_fitted"] = v.get("mean_fitted_error")
        row["verdict"] = v.get("verdict")
        row["wall_seconds"] = run.get("wall_seconds", r.get("wall_seconds"))
        rows.append(row)
    return rows


def _flow_rows(r: dict, axes) -> list[dict]:
    rows = []
    for pt in r.get("points", []):
        row = _fitted_columns(pt, flow_point_std, axes)
        row["wall_seconds"] = r.get("wall_seconds")
        rows.append(row)
    return rows


def _other_rows(r: dict, axes) -> list[dict]:
    """Any other command's result: its top-level numbers, strings and switches (result_<key> where an axis has
    that name)."""
    row = {(f"result_{k}" if k in axes else k): v for k, v in r.items()
           if isinstance(v, (int, float, str, bool)) and k not in ("schema",)}
    return [row]


def _command_rows(table_rows):
    """A command's own rows (ExtraCommand.table_rows), its keys kept off the axes' columns as _other_rows keeps them."""
    def rows(r: dict, axes) -> list[dict]:
        return [{(f"result_{k}" if k in axes else k): v for k, v in row.items()} for row in table_rows(r)]

    return rows


def _command(verb: str, system: str | None):
    """The ExtraCommand a sweep's cells run (None for fit and flow, or without a system)."""
    if verb in ("fit", "flow") or not system:
        return None
    from wrenorm.system import get

    return next((c for c in get(system).commands if c.verb == verb), None)


def result_rows(verb: str, result: dict | None, axes=(), system: str | None = None) -> list[dict]:
    """axes: the spec's axis keys, which result columns must not take. system: where a command beyond fit and flow
    says what its table shows (ExtraCommand.table_rows), else the result's top-level numbers and strings."""
    if not result:
        return [{}]
    rows = {"fit": _fit_rows, "flow": _flow_rows}.get(verb)
    if rows is None:
        from wrenorm.system import resolve

        command = _command(verb, system)
        rows = _command_rows(resolve(command.table_rows)) if command and command.table_rows else _other_rows
    return rows(result, set(axes)) or [{}]


def summary(spec, records: dict, results: dict) -> list[str]:
    """What the command says of all finished cells together (ExtraCommand.sweep_summary over its table_rows; e.g. a
    correction campaign's runs reached per arm), or nothing."""
    from wrenorm.system import resolve

    command = _command(spec.verb, spec.system)
    if command is None or command.sweep_summary is None or command.table_rows is None:
        return []
    rows = [row for cell in spec.cells if (records.get(cell.id) or {}).get("status") == "done"
            and results.get(cell.id) for row in resolve(command.table_rows)(results[cell.id])]
    return list(resolve(command.sweep_summary)(rows)) if rows else []


def build(spec, records: dict, results: dict) -> list[dict]:
    """Rows in cell order: every cell of the spec, finished or not (status pending)."""
    rows = []
    for cell in spec.cells:
        rec = records.get(cell.id) or {}
        base = {"cell": cell.id, **{k: _text(v) for k, v in cell.axes.items()}, "seed": cell.seed,
                "status": rec.get("status", "pending")}
        extra = (result_rows(spec.verb, results.get(cell.id), spec.axes, spec.system) if rec.get("status") == "done"
                 else [{}])
        for part in extra:
            row = dict(base)
            row.update({k: v for k, v in part.items() if k not in VOLATILE})
            row["error"] = rec.get("error")
            row["wall_seconds"] = part.get("wall_seconds")
            for k in VOLATILE[1:]:
                row[k] = rec.get(k)
            rows.append(row)
    return rows


def columns(spec, rows: list[dict]) -> list[str]:
    cols = ["cell", *spec.axes, *LEADING[1:]]
    for row in rows:
        cols += [k for k in row if k not in cols and k not in VOLATILE and k != "error"]
    return cols + ["error", *VOLATILE]


def _cell(value) -> str:
    if value is None:
        return ""
    if isinstance(value, float):
        return repr(value)
    return _text(value)


def write_csv(path, spec, rows: list[dict]) -> None:
    cols = columns(spec, rows)
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(cols)
    for row in rows:
        w.writerow([_cell(row.get(c)) for c in cols])
    write_atomic(path, buf.getvalue())


def plotted(spec, results: dict) -> tuple[list[str], str | None]:
    """What sweep.png draws against the axes, and the column that splits a cell into several rows (None: a fit's or
    a flow's resolutions): the fitted parameters (free_names), or a command's ExtraCommand.sweep_plot columns."""
    command = _command(spec.verb, spec.system)
    if command is not None:
        return list(command.sweep_plot), command.sweep_part
    return free_names(spec.verb, results, spec.axes), None


def free_names(verb: str, results: dict, axes=()) -> list[str]:
    """The columns of the parameters fitted (not frozen) in any finished cell, in the order the results list them
    (parameter_column: not an axis's)."""
    names = []
    for r in results.values():
        if not r:
            continue
        runs = r.get("runs", [r]) if verb == "fit" else r.get("points", []) if verb == "flow" else []
        for run in runs:
            cols = [parameter_column(n, axes) for n, p in run.get("parameters", {}).items() if not p.get("frozen")]
            names += [c for c in cols if c not in names]
    return names


def stable(rows: list[dict]) -> list[dict]:
    """The rows without the columns that differ from run to run (what a resumed sweep must reproduce)."""
    return [{k: v for k, v in row.items() if k not in VOLATILE} for row in rows]
