"""The network's settling time the inspection implies, and the burn-in it calls for."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from surrogate.diagnosis.fixed import FixedInputs
from surrogate.models.network import NetworkInternalModel


def round_up(value: float) -> float:
    """``value`` rounded up to two significant digits (a setting to recommend)."""
    if not (value > 0 and math.isfinite(value)):
        return value
    scale = 10 ** (math.floor(math.log10(value)) - 1)
    return math.ceil(value / scale - 1e-9) * scale


#: a network settling (from the file's counts) over at least this many windows gets classes
#: whose bins relax (:mod:`surrogate.gp.class_relaxation`). Set between the measured cases: the
#: auto-regulatory network settles over ~21,000 windows (1,060 s at dt 0.05) and its learned
#: moves between bins, ~1e-3 per window from 5-30 collected events each, mix the bins ~30x
#: too fast; a protein relaxing in 20 s settles over ~1,800
SLOW_SETTLING_WINDOWS = 10_000
#: bins per lump of ``classes: auto`` recommended where the bins relax: their flips are learned
#: from every window of the bin, not from rare crossings, so finer bins cost little data and
#: hold the count closer. The auto-regulatory network (docs/fidelity.md): 8 bins, 23 of 24
#: checks (a mean duration +3.009 %); 16 bins, 24 of 24 (durations -0.5 to +2.7 %)
RELAXATION_BINS = 16


def slowest_settling(fixed: FixedInputs) -> float:
    """The longest settling time (s) over the grid of the network's counts and phi (0 where
    none is finite)."""
    settle = fixed.settle_phi if fixed.settle_network is None else \
        np.maximum(fixed.settle_phi, fixed.settle_network)  # fmt: skip
    finite = settle[np.isfinite(settle)]
    return float(finite.max()) if finite.size else 0.0


def settling_estimate(fixed: FixedInputs, tolerance: float) -> dict[str, Any]:
    """The network's settling time (s) the inspection implies, for the rule of
    :data:`SLOW_SETTLING_WINDOWS`: ``{"seconds", "basis", "caveat"}``.

    Where every grid point settled: the longest settling over the grid
    (:func:`slowest_settling`; ``basis`` empty). Where the run stopped first (its budget,
    ``inspect.max_seconds``, or ``inspect.max_time``), the settling times measured are lower
    bounds that can fall far short: the auto-regulatory network at the default budget stopped
    at 640 s with 230 s measured, where 2,560 s of run measured 1,250 s. Then the larger of
    half the run (a point settles in the first half of its run) and ``ln(1 / tolerance)`` x
    phi's relaxation time at stationarity (a mean relaxing as ``exp(-t / tau)`` from a start
    as far from its plateau as the plateau is from 0 is within ``tolerance`` after that; the
    same network: 419 s, so ~1,250 s), each named in ``basis``; ``caveat`` says what would
    settle it."""
    measured = slowest_settling(fixed)
    if bool(fixed.settled.all()):
        return {"seconds": measured, "basis": "", "caveat": ""}
    half = fixed.horizon / 2
    parts = [f"not settled by the end of the inspector's {fixed.horizon:.3g}-s run: at least "
             f"{max(measured, half):.4g} s"]  # fmt: skip
    seconds = max(measured, half)
    tau = fixed.relaxation.get("tau_s")
    if tau is not None and math.isfinite(tau) and tau > 0:
        from_tau = math.log(1 / tolerance) * float(tau)
        se = fixed.relaxation.get("se")
        err = f" +- {se:.3g}" if se is not None and math.isfinite(se) and se > 0 else ""
        parts.append(f"phi's relaxation time at stationarity, {tau:.3g}{err} s, implies "
                     f"ln(1 / {tolerance:g}) x {tau:.3g} = {from_tau:.4g} s")  # fmt: skip
        seconds = max(seconds, from_tau)
    caveat = ("; the run did not settle, so a larger `inspect.max_seconds` (or "
              "`inspect.max_time`) would tell")  # fmt: skip
    return {"seconds": seconds, "basis": "; ".join(parts), "caveat": caveat}


def burn_in_advice(
    network: NetworkInternalModel | None,
    fixed: FixedInputs,
    factor: float,
    tolerance: float | None = None,
) -> dict[str, Any]:
    """``model.burn_in`` against ``factor`` x the network's settling time: the same estimate
    the recommendation states (:func:`settling_estimate` at ``tolerance``; without one, the
    longest settling over the grid, or half the run where it stopped first), with its
    ``basis`` and the grid points that did not settle. Where the run stopped before settling,
    that is a lower bound: a burn-in below it is too short, one above it is not known to be
    enough (``enough`` None), never told to shrink to it."""
    if network is None:
        return {"applies": False, "text": "the internal model draws its own initial state (no "
                                          "burn-in setting)"}  # fmt: skip
    if network.state_space is not None:
        return {"applies": False, "text": "not used: initial states are drawn from the exact "
                                          "stationary law (an enumerable network)"}  # fmt: skip
    settled = bool(fixed.settled.all())
    if tolerance is not None:
        est = settling_estimate(fixed, tolerance)
        worst, basis = float(est["seconds"]), str(est["basis"])
    else:
        worst = slowest_settling(fixed)
        worst, basis = (worst, "") if settled else (max(worst, fixed.horizon / 2), "")
    unsettled = [int(g) for g in np.flatnonzero(~np.asarray(fixed.settled, bool))]
    needed = round_up(factor * worst)
    have = float(network.burn_in)
    return {"applies": True, "settling_s": worst, "settled": settled, "needed_s": needed,
            "burn_in_s": have, "enough": have >= needed if settled or have < needed else None,
            "basis": basis, "unsettled_points": unsettled, "text": ""}  # fmt: skip


__all__ = [
    "RELAXATION_BINS",
    "SLOW_SETTLING_WINDOWS",
    "burn_in_advice",
    "round_up",
    "settling_estimate",
    "slowest_settling",
]
