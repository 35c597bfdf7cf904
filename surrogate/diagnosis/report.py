"""The inspection's report and figures (the modules of :mod:`surrogate.diagnosis` measure).

``report.md`` is written from ``inspect.json``'s content (the summary) and the measurements at
fixed inputs; the figures are matplotlib ``Figure`` objects (no pyplot), saved by the stage.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import pandas as pd

from surrogate.diagnosis.fixed import FixedInputs
from surrogate.diagnosis.population import Grid
from surrogate.diagnosis.recommendation import COLLECT_TIME_MARGIN
from surrogate.evaluate.report import format_markdown_table

#: the report's figures, beside it in the inspection's directory
INPUT_OCCUPANCY_FIGURE = "occupancy.png"
SETTLING_FIGURE = "settling.png"
MEMORY_FIGURE = "memory.png"


def plot_occupancy(grid: Grid, fixed: FixedInputs, lump: str, low: float) -> Any:
    """phi's occupancy (+- 2 standard errors) along each input's range."""
    from matplotlib.figure import Figure

    axes_ids = sorted({int(a) for a in grid.axis if a >= 0}) or [-1]
    fig = Figure(figsize=(4.2 * len(axes_ids), 3.4))
    fig.subplots_adjust(left=0.16 / len(axes_ids) + 0.02, right=0.98, bottom=0.17, top=0.85,
                        wspace=0.3)  # fmt: skip
    for ax, i in zip(np.atleast_1d(fig.subplots(1, len(axes_ids))), axes_ids, strict=True):
        rows = grid.axis == i
        values = grid.x[rows, i] if i >= 0 else np.zeros(1)
        ax.errorbar(values, fixed.occupancy[rows], yerr=2 * fixed.occupancy_se[rows], fmt="o-",
                    ms=4, capsize=3, label="P(phi = 1)")  # fmt: skip
        if i >= 0:
            ax.plot([grid.median[i]], [fixed.occupancy[0]], "k*", ms=9, label="all at median")
            ax.set_xlabel(grid.names[i])
        for level in (low, 1 - low):
            ax.axhline(level, ls=":", c="tab:red", lw=1)
        ax.set_ylim(-0.03, 1.03)
        ax.set_ylabel("stationary P(phi = 1)")
        ax.legend(fontsize=7)
    fig.suptitle(f"phi = {lump}: occupancy across the inputs the fields give ({fixed.method})",
                 fontsize=10)  # fmt: skip
    return fig


def plot_settling(fixed: FixedInputs, burn_in: float | None) -> Any:
    """The median point's mean counts (over their final value) and occupancy against time
    from the file's counts, with the settling times and the model's burn-in."""
    from matplotlib.figure import Figure

    curves = fixed.curves
    t = np.asarray(curves["times"])
    fig = Figure(figsize=(10, 3.6))
    fig.subplots_adjust(left=0.07, right=0.98, bottom=0.15, top=0.86, wspace=0.25)
    left, right = fig.subplots(1, 2)
    for name, mean in curves.get("species", {}).items():
        final = curves["final"][name]
        if abs(final) > 0:
            left.plot(t, np.asarray(mean) / final, lw=1.2,
                      label=f"{name} ({fixed.species_settle.get(name, math.nan):.3g} s)")  # fmt: skip
    left.axhline(1.0, c="k", lw=0.8)
    left.set_xlabel("t (s) from the file's counts")
    left.set_ylabel("mean count / final value")
    left.set_title("mean counts at the median inputs (settling time)", fontsize=9)
    right.plot(t, curves["phi"], c="tab:purple", lw=1.2)
    right.axhline(curves["phi_final"], c="k", lw=0.8)
    right.axvline(fixed.settle_phi[0], c="tab:purple", ls="--", lw=1,
                  label=f"settled {fixed.settle_phi[0]:.3g} s")  # fmt: skip
    right.set_xlabel("t (s) from the file's counts")
    right.set_ylabel("P(phi = 1)")
    right.set_title("phi's occupancy at the median inputs", fontsize=9)
    for ax in (left, right):
        if burn_in is not None:
            ax.axvline(burn_in, c="tab:red", ls=":", lw=1, label=f"model.burn_in {burn_in:g} s")
        if ax.get_legend_handles_labels()[0]:
            ax.legend(fontsize=7)
    return fig


def plot_memory(fixed: FixedInputs, dt: float, lumps: Sequence[str]) -> Any:
    """phi's autocorrelation (simulated) or its exact decay, and the hazard of leaving each
    lump against the time since phi last changed, at the median inputs."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(10, 3.6))
    fig.subplots_adjust(left=0.07, right=0.98, bottom=0.15, top=0.86, wspace=0.25)
    left, right = fig.subplots(1, 2)
    r = fixed.relaxation
    tau = r["tau_s"]
    if "acf" in r:
        rho, se = np.asarray(r["acf"]), np.asarray(r["acf_se"])
        lags = np.arange(rho.size) * dt
        left.fill_between(lags, rho - 2 * se, rho + 2 * se, alpha=0.3)
        left.plot(lags, rho, lw=1.2, label="autocorrelation of phi")
        osc = fixed.oscillation
        if osc and osc["detected"]:
            left.axvline(osc["period_s"], lw=0.8, ls=":", c="k",
                         label=f"period {osc['period_s']:.3g} s")  # fmt: skip
        if math.isfinite(tau):
            a = r.get("amplitude", 1.0)
            left.plot(lags[1:], a * np.exp(-lags[1:] / tau), "k--", lw=1,
                      label=f"{a:.2f} exp(-lag / {tau:.3g} s)")  # fmt: skip
    elif math.isfinite(tau):
        lags = np.linspace(0, 4 * tau, 200)
        left.plot(lags, np.exp(-lags / tau), "k--", lw=1, label=f"exp(-lag / {tau:.3g} s)")
    left.set_xlabel("lag (s)")
    left.set_title("relaxation of phi at the median inputs", fontsize=9)
    for v, h in enumerate(fixed.hazards):
        if h is None:
            continue
        age = np.asarray(h["age_s"])
        hazard = np.asarray(h["hazard"])
        if h["se"] is not None:
            right.errorbar(age, hazard, yerr=2 * np.asarray(h["se"]), fmt="o-", ms=3,
                           capsize=2, label=f"leaving {lumps[v]}")  # fmt: skip
        else:
            right.plot(age, hazard, lw=1.2, label=f"leaving {lumps[v]}")
        right.axhline(h["pooled"], lw=0.8, ls=":", c=f"C{v}")
    right.set_xscale("symlog", linthresh=max(dt, 1e-9))
    right.set_xlim(left=0)
    right.set_xlabel("time since phi last changed (s)")
    right.set_ylabel("P(phi changes in the next window)")
    right.set_title("hazard against age (constant = Markov)", fontsize=9)
    for ax in (left, right):
        if ax.get_legend_handles_labels()[0]:
            ax.legend(fontsize=7)
    return fig


def settling_text(summary: dict[str, Any]) -> str:
    """One line: the median point's settling times and the run's horizon."""
    s = summary["settling"]
    phi = f"phi {_fmt_s(s['phi_s'][0])}"
    if s["network_s"] is None:
        return phi
    unsettled = "" if all(summary["occupancy"]["settled"]) else ", not settled"
    return (f"network {_fmt_s(s['network_s'][0])}, {phi} at the median (horizon "
            f"{s['horizon_s']:.3g} s{unsettled})")  # fmt: skip


def relaxation_text(r: Mapping[str, Any]) -> str:
    """The lump's relaxation time as the report writes it (a bound where it is one)."""
    if r.get("bound") == "above":
        return (f"longer than the {r['max_lag_s']:g} s of lags measured (the autocorrelation "
                f"is still {r['acf_at_max_lag']:.2f} there)")  # fmt: skip
    if r.get("bound") == "below":
        return "shorter than a window"
    if r.get("bound") == "noise":
        return "not measured (the autocorrelation at one window is within its noise)"
    tau = r["tau_s"]
    more = " (at least: still correlated at the last lag)" if r.get("bound") == "above" else ""
    se = f" +- {r['se']:.2g}" if r.get("se") and math.isfinite(r["se"]) and r["se"] > 0 else ""
    return f"{tau:.3g}{se} s{more}"


def _fmt_s(value: float | None) -> str:
    if value is None or not math.isfinite(value):
        return "not within the run"
    return f"{value:.3g} s"


def report_markdown(summary: dict[str, Any], fixed: FixedInputs) -> str:  # noqa: C901  # one branch per optional section
    """``report.md``: the measurements of ``summary`` (inspect.json) with their figures."""
    lines = [f"# Inspection: {summary['model']}", "",
             f"`{summary['command']}` ({summary['wall_time_s']:.0f} s). phi = "
             f"{summary['lump_names'][1]} iff `{summary['lump']}`; dt = {summary['dt']:g} s.",
             ""]  # fmt: skip
    if summary["refused"]:
        lines += [f"**Refused:** {summary['refused']}.", ""]
    if summary.get("warning"):
        lines += [f"**Warning:** {summary['warning']}.", ""]
    net = summary["network"]
    if net is not None:
        lines += ["## The network", "",
                  "Species (initial counts): " + ", ".join(f"{k} = {v}" for k, v in
                                                          net["species"].items()) + "."]  # fmt: skip
        if net["global_parameters"]:
            lines.append("Global parameters: " + ", ".join(
                f"{k} = {v:.4g}" for k, v in net["global_parameters"].items()) + ".")  # fmt: skip
        if net["local_parameters"]:
            lines.append("Local parameters: " + ", ".join(
                f"{k} = {v:.4g}" for k, v in net["local_parameters"].items()) + ".")  # fmt: skip
        rows = [{"input": i["name"], "range": f"{i['low']:.4g} - {i['high']:.4g}",
                 "enters": ", ".join(i["reactions"]) or "-",
                 "largest change": max(i["sensitivity"].values(), default=0.0),
                 "flags": "; ".join(i["flags"])} for i in net["inputs"]]  # fmt: skip
        lines += ["", "Input parameters: the relative change of each propensity they enter "
                  "as the input moves across its range (others at their median), over the "
                  "states of the population runs:", "",
                  format_markdown_table(pd.DataFrame(rows), {"largest change": ".3g"})]  # fmt: skip
        flagged = [f"`{i['name']}` ({'; '.join(i['flags'])})" for i in net["inputs"]
                   if i["flags"]]  # fmt: skip
        if flagged and net["file_inputs"]:
            lines += [f"**Check:** {', '.join(flagged)}.", ""]
    lines += ["## The inputs the fields give", ""]
    rows = []
    for name, f in summary["population"]["fields"].items():
        row = {"field": name, "cells": f["cells"], "s": f["seconds"], "phi = 1": f["phi_share"]}
        for n, q in f["inputs"].items():
            row[n] = f"{q['low']:.4g} / {q['median']:.4g} / {q['high']:.4g}"
        rows.append(row)
    lines += ["Each input's low quantile / median / high quantile in a full-model population "
              "(from reproduce's start):", "",
              format_markdown_table(pd.DataFrame(rows), {"s": "g", "phi = 1": ".3f"})]  # fmt: skip
    lines += [f"- {n}" for n in summary["population"]["notes"]]
    occ = summary["occupancy"]
    grid = summary["grid"]
    rows = [{"point": "median" if a < 0 else grid["inputs"][a],
             **{n: x[i] for i, n in enumerate(grid["inputs"])},
             "P(phi = 1)": v, "se": s, "settled": st}
            for a, x, v, s, st in zip(grid["axis"], grid["x"], occ["value"], occ["se"],
                                      occ["settled"], strict=True)]  # fmt: skip
    lines += ["", "## phi's occupancy across that range", "",
              f"Stationary P(phi = 1) at fixed inputs ({occ['method']}):", "",
              format_markdown_table(pd.DataFrame(rows), {"P(phi = 1)": ".4f", "se": ".2g",
                                                         **{n: ".4g" for n in grid["inputs"]}}),
              f"![occupancy]({INPUT_OCCUPANCY_FIGURE})", ""]  # fmt: skip
    if occ.get("balanced"):
        bal = occ["balanced"]
        offer = (f"`lump: \"{bal['lump']}\"` would give {bal['occupancy']:.2f}, but the "
                 f"settings refuse it ({bal['refused']})" if bal.get("refused") else
                 f"`lump: \"{bal['lump']}\"`, would give {bal['occupancy']:.2f}")  # fmt: skip
        lines += [f"- phi = 1 in {bal['now']:.3g} of the time at the median inputs: one lump "
                  f"gives few windows to learn its switching from. The same species' threshold "
                  f"at its stationary law there, {offer}.", ""]  # fmt: skip
    s, b = summary["settling"], summary["burn_in"]
    lines += ["## Settling and relaxation", ""]
    settled = all(summary["occupancy"]["settled"])
    where = (f"every grid point settled within the run's {s['horizon_s']:.3g} s" if settled else
             f"**not every grid point settled within the run's {s['horizon_s']:.3g} s**: the "
             f"occupancies and what follows are those at its end, and the settling times lower "
             f"bounds")  # fmt: skip
    if s["network_s"] is not None:
        species = ", ".join(f"{k} {_fmt_s(v)}" for k, v in s["species_s_at_median"].items())
        slowest = max(max(s["network_s"]), max(s["phi_s"]))
        lines.append(f"- Settling from the file's counts at the median inputs (the time after "
                     f"which the mean stays within {summary['settings']['settle_tolerance']:.0%} "
                     f"or the noise of its final value): {species}; phi's occupancy "
                     f"{_fmt_s(s['phi_s'][0])}. The slowest grid point: {_fmt_s(slowest)}; "
                     f"{where}.")  # fmt: skip
    else:
        lines.append(f"- phi's occupancy from the model's initial state settles in "
                     f"{_fmt_s(s['phi_s'][0])} at the median inputs; {where}.")  # fmt: skip
    lines += [f"- {n}" for n in s["notes"]]
    r = summary["relaxation"]
    lines.append(f"- The lump's relaxation time at stationarity: {relaxation_text(r)} "
                 f"({r['method']}).")  # fmt: skip
    osc = summary.get("oscillation")
    if osc and osc["detected"]:
        crest = (f", peaks again at {osc['crest']:.2f} at {osc['period_s']:.3g} s (the period)"
                 if osc.get("crest") is not None else
                 f", the last lag measured (still falling: a period of at least "
                 f"{osc['period_s']:.3g} s; raise `inspect.record_windows` to measure it)"
                 if osc.get("bound") else
                 f" (no crest within the record: a period of ~{osc['period_s']:.3g} s)")  # fmt: skip
        coherence = osc.get("coherence_s")
        envelope = (f"; its envelope decays over {coherence:.3g} s (the time over which the "
                    f"cells forget their phase)" if coherence is not None
                    and math.isfinite(coherence) else "")  # fmt: skip
        lines.append(f"- **phi oscillates**: its autocorrelation dips to {-osc['depth']:.2f} "
                     f"at {osc['trough_s']:.3g} s{crest}{envelope}. The relaxation time above "
                     f"fits an exponential to the first fall only; the period and the "
                     f"envelope are the oscillation's time scales.")  # fmt: skip
    if b["applies"]:
        verdict = ("enough" if b["enough"] else
                   "above this lower bound, but not known to be enough until the run settles "
                   "(a larger `inspect.max_seconds` or `inspect.max_time`)"
                   if b["enough"] is None else
                   f"**too short: set `burn_in: {b['needed_s']:g}`** in the model's yaml "
                   f"(`++model.burn_in={b['needed_s']:g}`)")  # fmt: skip
        if b.get("refused"):
            verdict = (f"too short, but `burn_in: {b['needed_s']:g}` is not advised: the "
                       f"settings refuse it ({b['refused']})")  # fmt: skip
        bound = "" if b["settled"] else " at least (not settled within the run)"
        points = b.get("unsettled_points") or []
        basis = (f" (the settling, {b['settling_s']:.4g} s: {b['basis']}"
                 + (f"; grid points not settled: {', '.join(map(str, points))} of the "
                    f"occupancy table" if points else "") + ")" if b.get("basis") else "")  # fmt: skip
        lines.append(f"- Burn-in: model.burn_in = {b['burn_in_s']:g} s against "
                     f"{summary['settings']['burn_in_factor']:g} x the slowest settling = "
                     f"{b['needed_s']:g} s{bound}{basis}: {verdict}.")  # fmt: skip
    else:
        lines.append(f"- Burn-in: {b['text']}.")
    if fixed.settling_curves:
        lines.append(f"\n![settling]({SETTLING_FIGURE})")
    c = summary["cost"]
    lines += ["", "## Cost", ""]
    if c["events_per_window_model"] is not None:
        stationary = c["events_per_window_stationary"]
        lines.append(f"- SSA events per window of dt: {c['events_per_window_model']:.3g} from the "
                     f"file's counts (what the stages' budgets use), {stationary:.3g} at "
                     f"stationarity at the median inputs; per cell-step "
                     f"{c['cell_step_s_model']:.2g} s against {c['cell_step_s_measured']:.2g} "
                     f"s.")  # fmt: skip
    else:
        lines.append(f"- Per cell-step of the full model: {c['cell_step_s_model']:.2g} s.")
    probe = c.get("probe")
    if probe:
        lines.append(f"- Cost probe (before the runs): {probe['cells']} cells from the file's "
                     f"counts at its input values for {probe['horizon_s']:.3g} s in "
                     f"{probe['wall_s']:.2g} s, {probe['events_per_window_end']:.3g} SSA events "
                     f"per window at the end (at most {probe['events_per_window_max']:.3g}); "
                     f"the estimates below still use the file's counts.")  # fmt: skip
    stages = c["stages"]
    if stages["rows"]:
        table = pd.DataFrame(stages["rows"])[["stage", "what", "count", "cells", "steps",
                                              "estimate_s", "at_measured_s"]]  # fmt: skip
        table = table.rename(columns={"estimate_s": "estimate (s)",
                                      "at_measured_s": "at the measured events (s)"})  # fmt: skip
        lines += ["", "The stages of `scripts/reproduce.py` with these settings (the estimate of "
                  "each run; `count` runs of each):", "",
                  format_markdown_table(table, {"steps": ".3g", "estimate (s)": ".3g",
                                                "at the measured events (s)": ".3g"})]  # fmt: skip
    elif stages.get("note"):
        lines.append(f"- Stage costs {stages['note']}.")
    col = c["collection"]
    if col.get("recommended_n_per_state"):
        sw = col["switch_per_window"]
        needed_s = max(col["seconds_needed"])
        advised = col.get("advised")
        fix = (" or ".join(f"`{' '.join(o[1:])}`" for o in advised if len(o) > 1)
               if advised else "")  # fmt: skip
        short = (f", too short for {COLLECT_TIME_MARGIN:g} times that: {fix}" if fix
                 else ", too short") \
            if "max_time_needed" in col else ""  # fmt: skip
        blackout = (f" with the next command's `{' '.join(col['blackout'])}`"
                    if col.get("blackout") else "")  # fmt: skip
        # a lump the free population never visited in the collection's field cannot be timed
        timing = (f"it takes ~{needed_s:.3g} s of simulated time{blackout} (collect.max_time = "
                  f"{col['max_time']:g} s{short})" if math.isfinite(needed_s) else
                  f"its time cannot be estimated: the population in collect's field was never "
                  f"in one lump (the table above), so collect (collect.max_time = "
                  f"{col['max_time']:g} s) may stop early for want of its rows; choose a lump "
                  f"the cells visit there")  # fmt: skip
        more = f"`collect.n_per_state={col['recommended_n_per_state']}`"
        if advised == [] and col.get("refused"):  # none of the settings it needs runs
            more = f"{more}, but the settings refuse it, so it is not advised ({col['refused']})"
        lines.append(f"- Collection: phi changes in {sw[0]:.3g} (from "
                     f"{summary['lump_names'][0]}) and {sw[1]:.3g} (from "
                     f"{summary['lump_names'][1]}) of windows at the median inputs, so "
                     f"{summary['settings']['min_switches']:,} switches per origin need "
                     f"{max(col['rows_needed']):.3g} rows per origin"
                     + (f" (every switch kept, collect.keep_switches: a row stands for "
                        f"{col['windows_per_row']} windows)"
                        if col.get("windows_per_row", 1) > 1 else "")
                     + f": {more} (now "
                     f"{col['n_per_state']}), ~{col['cost_s']:.3g} s at the measured events; "
                     f"{timing}.")  # fmt: skip
        dense = col.get("dense")
        if dense and advised and "collect.record_every=1" in advised[0]:
            longer = [
                o for o in advised[0] if o.startswith(("collect.max_time", "collect.n_cells"))
            ]
            lines.append(f"- Recording every window (`collect.record_every=1`, now every "
                         f"{col['record_every']}th) gives the same rows, so the same switches, "
                         f"from ~{max(dense['seconds_needed']):.3g} s of simulated time"
                         + (f" (`{' '.join(longer)}`)" if longer else "")
                         + f", ~{dense['cost_s']:.3g} s at the measured events: the collection "
                         f"advised first (its rows are closer together in their inputs).")  # fmt: skip
    a, pilot = summary["recommendation"], summary.get("pilot") or {}
    lines += ["", "## The chain kind, measured", ""]
    lines.append(f"- Memory (the hazard of leaving phi against the time since it changed, at "
                 f"the median inputs): {summary['memory']['facts']['reason']}.")  # fmt: skip
    if a.get("kind") is None:
        lines.append(f"- The pilot's measured choice: {pilot.get('note') or a['reason']}. "
                     f"`gp=auto` (the default) makes it at full size when it trains.")  # fmt: skip
    else:
        keep = (f"`{' '.join(a['overrides'])}`" if a["overrides"]
                else "`gp=auto` (the default, as set)")  # fmt: skip
        if a.get("refused"):
            keep = (f"`gp=auto`; `{' '.join(a['overrides'])}` would be advised, but the settings "
                    f"refuse it: {a['refused']}")  # fmt: skip
        cap = (f" with the switch clock at the hazard's cap, {pilot['cap']:g} s, among them"
               if pilot.get("cap_added") else "")  # fmt: skip
        lines.append(f"- The pilot ({pilot['n_per_state']:,} rows per origin, "
                     f"{pilot['n_cells']} held-out cells x {pilot['t_end']:g} s; "
                     f"{pilot['wall_s']:.0f} s; the candidates of `gp.choice`{cap}) chose "
                     f"**{a['kind']}**. Recommended: {keep}: it measures the same candidates "
                     f"at full size and trains the best (docs/choice.md); a pilot of this size "
                     f"can rank close candidates otherwise."
                     + (f" The pilot {pilot['note']}." if pilot.get("note") else ""))  # fmt: skip
        if a.get("named") and not a.get("named_refused"):
            lines.append(f"- The pilot's choice named outright (skips the full-size "
                         f"measurement): `{' '.join(a['named'])}`.")  # fmt: skip
        if a.get("blackout"):
            lines.append(f"- The pilot's collection: rows soon after a jump switched at other "
                         f"rates than settled rows at the same inputs (collect's lag "
                         f"measurement, docs/choice.md); train leaves such rows out "
                         f"(`gp.jump_rows=auto`), and a collection with "
                         f"`{' '.join(a['blackout'])}` (in the next command below) records as "
                         f"many settled rows as it asks for.")  # fmt: skip
        lines += ["", pilot["text"]]
    if a.get("signal_bounds"):
        lines += ["", f"The network is enumerable: with `{a['signal_bounds']}` in the yaml (the "
                  f"inputs' range above), reproduce tabulates its exact chain, the method's "
                  f"limit, instead of computing exp(Q dt) at each cell's inputs every step."]  # fmt: skip
    lines += ["", f"![memory]({MEMORY_FIGURE})", ""]
    after = a.get("next")
    if after:
        lines += ["## Next", "",
                  f"`{after['command']}`: the settings above, the chain measured and trained, "
                  f"the full model beside it; its report says whether to trust it and, where "
                  f"it does, names the check at scale."]  # fmt: skip
        lines += [f"(Left out, refused together: {d}.)" for d in after.get("dropped") or []]
        lines.append("")
    return "\n".join(lines)


__all__ = [
    "INPUT_OCCUPANCY_FIGURE",
    "MEMORY_FIGURE",
    "SETTLING_FIGURE",
    "plot_memory",
    "plot_occupancy",
    "plot_settling",
    "relaxation_text",
    "report_markdown",
    "settling_text",
]
