"""The DCT built from torch.fft against scipy's: every length parity, every dimension, both ways."""

from __future__ import annotations

import math

import numpy as np
import pytest
import scipy.fft
import torch

from surrogate.grid.transforms import dct, idct

EPS = float(np.finfo(np.float64).eps)


def _tolerance(x: np.ndarray, n: int) -> float:
    """An FFT's rounding: a few ulps per butterfly level (log2 n) of the vector's 2-norm."""
    return 8 * EPS * math.log2(2 * n) * float(np.linalg.norm(x))


@pytest.mark.parametrize("n", [1, 2, 3, 8, 17, 32])
@pytest.mark.parametrize("dim", [0, 1, 2])
def test_dct_and_its_inverse_are_scipys(n: int, dim: int) -> None:
    rng = np.random.default_rng(n * 10 + dim)
    shape = [3, 5, 4]
    shape[dim] = n
    x = rng.normal(size=shape)
    tol = _tolerance(x, n)
    got = dct(torch.from_numpy(x), dim).numpy()
    np.testing.assert_allclose(got, scipy.fft.dct(x, type=2, norm="ortho", axis=dim), atol=tol)
    back = idct(torch.from_numpy(x), dim).numpy()
    np.testing.assert_allclose(back, scipy.fft.idct(x, type=2, norm="ortho", axis=dim), atol=tol)
    np.testing.assert_allclose(idct(dct(torch.from_numpy(x), dim), dim).numpy(), x, atol=2 * tol)


def test_the_two_dimensional_transform_is_scipys_dctn() -> None:
    x = np.random.default_rng(1).normal(size=(2, 12, 7))
    two = dct(dct(torch.from_numpy(x), -2), -1).numpy()
    want = scipy.fft.dctn(x, type=2, norm="ortho", axes=(-2, -1))
    np.testing.assert_allclose(two, want, atol=2 * _tolerance(x, 12 * 7))
    back = idct(idct(torch.from_numpy(want), -2), -1).numpy()
    np.testing.assert_allclose(back, x, atol=4 * _tolerance(x, 12 * 7))


def test_float32_keeps_its_dtype_and_float32_accuracy() -> None:
    x = torch.randn(4, 16)
    y = dct(x)
    assert y.dtype == torch.float32
    want = scipy.fft.dct(x.numpy().astype(np.float64), type=2, norm="ortho")
    eps32 = float(np.finfo(np.float32).eps)
    assert np.abs(y.numpy() - want).max() <= 8 * eps32 * math.log2(32) * float(x.norm())
