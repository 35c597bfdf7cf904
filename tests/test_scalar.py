"""Scalar formulas written once: the torch function and its numba copy compute the same."""

from __future__ import annotations

import numba
import numpy as np
import torch

from surrogate.scalar import clamp, exp, f32, numba_formulas, remainder, sigmoid, where

SCALE = 0


def _half(x):
    return x * f32(0.5)


def _formula(x, c):
    y = _half(x) + f32(1.0)
    z = where(y > 1.5, sigmoid(-y), exp(-y) * c[SCALE])
    return clamp(remainder(z + y, f32(1.25)), f32(0.0), f32(1.0))


def test_the_numba_copy_keeps_float32_and_computes_the_torch_values() -> None:
    compiled = numba_formulas((_half, _formula), {"SCALE": SCALE})
    c32 = np.array([0.3], dtype=np.float32)
    x = torch.linspace(-3.0, 3.0, 61)
    expected = _formula(x, (0.3,))
    assert expected.dtype == torch.float32
    got = np.array([compiled._formula(np.float32(v), c32) for v in x.numpy()])
    # f32 literals and the float32 constants: no float64 inside
    (signature,) = compiled._formula.nopython_signatures
    assert signature.return_type == numba.float32
    np.testing.assert_allclose(got, expected.numpy(), rtol=0, atol=2e-7)


def test_the_formulas_module_stays_as_it_was() -> None:
    """numba_formulas re-binds copies: the original functions still compute over tensors."""
    numba_formulas((_half,))
    assert torch.equal(_half(torch.ones(2)), torch.full((2,), 0.5))


def test_both_namespaces_name_the_same_primitives() -> None:
    from surrogate import scalar

    assert set(scalar.numba_primitives()) == set(scalar.PRIMITIVES)
    assert all(hasattr(scalar, name) for name in scalar.PRIMITIVES)
