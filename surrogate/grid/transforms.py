"""The orthonormal DCT-II and its inverse (DCT-III) along one dimension, built from torch.fft.

torch has no DCT; this is Makhoul's algorithm (IEEE Trans. ASSP 28, 1980), the one
``scipy.fft.dct`` documents: reorder ``x`` into ``v = (x_0, x_2, x_4, ..., x_5, x_3, x_1)``, take
one complex FFT of the same length and rotate each coefficient by ``exp(-i pi k / (2N))``. So
a DCT costs one FFT of length N (no mirrored copy of length 2N), on any device and for any
leading batch dimensions. ``norm="ortho"`` scaling, as ``scipy.fft.dct(x, type=2,
norm="ortho")``: the transform is orthogonal, so :func:`idct` is its transpose and inverse.

The cosines ``cos(pi k (2n + 1) / (2N))`` are the eigenvectors of the cell-centred second
difference with mirrored ghost cells (a no-flux wall half a cell beyond the first and the last
cell centre), which is why the no-flux field step is diagonal in this basis
(:mod:`surrogate.grid.solvers`).
"""

from __future__ import annotations

import math
from functools import lru_cache

import torch
from torch import Tensor

__all__ = ["dct", "idct"]


def _twiddle(n: int, like: Tensor, sign: float) -> Tensor:
    """``exp(sign * i pi k / (2n))`` for k = 0..n-1, complex, on ``like``'s device."""
    return _constants(n, like.dtype, like.device, sign)[0]


def _scale(n: int, like: Tensor) -> Tensor:
    """The orthonormal scaling of the DCT-II coefficients: sqrt(1/(4n)) for k = 0, else
    sqrt(1/(2n))."""
    return _constants(n, like.dtype, like.device, 1.0)[1]


@lru_cache(maxsize=32)
def _constants(
    n: int, dtype: torch.dtype, device: torch.device, sign: float
) -> tuple[Tensor, Tensor]:
    """The twiddles and the scaling of length ``n``, made once per (length, dtype, device):
    every field step transforms the same lengths."""
    k = torch.arange(n, device=device, dtype=dtype)
    twiddle = torch.polar(torch.ones_like(k), (sign * math.pi / (2 * n)) * k)
    s = torch.full((n,), math.sqrt(1.0 / (2 * n)), device=device, dtype=dtype)
    s[0] = math.sqrt(1.0 / (4 * n))
    return twiddle, s


def dct(x: Tensor, dim: int = -1) -> Tensor:
    """The orthonormal DCT-II of a real tensor along ``dim`` (``scipy.fft.dct(x, type=2,
    norm="ortho", axis=dim)``).

    Args:
        x: real ``(..., n, ...)`` tensor (float32 or float64).
        dim: the dimension to transform.

    Returns:
        The coefficients, the shape and dtype of ``x``.

    Example:
        >>> dct(torch.ones(4, dtype=torch.float64))  # only the mean mode: 2 = sqrt(4) * 1
        tensor([2., 0., 0., 0.], dtype=torch.float64)
    """
    x = x.movedim(dim, -1)
    n = x.shape[-1]
    v = torch.cat([x[..., ::2], x[..., 1::2].flip(-1)], dim=-1)
    spectrum = torch.fft.fft(v, dim=-1)
    y = 2.0 * (spectrum * _twiddle(n, x, -1.0)).real
    return (y * _scale(n, x)).movedim(-1, dim)


def idct(y: Tensor, dim: int = -1) -> Tensor:
    """The inverse of :func:`dct` (the orthonormal DCT-III, ``scipy.fft.idct(y, type=2,
    norm="ortho", axis=dim)``).

    Args:
        y: real ``(..., n, ...)`` coefficients.
        dim: the dimension to transform.

    Returns:
        The values, the shape and dtype of ``y``.
    """
    y = y.movedim(dim, -1)
    n = y.shape[-1]
    coeff = y / _scale(n, y)  # the unnormalised DCT-II coefficients Y_k
    # Y_{n-k} for k = 0..n-1, with Y_n = 0: then W_k = (Y_k - i Y_{n-k}) / 2 = exp(-i pi k/2n) V_k
    mirrored = torch.cat([torch.zeros_like(coeff[..., :1]), coeff[..., 1:].flip(-1)], dim=-1)
    spectrum = torch.complex(coeff, -mirrored) * (0.5 * _twiddle(n, y, 1.0))
    v = torch.fft.ifft(spectrum, dim=-1).real
    half = (n + 1) // 2
    x = torch.empty_like(v)
    x[..., ::2] = v[..., :half]
    x[..., 1::2] = v[..., half:].flip(-1)
    return x.movedim(-1, dim)
