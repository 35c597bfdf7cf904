"""The abstraction the inspection recommends (item 6), and the settings it offers beside it:
``signal_bounds``, a balanced threshold, the collection's overrides.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np

from surrogate.diagnosis.fixed import FixedInputs
from surrogate.diagnosis.options import InspectOptions
from surrogate.diagnosis.population import Population
from surrogate.diagnosis.settling import (
    RELAXATION_BINS,
    SLOW_SETTLING_WINDOWS,
    round_up,
    settling_estimate,
)
from surrogate.gp.class_relaxation import CELLS_PER_BIN, relaxation_cells
from surrogate.models.base import Model
from surrogate.models.capabilities import lump_expr_of, signal_bounds_of
from surrogate.models.count_classes import threshold_of
from surrogate.models.network import NetworkInternalModel


def collection_overrides(collection: Mapping[str, Any]) -> list[list[str]]:
    """The collection advice (:func:`collection_budget`) as override sets: the rows per origin,
    with the longer run or (else) the more cells it needs where ``collect.max_time`` is too
    short; empty where nothing is advised."""
    if not collection.get("recommended_n_per_state"):
        return []
    rows = f"collect.n_per_state={collection['recommended_n_per_state']}"
    if "max_time_needed" not in collection:
        return [[rows]]
    out = [[rows, f"collect.max_time={collection['max_time_needed']:g}"]]
    if "n_cells_needed" in collection:
        out.append([rows, f"collect.n_cells={collection['n_cells_needed']}"])
    return out


def signal_bounds_advice(
    internal: Any, fixed: FixedInputs, ranges: Mapping[str, tuple[float, float]]
) -> str | None:
    """The yaml's ``signal_bounds`` over the inputs' range the fields give, for an enumerable
    network that declares none (its exact chain, the method's limit, is then a table rather
    than exp(Q dt) per cell and step); else None."""
    if not fixed.exact or not ranges or signal_bounds_of(internal) is not None:
        return None
    listed = ", ".join(f"{n}: [{lo!r}, {hi!r}]" for n, (lo, hi) in ranges.items())
    return f"signal_bounds: {{{listed}}}"


#: outside this band of phi's occupancy at the median inputs the report offers a threshold
#: that balances the lumps there (one lump then gives few windows to learn its switching from)
BALANCE_BAND = (0.1, 0.9)


def balanced_threshold(internal: Any, fixed: FixedInputs) -> dict[str, Any] | None:
    """For a threshold lump whose occupancy at the median inputs lies outside
    :data:`BALANCE_BAND`: the threshold on the same species, at its stationary law there, that
    puts phi = 1 nearest 1/2 (``{"lump": "P2 >= 87", "occupancy": 0.49, "now": 0.0033}``);
    else None."""
    threshold = threshold_lump(internal)
    now = float(fixed.occupancy[0])
    if threshold is None or BALANCE_BAND[0] <= now <= BALANCE_BAND[1]:
        return None
    species, _, upper = threshold
    if species not in fixed.species_law:
        return None
    values, weights = (np.asarray(a, float) for a in fixed.species_law[species])
    if weights.sum() <= 0:
        return None
    levels = np.unique(values)
    # P(count >= v) at each level v
    at_least = np.array([weights[values >= v].sum() for v in levels]) / weights.sum()
    share = at_least if upper else 1.0 - at_least
    best = int(np.argmin(np.abs(share - 0.5)))
    edge = int(levels[best])
    return {
        "lump": f"{species} {'>=' if upper else '<'} {edge}",
        "occupancy": float(share[best]),
        "now": now,
    }


def threshold_lump(internal: Any) -> tuple[str, int, bool] | None:
    """``(species, edge, upper)`` where the lump is a threshold on one species count: phi = 1
    iff ``count >= edge`` (``upper``) or ``count < edge``; None for any other lump."""
    return threshold_of(lump_expr_of(internal))


def _weighted_quantile(values: np.ndarray, weights: np.ndarray, q: float) -> float:
    order = np.argsort(values, kind="stable")
    cum = np.cumsum(weights[order])
    return float(values[order][min(np.searchsorted(cum, q * cum[-1]), values.size - 1)])


def class_edges(values: np.ndarray, weights: np.ndarray, edge: int, per_side: int) -> list[int]:
    """Bins of a species count for K lumps: the threshold ``edge`` and, on each side, edges at
    the ``j / per_side`` quantiles of the species' stationary law there (integers strictly
    inside the side; a side without mass gets none)."""
    edges = {int(edge)}
    below = values < edge
    for low in (True, False):
        w = weights * (below if low else ~below)
        if not w.sum() > 0:
            continue
        for j in range(1, per_side):
            cut = math.ceil(_weighted_quantile(values, w, j / per_side))
            if (low and 0 < cut < edge) or (not low and cut > edge):
                edges.add(cut)
    return sorted(e for e in edges if e > 0)


def input_ranges(
    network: NetworkInternalModel | None, population: Population
) -> dict[str, tuple[float, float]]:
    """Each kinetic input's range over the fields (the lowest low and highest high quantile of
    :attr:`Population.fields`), widened outward to two significant digits; inputs the fields
    leave at one value are left out."""
    if network is None:
        return {}
    out = {}
    for name in network.kinetics.input_names:
        spans = [f["inputs"][name] for f in population.fields.values() if name in f["inputs"]]
        if not spans:
            continue
        lo, hi = min(s["low"] for s in spans), max(s["high"] for s in spans)
        if hi > lo:
            out[name] = (round_sig(lo, math.floor), round_sig(hi, math.ceil))
    return out


def round_sig(value: float, to: Callable[[float], int], digits: int = 2) -> float:
    """``value`` rounded with ``to`` (floor / ceil) at ``digits`` significant digits."""
    if value == 0:
        return 0.0
    scale = 10 ** (digits - 1 - math.floor(math.log10(abs(value))))
    return to(value * scale) / scale


def recommend(
    model: Model,
    fixed: FixedInputs,
    options: InspectOptions,
    dt: float,
    input_ranges: Mapping[str, tuple[float, float]] | None = None,
) -> dict[str, Any]:
    """Item 6: the abstraction the memory measured at the median inputs calls for.

    ``input_ranges``: the network's kinetic inputs' range the fields give (:func:`input_ranges`):
    ``classes: auto`` then chooses its bins over that range, not at the file's values alone."""
    internal = model.internal
    hazards = fixed.hazards
    if fixed.memory is None:
        return {"abstraction": None, "command": "", "yaml": "",
                "reason": "phi does not switch both ways at the median inputs, so its memory "
                          "cannot be measured there"}  # fmt: skip
    exact = fixed.exact

    def describe(h: dict[str, Any], v: int) -> str:
        name = internal.lump_names[v]
        first = h["hazard"][0]
        if exact:
            test = f", departing from it by up to {h['effect']:.0%} with the age"
        else:
            departs = (f"age bins departing by up to {h['effect']:.0%} (beyond 3 standard "
                       f"errors)" if h["effect"] > 0 else "no age bin beyond 3 standard "
                       "errors")  # fmt: skip
            test = f", {departs}, chi-square p = {h['p_value']:.2g} over {h['df'] + 1} bins"
        return (f"leaving {name}: {first:.3g} per window at age 0 against {h['pooled']:.3g} "
                f"overall{test}")  # fmt: skip

    facts = "; ".join(describe(h, v) for v, h in enumerate(hazards) if h is not None)
    if not fixed.memory:
        return {"abstraction": "two-state", "command": "gp=svgp (what the default, gp=auto, runs for a model without classes)", "yaml": "",
                "overrides": ["gp=svgp"],
                "reason": f"the hazard of leaving each lump does not depend on the time since "
                          f"phi last changed ({facts}): phi's switching is Markov in the "
                          f"current input, as the two-state chain assumes"}  # fmt: skip
    threshold = threshold_lump(internal)
    if fixed.oscillation is not None and fixed.oscillation["detected"]:
        species = threshold[0] if threshold is not None else None
        return oscillation_advice(fixed.oscillation, internal.lump_names, facts, dt, species)
    if threshold is not None and threshold[0] in fixed.species_law:
        species, edge, upper = threshold
        values, weights = fixed.species_law[species]
        edges = class_edges(np.asarray(values, float), np.asarray(weights, float), edge,
                            int(options.classes_per_side))  # fmt: skip
        # each lump's bins on its own side of the threshold (model.classes' edges by lump)
        below, above = [e for e in edges if e < edge], [e for e in edges if e > edge]
        by_lump = dict(zip(internal.lump_names, (below, above) if upper else (above, below),
                           strict=True))  # fmt: skip
        # quoted: YAML reads bare off/on/yes/no as booleans
        listed = ", ".join(f'"{n}": [{", ".join(str(e) for e in v)}]' for n, v in by_lump.items())
        declared = f"classes: {{species: {species}, edges: {{{listed}}}}}"
        # a network can let the toolkit choose the count by measurement (the slow count that
        # holds the memory need not be the lump's species): model.classes=auto
        auto = isinstance(internal, NetworkInternalModel)
        over = ", ".join(f"{n}: [{lo!r}, {hi!r}]" for n, (lo, hi) in (input_ranges or {}).items())
        # a count that settles over many windows moves between bins too rarely per window to
        # learn, and its jitter across an edge reads as moves: its bins relax instead, finer
        est = settling_estimate(fixed, float(options.settle_tolerance))
        settling = est["seconds"]
        slow = auto and settling >= SLOW_SETTLING_WINDOWS * dt
        auto_options = [f"over: {{{over}}}"] if over else []
        if slow:
            # relaxation needs bins shared by both lumps: never the lump's own count's
            auto_options += [f"bins: {RELAXATION_BINS}", "shared: true"]
        yaml = (f"classes: {{auto: {{{', '.join(auto_options)}}}}}" if auto_options
                else "classes: auto") if auto else declared  # fmt: skip
        command = "gp=classes gp.class_moves=relaxation" if slow else "gp=classes"
        basis = f": {est['basis']}" if est["basis"] else ""
        relax = (f"; the network settles over {settling:.4g} s ({settling / dt:,.0f} windows"
                 f"{basis}), at least the {SLOW_SETTLING_WINDOWS:,} windows from which the bins "
                 f"move by relaxation to their stationary law (`gp.class_moves=relaxation`), "
                 f"not by a one-window law learned from rare, jittery crossings; "
                 f"{RELAXATION_BINS} bins per lump, the flips given each bin being learned from "
                 f"the windows, not from crossings, and the stationary sample "
                 f"{relaxation_cells(RELAXATION_BINS)} cells, {CELLS_PER_BIN} per bin" if slow else
                 f"; the network settles over {settling:.4g} s ({settling / dt:,.0f} windows"
                 f"{basis}), below the {SLOW_SETTLING_WINDOWS:,} windows from which bins relax "
                 f"(`gp.class_moves=relaxation`){est['caveat']}" if auto else "")  # fmt: skip
        # the lump's own species' bins, each lump's own: learned moves only (bins that relax
        # must hold both lumps), so offered beside auto with gp=classes alone
        alternative = {"overrides": ["gp=classes"], "yaml": declared,
                       "text": f"bins of the lump's own species at its stationary quantiles on "
                               f"each side of {edge}" + (", each lump's own (so learned moves, "
                               "not relaxation)" if slow else "")} if auto else None  # fmt: skip
        return {"abstraction": "classes", "command": command, "yaml": yaml,
                "overrides": command.split(),
                "settling_s": settling, "settling_basis": est["basis"],
                "declared": declared, "edges": edges, "edges_by_lump": by_lump,
                "species": species, "alternative": alternative,
                "reason": f"phi's switching has memory ({facts}) and the lump is a threshold on "
                          f"{species}: classes over bins of a count carry the hidden state"
                          + (" (`classes: auto` chooses the count whose bins best predict "
                             "the next phi, by a short seeded run"
                             + (" over the inputs' range the fields give" if over else "")
                             + ")" if auto else
                             f": bins of {species} at its stationary quantiles on each side of "
                             f"{edge}") + relax}  # fmt: skip
    flat = max(h["flat_from_s"] for h in hazards if h is not None)
    max_age = float(f"{max(flat, dt):.2g}")
    return {"abstraction": "clock", "command": f"gp=clock gp.max_age={max_age:g}", "yaml": "",
            "overrides": ["gp=clock", f"gp.max_age={max_age:g}"], "max_age": max_age,
            "reason": f"phi's switching has memory ({facts}); the lump is not a threshold on one "
                      f"species, so the switch clock carries it: the hazard is flat from "
                      f"{flat:.3g} s since the last change"}  # fmt: skip


def oscillation_advice(
    osc: Mapping[str, Any], lump_names: Sequence[str], facts: str, dt: float,
    species: str | None = None,
) -> dict[str, Any]:  # fmt: skip
    """The switch clock for a lump that oscillates (:func:`oscillation_dict`), whatever the
    lump: the memory is the cycle's phase, which the time since phi last changed measures, not
    a count near a threshold that bins of it would hold. ``gp.max_age``: the largest of the
    period and the 90th percentile of either lump's segment durations (a cycle is one segment
    of each lump, so the clock covers the ages at which the segments end), at the median inputs
    and, where measured (``osc["over_range"]``: every grid point exactly, the ends of each
    input's range simulated), wherever phi oscillates over the range the fields give (a period
    that grows towards one end would outrun a cap from the median's), rounded up to two
    significant digits. ``species``: the threshold lump's species (the reason says why not
    classes over it)."""
    period = float(osc["period_s"])
    segments = [s for s in (osc.get("segments") or []) if s is not None]
    # the period (and the segments) wherever phi oscillates over the fields' range: the clock
    # must cover the longest cycle the population meets, not the median inputs' alone
    others = [p for p in (osc.get("over_range") or []) if p["detected"]]
    longest = max([period, dt] + [s["q90_s"] for s in segments]
                  + [p["period_s"] for p in others]
                  + [p["q90_s"] for p in others if p.get("q90_s") is not None])  # fmt: skip
    max_age = round_up(longest)
    over = osc.get("over_range")
    if over:
        slowest = max(others, key=lambda p: p["period_s"], default=None)
        quiet = [p["at"] for p in over if not p["detected"]]
        across = (f"; over the range the fields give, the period is at most "
                  f"{slowest['period_s']:.3g} s ({slowest['at']})" if slowest is not None else
                  "; over the range the fields give it oscillates at the median alone")  # fmt: skip
        if quiet:
            across += f" (no oscillation found at {', '.join(quiet)})"
    else:
        across = ("; measured at the median inputs only (the range's ends not recorded, or "
                  "one value of each input)")  # fmt: skip
    trough = (f"its autocorrelation dips to {-osc['depth']:.2f}"
              + (f" +- {osc['depth_se']:.2g}" if osc["depth_se"] else "")
              + f" at a lag of {osc['trough_s']:.3g} s")  # fmt: skip
    if osc.get("crest") is not None:
        coherence = osc.get("coherence_s")
        forget = (f"; the cells forget their phase over ~{coherence:.3g} s" if coherence
                  is not None and math.isfinite(coherence) else "")  # fmt: skip
        trough += (f" and peaks again at {osc['crest']:.2f} at {period:.3g} s (the period"
                   f"{forget})")  # fmt: skip
    elif osc.get("bound"):
        trough += (f", the last lag measured (still falling: a period of at least "
                   f"{period:.3g} s; a longer record, `inspect.record_windows`, measures it)")  # fmt: skip
    else:
        trough += f" (no crest within the record: a period of about twice that, {period:.3g} s)"
    regular = ""
    if osc.get("segments"):
        parts = [f"{name} segments {s['mean_s']:.3g} s on average, coefficient of variation "
                 f"{s['cv']:.2f}, 90 % within {s['q90_s']:.3g} s"
                 for name, s in zip(lump_names, osc["segments"], strict=True) if s is not None]  # fmt: skip
        regular = (f"; {'; '.join(parts)} (a memoryless lump's durations are exponential, "
                   f"coefficient of variation 1)") if parts else ""  # fmt: skip
    why_not = (f". Classes over bins of {species} (the lump is a threshold on it) would hold "
               f"a count, not the phase" if species else "")  # fmt: skip
    return {"abstraction": "clock", "command": f"gp=clock gp.max_age={max_age:g}", "yaml": "",
            "overrides": ["gp=clock", f"gp.max_age={max_age:g}"],
            "max_age": max_age, "oscillation": True, "period_s": period,
            "reason": f"phi oscillates: {trough}, and no reversible network nor memoryless lump "
                      f"gives a negative autocorrelation (the check: below "
                      f"-{osc['depth_threshold']:g} and beyond {osc['z']:.1f} standard errors)"
                      f"{regular}. Its switching's memory ({facts}) is the cycle's phase, which "
                      f"the time since phi last changed measures: the switch clock carries it, "
                      f"its age capped at `gp.max_age={max_age:g}` s, the largest of the "
                      f"periods and the 90th percentiles of the segments' durations where the "
                      f"population lives{across}, so that it covers the ages at which both "
                      f"lumps' segments end{why_not}"}  # fmt: skip


__all__ = [
    "BALANCE_BAND",
    "balanced_threshold",
    "class_edges",
    "collection_overrides",
    "input_ranges",
    "oscillation_advice",
    "recommend",
    "round_sig",
    "signal_bounds_advice",
    "threshold_lump",
]
