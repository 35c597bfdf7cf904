"""The memory the inspection measured (item 6: facts, and the switch clock's cap they suggest;
the kind is the pilot's measured choice, :mod:`surrogate.stages.pilot`), and the settings it
offers beside it: ``signal_bounds``, a balanced threshold, the collection's overrides.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np

from surrogate.diagnosis.fixed import FixedInputs
from surrogate.diagnosis.population import Population
from surrogate.diagnosis.settling import round_up
from surrogate.models.base import Model
from surrogate.models.capabilities import lump_expr_of, signal_bounds_of
from surrogate.models.count_classes import threshold_of
from surrogate.models.network import NetworkInternalModel

#: ``collect.max_time`` is a cap (collect stops once it has its rows), advised at this many
#: times the simulated time estimated: the estimate reads each lump's share in the free
#: population, and collect's cells sit where its perturbation puts them (Wilkinson's
#: immigration-death: `low` in 32 % of the collection's windows against 42 % of the
#: population's, 1.3x the time; the run advised at the estimate stopped short)
COLLECT_TIME_MARGIN = 2.0


def collection_overrides(collection: Mapping[str, Any]) -> list[list[str]]:
    """The collection advice (:func:`collection_budget`) as override sets: the rows per origin,
    with the longer run or (else) the more cells it needs where ``collect.max_time`` is too
    short; first, where offered (``dense``), the same with every window recorded
    (``collect.record_every=1``); empty where nothing is advised."""
    if not collection.get("recommended_n_per_state"):
        return []
    rows = f"collect.n_per_state={collection['recommended_n_per_state']}"
    dense = collection.get("dense")
    out = [[rows, "collect.record_every=1", *extra] for extra in _longer(dense)] if dense else []
    return out + [[rows, *extra] for extra in _longer(collection)]


def _longer(timing: Mapping[str, Any]) -> list[list[str]]:
    """The settings that give a collection's rows in time: none where ``collect.max_time``
    suffices, else the longer run, then (where it can) more cells."""
    if "max_time_needed" not in timing:
        return [[]]
    out = [[f"collect.max_time={timing['max_time_needed']:g}"]]
    if "n_cells_needed" in timing:
        out.append([f"collect.n_cells={timing['n_cells_needed']}"])
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


def memory_facts(model: Model, fixed: FixedInputs, dt: float) -> dict[str, Any]:
    """Item 6: what the memory measured at the median inputs says; no kind (the inspector's
    pilot measures which chain holds phi, :mod:`surrogate.stages.pilot`).

    Returns:
        ``memory``: None (phi does not switch both ways there), False (the hazard of leaving
        each lump does not depend on the time since phi changed: Markov) or True; ``reason``:
        the hazards in words (and the oscillation where phi oscillates); ``max_age``: where
        there is memory, the switch clock's cap it suggests (s; where the hazard flattens, or
        the longest cycle where phi oscillates, :func:`oscillation_cap`), which the pilot adds
        to its candidates, else None; ``oscillation``: whether phi oscillates.
    """
    internal = model.internal
    hazards = fixed.hazards
    if fixed.memory is None:
        return {"memory": None, "max_age": None, "oscillation": False,
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
        return {"memory": False, "max_age": None, "oscillation": False,
                "reason": f"the hazard of leaving each lump does not depend on the time since "
                          f"phi last changed ({facts}): phi's switching is Markov in the "
                          f"current input, as the two-state chain assumes"}  # fmt: skip
    if fixed.oscillation is not None and fixed.oscillation["detected"]:
        return oscillation_cap(fixed.oscillation, internal.lump_names, facts, dt)
    flat = max(h["flat_from_s"] for h in hazards if h is not None)
    max_age = float(f"{max(flat, dt):.2g}")
    return {"memory": True, "max_age": max_age, "oscillation": False,
            "reason": f"phi's switching has memory ({facts}): the hazard is flat from "
                      f"{flat:.3g} s since the last change, so a switch clock would cap its "
                      f"age at {max_age:g} s"}  # fmt: skip


def oscillation_cap(
    osc: Mapping[str, Any], lump_names: Sequence[str], facts: str, dt: float
) -> dict[str, Any]:
    """The switch clock's cap for a lump that oscillates (:func:`oscillation_dict`), as
    :func:`memory_facts` returns it: the memory is the cycle's phase, which the time since phi
    last changed measures. ``max_age``: the largest of the
    period and the 90th percentile of either lump's segment durations (a cycle is one segment
    of each lump, so the clock covers the ages at which the segments end), at the median inputs
    and, where measured (``osc["over_range"]``: every grid point exactly, the ends of each
    input's range simulated), wherever phi oscillates over the range the fields give (a period
    that grows towards one end would outrun a cap from the median's), rounded up to two
    significant digits."""
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
    return {"memory": True, "max_age": max_age, "oscillation": True, "period_s": period,
            "reason": f"phi oscillates: {trough}, and no reversible network nor memoryless lump "
                      f"gives a negative autocorrelation (the check: below "
                      f"-{osc['depth_threshold']:g} and beyond {osc['z']:.1f} standard errors)"
                      f"{regular}. Its switching's memory ({facts}) is the cycle's phase, which "
                      f"the time since phi last changed measures: a switch clock would cap its "
                      f"age at {max_age:g} s, the largest of the periods and the 90th "
                      f"percentiles of the segments' durations where the population "
                      f"lives{across}"}  # fmt: skip


__all__ = [
    "BALANCE_BAND",
    "balanced_threshold",
    "collection_overrides",
    "input_ranges",
    "memory_facts",
    "oscillation_cap",
    "round_sig",
    "signal_bounds_advice",
    "threshold_lump",
]
