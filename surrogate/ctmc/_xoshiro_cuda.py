"""xoshiro256** for CUDA device code (numba-cuda): the same streams as
:mod:`surrogate.ctmc._xoshiro`, one ``(4,)`` uint64 state per cell (thread).

The same arithmetic as the CPU version, so a cell draws the same numbers on either device (the
CUDA SSA's tests check the counts bit for bit against the compiled CPU SSA on numba's CUDA
simulator). Imported only where numba-cuda is installed.
"""

from __future__ import annotations

import numpy as np
from numba import cuda

_U5 = np.uint64(5)
_U9 = np.uint64(9)
_U7 = np.uint64(7)
_U17 = np.uint64(17)
_U45 = np.uint64(45)
_U11 = np.uint64(11)
_U64 = np.uint64(64)
_TWO_M53 = 1.0 / 9007199254740992.0  # 2**-53


@cuda.jit(device=True, inline=True)
def _rotl(x, k):
    return (x << k) | (x >> (_U64 - k))


@cuda.jit(device=True, inline=True)
def next_u64(s):
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


@cuda.jit(device=True, inline=True)
def next_double(s):
    """Uniform double in [0, 1) with 53 random bits, from the stream ``s`` (advanced)."""
    return float(next_u64(s) >> _U11) * _TWO_M53
