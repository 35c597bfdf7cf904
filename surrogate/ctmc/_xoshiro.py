"""xoshiro256** (Blackman & Vigna 2018) on one cell's ``(4,)`` uint64 state, compiled by numba.

Hand-written because the compiled SSA needs one independent, stored stream per cell: numba's
``np.random`` keeps one hidden state per thread, so under ``prange`` which cell draws which number
depends on the thread schedule. With a stream per cell the result is the same for any thread
count. Streams are seeded from ``numpy.random.SeedSequence`` (the well-kept part: high-quality,
distinct state words per cell).
"""

from __future__ import annotations

import numba
import numpy as np

__all__ = ["next_double", "next_u64", "seed_streams"]

_U5 = np.uint64(5)
_U9 = np.uint64(9)
_U7 = np.uint64(7)
_U17 = np.uint64(17)
_U45 = np.uint64(45)
_U11 = np.uint64(11)
_U64 = np.uint64(64)
_TWO_M53 = 1.0 / 9007199254740992.0  # 2**-53


@numba.njit(cache=True, inline="always")
def _rotl(x: np.uint64, k: np.uint64) -> np.uint64:
    return (x << k) | (x >> (_U64 - k))


@numba.njit(cache=True, inline="always")
def next_u64(s: np.ndarray) -> np.uint64:
    """Next 64-bit output of the stream ``s`` (``(4,)`` uint64, advanced in place)."""
    result = _rotl(s[1] * _U5, _U7) * _U9
    t = s[1] << _U17
    s[2] ^= s[0]
    s[3] ^= s[1]
    s[1] ^= s[2]
    s[0] ^= s[3]
    s[2] ^= t
    s[3] = _rotl(s[3], _U45)
    return result


@numba.njit(cache=True, inline="always")
def next_double(s: np.ndarray) -> float:
    """Uniform double in [0, 1) with 53 random bits, from the stream ``s`` (advanced)."""
    return float(next_u64(s) >> _U11) * _TWO_M53


def seed_streams(seed: int, n: int) -> np.ndarray:
    """``(n, 4)`` uint64 xoshiro256** states, one independent stream per cell.

    The words come from ``numpy.random.SeedSequence(seed)``; an all-zero state (the one fixed
    point of xoshiro, probability 2^-256) is replaced.
    """
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"seed must be a non-negative int, got {seed!r}")
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 0:
        raise ValueError(f"n must be a non-negative int, got {n!r}")
    words = np.random.SeedSequence(int(seed)).generate_state(4 * int(n), dtype=np.uint64)
    states = words.reshape(int(n), 4).copy()
    zero = ~states.any(axis=1)
    states[zero, 0] = np.uint64(1)
    return states
