# mypy: disable-error-code="call-arg,var-annotated"
"""Source template of the CUDA per-cell Gillespie direct method (numba-cuda): one thread per cell
for a whole window.

The CUDA twin of :mod:`surrogate.ctmc._direct_method`, statement for statement, so that each cell
makes the same events from the same stream on either device (tested bit for bit on numba's CUDA
simulator). It differs only where CUDA must: scratch arrays are thread-local arrays of sizes
fixed when the kernel is generated (``N_REACTIONS`` ...), a cell is a thread (``cuda.grid``)
instead of a ``prange`` iteration, an event's values are addressed by offset rather than by a
slice, and ``math`` stands for ``np``. :mod:`surrogate.ctmc.cuda_ssa` copies these functions'
source (``inspect.getsource``) into a module generated per network, beside its propensities,
and compiles it there. The stubs keep this file importable and lint-clean; never called.
"""

from __future__ import annotations

import math

import numpy as np
from numba import cuda

from surrogate.ctmc._direct_method import (
    BAD_ASSIGNMENT,
    BAD_PROPENSITY,
    BAD_RULE,
    EVENT_CASCADE,
    MAX_EVENTS,
    NEGATIVE_COUNT,
)
from surrogate.ctmc._xoshiro_cuda import next_double

__all__ = [
    "BAD_ASSIGNMENT",
    "BAD_PROPENSITY",
    "BAD_RULE",
    "EVENT_CASCADE",
    "MAX_EVENTS",
    "NEGATIVE_COUNT",
]

# Set in the generated module: the sizes of the thread-local arrays (at least 1 each).
N_REACTIONS = 1
N_EVENTS = 1
N_VALUES = 1
N_THRESHOLDS = 0
N_BREAKS = 1
MAX_CASCADE = 1000
WHOLE_TOLERANCE = 1e-9


def propensities(x, p, a):  # pragma: no cover
    """Stub replaced by the generated per-network function."""
    raise NotImplementedError


def triggers(x, p, t, out):  # pragma: no cover
    """Stub replaced by the generated function."""
    raise NotImplementedError


def thresholds(x, p, out):  # pragma: no cover
    """Stub replaced by the generated function."""
    raise NotImplementedError


def event_values(e, x, p, t, v):  # pragma: no cover
    """Stub replaced by the generated function."""
    raise NotImplementedError


def apply_rules(x, p):  # pragma: no cover
    """Stub replaced by the generated function."""
    raise NotImplementedError


def advance_cells(x, p, dt, rng, change_ptr, change_species, change_delta, max_events, out):
    """Advance cell ``cuda.grid(1)`` (row of ``x``, in place) over its window ``dt[i]``; the
    arguments as :func:`surrogate.ctmc._direct_method.advance_cells`'s."""
    i = cuda.grid(1)
    if i >= x.shape[0]:
        return
    n_reactions = change_ptr.shape[0] - 1
    a = cuda.local.array(N_REACTIONS, np.float64)
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
            if not (ar >= 0.0 and ar < math.inf):
                status = BAD_PROPENSITY
                detail = r
                break
            total += ar
        if status != 0 or total <= 0.0:
            break
        t += -math.log1p(-next_double(si)) / total
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
        while a[r] <= 0.0:
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
    # math.floor gives an int64 on the device: only where it cannot overflow (a value past
    # 9e18, NaN or infinite fails the checks below as it stands)
    rounded = float(math.floor(value + 0.5)) if abs(value) < 9.0e18 else value
    if not (
        abs(value - rounded) <= WHOLE_TOLERANCE * max(1.0, abs(value))
        and rounded >= 0.0
        and rounded < 9.0e18
    ):
        return False
    x[column] = np.int64(rounded)
    return True


def check_events(x, p, t, fired, now, pending, values, assign_ptr, assign_col, persistent, early):
    """:func:`surrogate.ctmc._direct_method.check_events` for one thread's cell."""
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
    """:func:`surrogate.ctmc._direct_method.advance_cells_events` for cell ``cuda.grid(1)``."""
    i = cuda.grid(1)
    if i >= x.shape[0]:
        return
    n_reactions = change_ptr.shape[0] - 1
    a = cuda.local.array(N_REACTIONS, np.float64)
    now = cuda.local.array(N_EVENTS, np.bool_)
    pending = cuda.local.array(N_EVENTS, np.bool_)
    values = cuda.local.array(N_VALUES, np.float64)
    breaks = cuda.local.array(N_BREAKS, np.float64)
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
    else:
        status, detail = check_events(
            xi, pi, t, fi, now, pending, values, assign_ptr, assign_col, persistent, early
        )
    while status == 0:
        propensities(xi, pi, a)
        total = 0.0
        for r in range(n_reactions):
            ar = a[r]
            if not (ar >= 0.0 and ar < math.inf):
                status = BAD_PROPENSITY
                detail = r
                break
            total += ar
        if status != 0:
            break
        thresholds(xi, pi, breaks)
        next_break = math.inf
        for k in range(N_THRESHOLDS):
            if breaks[k] > t and breaks[k] < next_break:
                next_break = breaks[k]
        t_next = math.inf
        if total > 0.0:
            t_next = t - math.log1p(-next_double(si)) / total
        if next_break <= end and next_break <= t_next:
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
