"""How long a collection's cells remember a jump: each origin's switching rate in the rows a
few seconds after a perturbation, against the rate of rows long after one (or never
perturbed) at the same inputs and switch clock.

A jump moves a cell to new inputs with the hidden state of the old ones; the rows recorded
before that state has settled switch at other rates than a population cell's at the same
inputs, and psi learns their bias. ``collect.blackout_time`` keeps rows within it out of the
table; this measures, in the table a collection made, whether the rows just after the blackout
still lag (Tyson's oscillator: rows in `y_high` for 20 s or more at kt > 25 left it 5x as often
within 2 s of a jump as 20-40 s after; the dimerisation: `many_dimers` left 17 % more often
0-2 s after a jump, 4.6 % 10-20 s after; docs/choice.md). It reports, and names the blackout
that keeps the lagging rows out (:func:`blackout_advice`); the blackout is the user's (a
network yaml's ``collect``).

Rates are matched on the inputs and the clock, and again on the inputs alone: a jump carries
the old inputs' spread of clocks, which the clock's psi reads but the two-state chain's psi
(and the hidden phases' means, matched to it) averages over. CERENA's gene-expression network
(`Protein >= 40`): matched with the clock, no bin past 6 %; without it, `high` rows switched at
0.51x the settled rate 0-2 s after a jump and 0.83x 2-5 s after, and the two-state psi was
7-12 % low where the population lives.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import pandas as pd

from surrogate.gp.windows import row_windows

#: seconds after a jump: the bins compared (the last one open to :data:`SETTLED_AFTER`)
AFTER_JUMP_EDGES = (0.0, 2.0, 5.0, 10.0)
#: rows this long after a jump (or never perturbed) are the settled reference
SETTLED_AFTER = 20.0
#: equal-count bins per input, and the clock's edges (s), that rates are matched in
INPUT_BINS = 16
CLOCK_EDGES = (0.5, 1.0, 2.0, 5.0, 10.0, 20.0)
#: settled rows per origin below which nothing is measured
MIN_SETTLED_ROWS = 1000
#: a bin lags where its rate ratio is this many standard errors from 1 ...
LAG_SE = 3.0
#: ... and this far from it (E. coli's methylation lag, +-2 to 9 % in these bins, is below it;
#: the dimerisation's 11 % and Tyson's 13 % in the first 2 s, which moved means by 5-10 %, above)
LAG_RATIO = 0.10
#: the note on a lump whose rows lag only where matched without the clock
NO_CLOCK = " (without the clock)"
#: the share of a collected cell's time the advised blackout may take (Tyson's 20 s at one
#: jump per 40 s; E. coli's default, 1 s at 0.1 per s, is 0.1)
BLACKOUT_SHARE = 0.5


def after_jump_lag(
    table: pd.DataFrame, inputs: Sequence[str], dt: float, lump_names: Sequence[str]
) -> dict[str, Any] | None:
    """Each origin's switching rate in rows ``[a, b)`` s after a jump over the rate expected
    from the settled rows (``since_jump`` < 0 or >= :data:`SETTLED_AFTER` s) in the same input
    and clock bins: observed / expected switches, with its Poisson standard error.

    Args:
        table: a collection's rows (``phi``, ``phi_next``, ``since_jump`` in windows, the
            ``inputs`` columns, ``phi_age`` where recorded).
        inputs: the input columns rates are matched on.
        dt: the window (s).
        lump_names: phi's names, for the record.

    Returns:
        ``{"settled_after_s", "origins": {lump: [{"from_s", "to_s", "rows", "ratio",
        "se"}, ...]}, "lagging": [(lump, from_s, to_s, ratio), ...]}``, with
        ``"origins_without_clock"`` (the same, matched on the inputs alone) where the table
        records the clock; a lump that lags only there is named with :data:`NO_CLOCK`. None
        where the table has no jumps' clocks or too few settled rows for an origin.
    """
    if "since_jump" not in table.columns or len(table) == 0:
        return None
    since = table["since_jump"].to_numpy(np.float64)
    jumped = since >= 0
    after = since * dt
    settled = settled_rows(since, dt, SETTLED_AFTER)
    phi = table["phi"].to_numpy()
    switched = (table["phi_next"].to_numpy() != phi).astype(np.float64)
    # rows weighted by the windows they stand for (a collection that keeps every switch)
    windows = row_windows(table)
    weight = np.ones(len(table)) if windows is None else windows
    out: dict[str, Any] = {"settled_after_s": SETTLED_AFTER, "origins": {}, "lagging": []}
    # matched on the clock where it is recorded (what a clock's psi reads), and on the inputs
    # alone (what the two-state chain's psi reads, and the hidden phases' means from it): a
    # jump leaves the clocks' spread of the old inputs, which only the clock-free rates see
    views = [("origins", _cells(table, inputs, clock=True), "")]
    if "phi_age" in table.columns:
        views.append(("origins_without_clock", _cells(table, inputs, clock=False), NO_CLOCK))
    for key, cell, note in views:
        origins = _lags(cell, phi, switched, weight, jumped, after, settled, lump_names)
        if origins is None:
            return None
        out[key] = origins
        seen = {(lump, lo) for lump, lo, _, _ in out["lagging"]}  # the clock's view first
        for lump, bins in origins.items():
            out["lagging"] += [(lump + note, b["from_s"], b["to_s"], b["ratio"]) for b in bins
                               if (lump, b["from_s"]) not in seen and _lags_by(b)]  # fmt: skip
    return out


def _lags_by(b: dict[str, float]) -> bool:
    """Whether a bin's ratio is off by more than :data:`LAG_RATIO` and :data:`LAG_SE` SEs."""
    ratio = b["ratio"]
    return math.isfinite(ratio) and abs(ratio - 1.0) > max(LAG_SE * b["se"], LAG_RATIO)


def _lags(
    cell: np.ndarray,
    phi: np.ndarray,
    switched: np.ndarray,
    weight: np.ndarray,
    jumped: np.ndarray,
    after: np.ndarray,
    settled: np.ndarray,
    lump_names: Sequence[str],
) -> dict[str, list[dict[str, float]]] | None:
    """Each origin's bins of :func:`after_jump_lag` with rates matched in ``cell``, each row
    counted as the windows it stands for (``weight``); None where an origin has too few
    settled rows."""
    edges = (*AFTER_JUMP_EDGES, SETTLED_AFTER)
    size = int(cell.max()) + 1
    out: dict[str, list[dict[str, float]]] = {}
    for origin in (0, 1):
        rows = phi == origin
        ref = rows & settled
        if int(ref.sum()) < MIN_SETTLED_ROWS:
            return None
        n = np.bincount(cell[ref], weights=weight[ref], minlength=size)
        k = np.bincount(cell[ref], weights=(switched * weight)[ref], minlength=size)
        rate = k / np.maximum(n, 1)
        known = n[cell] >= 20  # a rate from a handful of settled windows is noise
        bins = []
        for lo, hi in itertools.pairwise(edges):
            sel = rows & jumped & known & (after >= lo) & (after < hi)
            observed = float((switched * weight)[sel].sum())
            expected = float((rate[cell[sel]] * weight[sel]).sum())
            ratio = observed / expected if expected > 0 else math.nan
            se = math.sqrt(max(observed, 1.0)) / expected if expected > 0 else math.nan
            bins.append({"from_s": lo, "to_s": hi, "rows": int(sel.sum()), "ratio": ratio,
                         "se": se})  # fmt: skip
        out[str(lump_names[origin])] = bins
    return out


def _cells(table: pd.DataFrame, inputs: Sequence[str], clock: bool = True) -> np.ndarray:
    """Each row's cell: equal-count bins of every input, times the clock's bins where the
    table records the clock and ``clock`` asks for it."""
    cell = np.zeros(len(table), dtype=np.int64)
    for name in inputs:
        x = table[name].to_numpy(np.float64)
        edges = np.unique(np.quantile(x, np.linspace(0.0, 1.0, INPUT_BINS + 1))[1:-1])
        cell = cell * (len(edges) + 1) + np.searchsorted(edges, x, side="right")
    if clock and "phi_age" in table.columns:
        age = table["phi_age"].to_numpy(np.float64)
        cell = cell * (len(CLOCK_EDGES) + 1) + np.searchsorted(CLOCK_EDGES, age, side="right")
    return cell


def outlasts(lag: Mapping[str, Any]) -> bool:
    """Whether rows still lag in the last bin before they count as settled (10-20 s after a
    jump): then the settled rows lag too, and no blackout this measurement can name keeps the
    lag out. The auto-regulatory network (a protein count relaxing over ~1,900 s): `low` rows
    at 0.84-0.85x in every bin without the clock, flat through 20 s."""
    until = float(lag["settled_after_s"])
    return any(hi >= until for _, _, hi, _ in lag["lagging"])


def lagging_window(lag: Mapping[str, Any] | None) -> float | None:
    """The seconds after a jump whose rows train leaves out of the fit by default
    (``gp.jump_rows=auto``): :data:`SETTLED_AFTER` (``lag["settled_after_s"]``) where rows
    lagged and the lag ends within the measurement; None where nothing lagged or it outlasts
    the measurement (:func:`outlasts`: the rows after it lag too). Rows this measurement
    counts as settled are the ones a blackout of that length would have recorded: CERENA's
    gene-expression network, its default collection 14 of 24 at the issue's check, the same
    collection's settled rows alone (16 % of them) 19 of 24, as a collection with the blackout
    (docs/choice.md)."""
    if not lag or not lag.get("lagging") or outlasts(lag):
        return None
    return float(lag["settled_after_s"])


def settled_rows(since_jump: np.ndarray, dt: float, window: float) -> np.ndarray:
    """Which rows lie ``window`` s or more after their cell's last jump, or before its first
    (``since_jump``: windows since the jump, -1 where none; ``dt``: the window, s)."""
    since = np.asarray(since_jump, dtype=np.float64)
    # in windows, with a hair of slack: a blackout of ceil(window / dt) steps records only these
    return (since < 0) | (since >= window / dt - 1e-6)


def blackout_advice(
    lag: dict[str, Any] | None, blackout: float, perturb_rate: float
) -> tuple[str, ...]:
    """The collection that keeps the lagging rows out: ``collect.blackout_time`` at
    :data:`SETTLED_AFTER` (``lag["settled_after_s"]``: every row recorded is then one this
    measurement counts as settled), and ``collect.perturb_rate`` lowered where needed so that
    a cell spends at most :data:`BLACKOUT_SHARE` of its time blacked out (one jump per
    ``1 / rate`` s on average); empty where nothing lags, and where the lag lasts through the
    last bin (:func:`outlasts`). Not the end of the last bin that lags: the dimerisation's
    first 2 s lag by 11 %, the next 18 s by 4-7 % (significant in one collection, not in
    another), and only 20 s took psi's bias out (-6.6 to +0.3 %).

    Example:
        >>> blackout_advice({"settled_after_s": 20.0, "lagging": [("y_low", 0.0, 2.0, 0.87)]},
        ...                 1.0, 0.1)
        ('collect.blackout_time=20', 'collect.perturb_rate=0.025')
    """
    until = lagging_window(lag)  # the rows a settled collection would not record
    if until is None or until <= blackout:
        return ()
    advice = [f"collect.blackout_time={until:g}"]
    if perturb_rate * until > BLACKOUT_SHARE:
        advice.append(f"collect.perturb_rate={BLACKOUT_SHARE / until:g}")
    return tuple(advice)


def lag_message(
    lag: dict[str, Any] | None,
    blackout: float,
    advice: Sequence[str] = (),
    refused: str = "",
    topped_up: str = "",
) -> str | None:
    """The log line where rows after the blackout still lag (None where none does, or
    nothing was measured), with ``advice`` (:func:`blackout_advice`, checked by the caller)
    or why the checks ``refused`` it, or what collect's top-up recorded (``topped_up``)."""
    if not lag or not lag["lagging"]:
        return None
    parts = [f"{lump} {ratio:.2f}x {lo:g}-{hi:g} s after"
             for lump, lo, hi, ratio in lag["lagging"]]  # fmt: skip
    window = lagging_window(lag)
    dropped = ("" if window is None else
               f"train leaves the rows within {window:g} s of a jump out of the fit "
               f"(gp.jump_rows=auto, the default); ")  # fmt: skip
    if topped_up:
        fix = f"{dropped}{topped_up}"
    elif advice:
        what = "only settled rows, more of them" if dropped else "none of those rows"
        fix = (f"{dropped}collect with `{' '.join(advice)}` (or in a network yaml's `collect:`) "
               f"to record {what}")  # fmt: skip
    elif outlasts(lag):
        fix = (f"the lag lasts through the last bin, so rows {lag['settled_after_s']:g} s after "
               f"a jump lag too and no blackout measured here keeps it out: the network holds "
               f"a hidden state slower than that, which a kind that carries it (K lumps whose "
               f"bins relax) holds and a blackout does not")  # fmt: skip
    else:
        fix = (f"{dropped}a longer blackout (a network yaml's collect.blackout_time, with a "
               f"lower collect.perturb_rate) keeps those rows out of the collection"
               + (f" (the measured one was refused: {refused})" if refused else ""))  # fmt: skip
    alone = ("; without the clock: at the same inputs alone, as the two-state psi reads them"
             if any(NO_CLOCK in lump for lump, *_ in lag["lagging"]) else "")  # fmt: skip
    return (
        f"rows soon after a jump switch at other rates than rows {lag['settled_after_s']:g} s "
        f"or more after, at the same inputs and clock ({'; '.join(parts)}{alone}): the network's "
        f"hidden state still lags the jump past collect.blackout_time={blackout:g} s"
        f"{'' if dropped else ', and psi learns that lag'}; {fix} (docs/choice.md)"
    )


__all__ = [
    "AFTER_JUMP_EDGES",
    "BLACKOUT_SHARE",
    "SETTLED_AFTER",
    "after_jump_lag",
    "blackout_advice",
    "lag_message",
    "lagging_window",
    "outlasts",
    "settled_rows",
]
