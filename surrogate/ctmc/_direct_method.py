"""Source template of the compiled per-cell Gillespie direct method.

``advance_cells`` is plain Python on purpose: :mod:`surrogate.ctmc.compiled` copies its source
(``inspect.getsource``) into a generated module next to the network's ``propensities`` function
and compiles it there with numba (``parallel=True``, ``cache=True``), so each network gets its
own kernel with the propensities inlined and an on-disk cache. A network with species
assignment rules or events gets ``advance_cells_events`` instead (with ``check_events`` and
``store_whole``, beside the generated functions of :func:`surrogate.ctmc.events.numba_source`;
semantics in :mod:`surrogate.ctmc.events`). The stubs below only keep this file importable and
lint-clean; they are never called.
"""

from __future__ import annotations

import numpy as np
from numba import prange

from surrogate.ctmc._xoshiro import next_double

# Status codes per cell (0: window completed).
MAX_EVENTS = 1  # more than max_events events in the window
BAD_PROPENSITY = 2  # a propensity was negative or not finite (detail: the reaction)
NEGATIVE_COUNT = 3  # an event drove a count negative (detail: the reaction)
BAD_ASSIGNMENT = 4  # an event assigned a count that is not a whole number >= 0 (detail: event)
BAD_RULE = 5  # a rule's value is not a whole number >= 0 (detail: the rule)
EVENT_CASCADE = 6  # events kept firing each other at one instant (detail: -1)

# Set in the generated module (surrogate.ctmc.events).
N_THRESHOLDS = 0
MAX_CASCADE = 1000
WHOLE_TOLERANCE = 1e-9


def propensities(x: np.ndarray, p: np.ndarray, a: np.ndarray) -> None:  # pragma: no cover
    """Stub replaced by the generated per-network function."""
    raise NotImplementedError


def triggers(x, p, t, out):  # pragma: no cover
    """Stub replaced by the generated function (each event's trigger just after ``t``)."""
    raise NotImplementedError


def thresholds(x, p, out):  # pragma: no cover
    """Stub replaced by the generated function (the times at which triggers may switch)."""
    raise NotImplementedError


def event_values(e, x, p, t, v):  # pragma: no cover
    """Stub replaced by the generated function (event ``e``'s assigned values into ``v``)."""
    raise NotImplementedError


def apply_rules(x, p):  # pragma: no cover
    """Stub replaced by the generated function (-1, or the rule that failed)."""
    raise NotImplementedError


def advance_cells(x, p, dt, rng, change_ptr, change_species, change_delta, max_events, out):
    """Advance every cell (row of ``x``, in place) over its window ``dt[i]``.

    ``p`` (n, P) inputs, ``rng`` (n, 4) uint64 per-cell streams (advanced in place),
    stoichiometry in CSR form (``change_ptr`` (R + 1,), ``change_species``, ``change_delta``),
    ``out`` (n, 3) int64 receives (events, status, detail) per cell.
    """
    n = x.shape[0]
    n_reactions = change_ptr.shape[0] - 1
    for i in prange(n):
        a = np.empty(n_reactions)
        xi = x[i]
        pi = p[i]
        si = rng[i]
        window = dt[i]
        t = 0.0
        events = 0
        status = 0
        detail = -1
        while True:
            propensities(xi, pi, a)
            total = 0.0
            for r in range(n_reactions):
                ar = a[r]
                if not (ar >= 0.0 and ar < np.inf):
                    status = BAD_PROPENSITY
                    detail = r
                    break
                total += ar
            if status != 0 or total <= 0.0:
                break
            # 1 - u in (0, 1]: finite waiting times, and a threshold > 0 below.
            t += -np.log1p(-next_double(si)) / total
            if t >= window:
                break
            if events >= max_events:
                status = MAX_EVENTS
                break
            threshold = (1.0 - next_double(si)) * total
            r = 0
            cum = a[0]
            while cum < threshold and r < n_reactions - 1:
                r += 1
                cum += a[r]
            while a[r] <= 0.0:  # rounding at the top end: step back to a possible reaction
                r -= 1
            for k in range(change_ptr[r], change_ptr[r + 1]):
                s = change_species[k]
                xi[s] += change_delta[k]
                if xi[s] < 0:
                    status = NEGATIVE_COUNT
                    detail = r
            events += 1
            if status != 0:
                break
        out[i, 0] = events
        out[i, 1] = status
        out[i, 2] = detail


def store_whole(x, column, value):
    """``x[column] = value`` if ``value`` is a whole number >= 0 (within WHOLE_TOLERANCE);
    returns whether it was."""
    rounded = np.floor(value + 0.5)
    if not (
        abs(value - rounded) <= WHOLE_TOLERANCE * max(1.0, abs(value))
        and rounded >= 0.0
        and rounded < 9.0e18
    ):
        return False
    x[column] = np.int64(rounded)
    return True


def check_events(x, p, t, fired, now, pending, values, assign_ptr, assign_col, persistent, early):
    """Fire the events whose trigger rose since ``fired`` (and those they make rise) for one
    cell at time ``t``; returns (status, detail). ``values`` holds every event's assigned
    values (event ``e``'s from ``assign_ptr[e]``); ``early[e]``: values taken before any event
    of the instant runs (useValuesFromTriggerTime)."""
    n_events = fired.shape[0]
    for _ in range(MAX_CASCADE):
        triggers(x, p, t, now)
        rising = False
        for e in range(n_events):
            pending[e] = now[e] and not fired[e]
            fired[e] = now[e]
            rising = rising or pending[e]
        if not rising:
            return 0, -1
        for e in range(n_events):
            if pending[e] and early[e]:
                event_values(e, x, p, t, values[assign_ptr[e] :])
        for e in range(n_events):
            if not pending[e]:
                continue
            if not persistent[e]:
                triggers(x, p, t, now)
                if not now[e]:
                    continue
            if not early[e]:
                event_values(e, x, p, t, values[assign_ptr[e] :])
            for k in range(assign_ptr[e], assign_ptr[e + 1]):
                if not store_whole(x, assign_col[k], values[k]):
                    return BAD_ASSIGNMENT, e
            rule = apply_rules(x, p)
            if rule >= 0:
                return BAD_RULE, rule
    return EVENT_CASCADE, -1


def advance_cells_events(
    x,
    p,
    dt,
    rng,
    change_ptr,
    change_species,
    change_delta,
    max_events,
    out,
    clock,
    fired,
    assign_ptr,
    assign_col,
    persistent,
    early,
):
    """``advance_cells`` with rules and events: each cell from its own time ``clock[i]`` to
    ``clock[i] + dt[i]`` (written back), ``fired`` (n, E) its triggers' last values (updated);
    the events' assignments in CSR form (``assign_ptr`` (E + 1,), ``assign_col``), their
    ``persistent`` and ``early`` (useValuesFromTriggerTime) flags (E,)."""
    n = x.shape[0]
    n_reactions = change_ptr.shape[0] - 1
    n_events = fired.shape[1]
    for i in prange(n):
        a = np.empty(n_reactions)
        now = np.empty(n_events, dtype=np.bool_)
        pending = np.empty(n_events, dtype=np.bool_)
        values = np.empty(assign_ptr[n_events] + 1)
        breaks = np.empty(N_THRESHOLDS)
        xi = x[i]
        pi = p[i]
        si = rng[i]
        fi = fired[i]
        t = clock[i]
        end = t + dt[i]
        events = 0
        status = 0
        detail = apply_rules(xi, pi)
        if detail >= 0:
            status = BAD_RULE
        else:  # inputs may have changed since the last window: rules and triggers read them
            status, detail = check_events(
                xi, pi, t, fi, now, pending, values, assign_ptr, assign_col, persistent, early
            )
        while status == 0:
            propensities(xi, pi, a)
            total = 0.0
            for r in range(n_reactions):
                ar = a[r]
                if not (ar >= 0.0 and ar < np.inf):
                    status = BAD_PROPENSITY
                    detail = r
                    break
                total += ar
            if status != 0:
                break
            thresholds(xi, pi, breaks)
            next_break = np.inf
            for k in range(N_THRESHOLDS):
                if breaks[k] > t and breaks[k] < next_break:
                    next_break = breaks[k]
            t_next = np.inf
            if total > 0.0:
                t_next = t - np.log1p(-next_double(si)) / total
            if next_break <= end and next_break <= t_next:
                # a trigger may switch first: stop there; the next waiting time is drawn
                # afresh from there (exact: it is memoryless)
                t = next_break
                status, detail = check_events(
                    xi, pi, t, fi, now, pending, values, assign_ptr, assign_col, persistent, early
                )
                continue
            if t_next >= end:
                break
            if events >= max_events:
                status = MAX_EVENTS
                break
            threshold = (1.0 - next_double(si)) * total
            r = 0
            cum = a[0]
            while cum < threshold and r < n_reactions - 1:
                r += 1
                cum += a[r]
            while a[r] <= 0.0:
                r -= 1
            for k in range(change_ptr[r], change_ptr[r + 1]):
                s = change_species[k]
                xi[s] += change_delta[k]
                if xi[s] < 0:
                    status = NEGATIVE_COUNT
                    detail = r
            events += 1
            t = t_next
            if status != 0:
                break
            rule = apply_rules(xi, pi)
            if rule >= 0:
                status = BAD_RULE
                detail = rule
                break
            status, detail = check_events(
                xi, pi, t, fi, now, pending, values, assign_ptr, assign_col, persistent, early
            )
        clock[i] = end
        out[i, 0] = events
        out[i, 1] = status
        out[i, 2] = detail
