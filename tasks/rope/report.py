"""The rope's sections of report.html: each throw's critical moment, reference against the chain with the
measured and the fitted parameters."""
from __future__ import annotations

from wrenorm.viz.report import flag, num, table


def _chain(c: dict) -> list:
    status = c.get("status", "")
    hit = num(c.get("hit_time")) if status == "hit" else flag("never hits" if status else "?", "bad")
    return [hit, num(c.get("total"), 3)]


def sections(result: dict) -> list[tuple[str, str]]:
    if str(result.get("schema", "")).startswith("wrenorm.sensitivity"):
        return sensitivity_sections(result)
    if str(result.get("schema", "")).startswith("wrenorm.correct"):
        return correction_sections(result)
    points = result.get("critical_points") or {}
    if not points:
        return []
    rows = []
    for name, p in points.items():
        ref = p.get("reference") or {}
        rows.append([name, "held out" if p.get("held_out") else "train", num(ref.get("time")),
                     f"{num(ref.get('s_a'), 3)} / {num(ref.get('s_b'), 3)}",
                     *_chain(p.get("measured") or {}), *_chain(p.get("fitted") or {})])
    body = ("<p>The observable is the state at the first self-collision. Times in s; contact places as arc-length "
            "fractions of the two touching points; errors are the weighted sum the fit minimises, where a chain that "
            "never hits costs the no-hit penalty. The held-out conditions table scores such a chain by its state at "
            "the reference's moment instead (the validation's rule), so a held-out throw the chain misses shows two "
            "different errors.</p>"
            + table(["throw", "", "reference time", "reference place", "measured: hit time", "measured: error",
                     "fitted: hit time", "fitted: error"], rows))
    comp = result.get("held_out_comparison") or {}
    if comp:
        crow = [[k.replace("_", " "), num(v.get("ratio_of_means"), 3)] for k, v in comp.items() if isinstance(v, dict)]
        body += table(["held-out scoring", "fitted / measured mean error"], crow)
        body += f"<p class='muted'>{comp.get('meaning', '')}</p>"
    out = [("Critical moments", body)]
    refs = result.get("references") or {}
    if refs.get("files"):
        rows = []
        for f in refs["files"]:
            ev = f.get("event") or {}
            state = (flag("left out", "bad") if not f.get("used") else flag("flagged", "warn") if f.get("flagged")
                     else flag("used", "ok"))
            why = "; ".join(f.get("warnings") or []) or (f"{f['field']}: {f['problem']}" if f.get("field") else "")
            rows.append([f.get("name", ""), f.get("role", ""), state, num(ev.get("time")), ev.get("source", ""),
                         ev.get("confidence", ""), why])
        out.append((f"References: {refs.get('used')} used, {refs.get('left_out')} left out, {refs.get('flagged')} "
                    "flagged",
                    table(["reference", "role", "", "event time", "from", "confidence", "why"], rows)
                    + "<p class='muted'>A flagged event is used, and said here; a reference without a usable event is "
                      "left out of the fit (the command says which and why).</p>"))
    return out


def condition_charts(problem, fitted, measured) -> list[str]:
    """Per throw, the critical state seen from the side (x-z, the samples the error compares): the reference's
    and each chain's at its own first self-collision, or a note in the legend where a chain never hits."""
    import numpy as np

    from wrenorm.viz.svg import ROLE_COLORS, line_chart

    conds = problem.train + problem.held_out
    _, st = problem._critical(np.stack([measured, fitted]), conds)
    out = []
    for j, c in enumerate(conds):
        g = c.data.target.state
        split = "held out" if j >= len(problem.train) else "train"
        series = [{"x": g.pos[0, :, 0], "y": g.pos[0, :, 2], "label": f"reference, t = {float(g.time[0]):.3f} s",
                   "color": ROLE_COLORS["reference"], "markers": True}]
        for i, who in enumerate(("measured", "fitted")):
            b = i * len(conds) + j
            if st.hit[b]:
                series.append({"x": st.pos[b, :, 0], "y": st.pos[b, :, 2], "color": ROLE_COLORS[who],
                               "label": f"{who} parameters, t = {float(st.time[b]):.3f} s", "markers": True})
            else:
                series.append({"x": [], "y": [], "color": ROLE_COLORS[who], "label": f"{who} parameters: never hits"})
        out.append(line_chart(series, f"{split}: {c.name}, critical state from the side", "x [m]", "z [m]",
                              width=360, height=300, equal_scale=True))
    return out


def _directions(names, sv, noise, above, vectors=None) -> str:
    """One row per singular direction, flagged as the analysis decided (never re-derived here)."""
    rows = []
    for i, (v, n, ok) in enumerate(zip(sv, noise, above)):
        row = [f"{i + 1}", num(v, 3), num(n, 3), flag("above the noise", "ok") if ok else flag("in the noise", "bad")]
        if vectors is not None:
            comp = vectors[i]
            big = sorted(range(len(comp)), key=lambda k: -abs(comp[k]))[:3]
            row.append(", ".join(f"{names[k]} {comp[k]:+.2f}" for k in big))
        rows.append(row)
    return table(["direction", "singular value", "noise", ""] + (["largest components"] if vectors is not None
                                                                  else []), rows)


def _criterion(result: dict, step_key: str) -> str:
    nm = result.get("noise_model") or {}
    return (f"<p class='muted'>A direction is above the noise when singular value x step >= snr x noise (step "
            f"{num(nm.get(step_key), 3)}, snr {num(nm.get('snr'), 3)}).</p>")


def sensitivity_sections(result: dict) -> list[tuple[str, str]]:
    cmd = result.get("command") or {}
    out = []
    if cmd:
        dirs = cmd.get("directions") or []
        vectors = [[d["direction"][n] for n in cmd["names"]] for d in dirs] if dirs else None
        out.append((f"Command directions ({result.get('path')}, {result.get('variant')} rope, {result.get('params')} "
                    "parameters)",
                    f"<p><b>{cmd.get('count_above_noise')} of {cmd.get('dim')}</b> command directions move the "
                    "critical state above the noise; a correction without a model needs at least "
                    f"{cmd.get('min_trials_model_free')} trials.</p>"
                    + _directions(cmd["names"], cmd.get("singular_values", []), cmd.get("noise", []),
                                  cmd.get("above_noise", []), vectors) + _criterion(result, "command_step")))
    par = result.get("parameters") or {}
    if par.get("stacked_singular_values") is not None:
        out.append(("Parameter directions over the built-in throws",
                    f"<p><b>{par.get('count_above_noise')} of {len(par.get('names', []))}</b> parameter directions "
                    f"are above the noise over {len(par.get('conditions_used', []))} throws; "
                    f"{par.get('min_experiments')} throws suffice ({', '.join(par.get('min_experiment_set', []))})."
                    "</p>" + _directions(par["names"], par["stacked_singular_values"], par["stacked_noise"],
                                         par.get("stacked_above_noise", []))
                    + _criterion(result, "param_step")))
    return out


def correction_sections(result: dict) -> list[tuple[str, str]]:
    """`correct rope`: the goal, each run's verdict, and per trial what was tried and predicted, what the rope did and
    how the model and the trust region reacted (the rows of report.md)."""
    from wrenorm.tasks.rope.control.correct_cli import TRIAL_COLUMNS, run_method, run_verdict, trial_cells

    runs = result.get("runs") or {}
    summary = []
    for label, r in runs.items():
        state = flag("reached", "ok") if r.get("success") else flag("not reached", "bad")
        summary.append([label, run_method(r) if "method" in r else "", state, r.get("trials_to_tolerance") or "",
                        num(r.get("best_error"), 4), r.get("trials_used", "")])
    goal = result.get("goal") or {}
    intro = (f"<p>Real system: {result.get('real_system', '')}; coarse chain {result['model']['segments']} links; "
             f"goal: the critical state of the <code>{goal.get('path', '')}</code> throw (first contact at "
             f"{num(goal.get('critical_time'))} s); tolerance {num(result.get('tolerance'), 3)}. Error: "
             f"{result.get('error_meaning', '')}.</p>")
    out = [("Correction", intro + table(["run", "method", "", "trials to tolerance", "best error", "trials used"],
                                        summary))]
    for label, r in runs.items():
        out.append((f"{label}: {run_verdict(r, result['tolerance'])}", table(TRIAL_COLUMNS, trial_cells(result, label))
                    + "<p class='muted'>predicted: what the plan expected of this trial; model floor: the least error "
                      "the corrected model predicted any command in the box could reach when this trial was planned "
                      "(no trust radius); model alone: the chain's own prediction without the offset learned from "
                      "earlier trials; rho: real over predicted "
                      "gain, which sets the next trust radius where the trust region adapts (a fixed one keeps its "
                      "radius). Full states: real-trials/*-trial-NN.json.</p>"))
    return out
