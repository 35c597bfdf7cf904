"""Source template of the compiled per-cell Gillespie direct method.

``advance_cells`` is plain Python on purpose: :mod:`surrogate.ctmc.compiled` copies its source
(``inspect.getsource``) into a generated module next to the network's ``propensities`` function
and compiles it there with numba (``parallel=True``, ``cache=True``), so each network gets its
own kernel with the propensities inlined and an on-disk cache. The stub below only keeps this
file importable and lint-clean; it is never called.
"""

from __future__ import annotations

import numpy as np
from numba import prange

from surrogate.ctmc._xoshiro import next_double

# Status codes per cell (0: window completed).
MAX_EVENTS = 1  # more than max_events events in the window
BAD_PROPENSITY = 2  # a propensity was negative or not finite (detail: the reaction)
NEGATIVE_COUNT = 3  # an event drove a count negative (detail: the reaction)


def propensities(x: np.ndarray, p: np.ndarray, a: np.ndarray) -> None:  # pragma: no cover
    """Stub replaced by the generated per-network function."""
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
