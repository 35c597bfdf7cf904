"""The field contract (:class:`FieldContract`): what the bodies, the simulator and the compiled
kernels rely on of every :class:`~surrogate.fields.Field`."""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from surrogate.ctmc.codegen import load_generated
from surrogate.fields import Field, FormulaField


class FieldContract:
    """What every field guarantees, as tests a field's test class inherits.

    A subclass (named ``Test...``) fills :meth:`make_field`; :attr:`times` are the times (s)
    it is read at.

    Example:
        >>> from surrogate.fields import LinearField
        >>> class TestLinearField(FieldContract):
        ...     def make_field(self):
        ...         return LinearField()
    """

    #: the times (s) the field is read at
    times: tuple[float, ...] = (0.0, 7.5, 120.0)
    #: the cells read
    n: int = 64

    def make_field(self) -> Field:
        """The field under test."""
        raise NotImplementedError(f"{type(self).__name__} must define make_field()")

    def positions(self, dtype: torch.dtype = torch.float32) -> Tensor:
        """``n x 2`` positions (mm) around the field's peak, seeded."""
        g = torch.Generator().manual_seed(0)
        peak = torch.tensor(self.make_field().peak, dtype=dtype)
        return peak + 3.0 * torch.randn(self.n, 2, generator=g, dtype=dtype)

    def test_values_are_per_cell_finite_and_non_negative(self) -> None:
        field = self.make_field()
        for dtype in (torch.float32, torch.float64):
            for t in self.times:
                value = field(self.positions(dtype), t)
                assert value.shape == (self.n,) and value.dtype == dtype, (value.shape, t)
                assert torch.isfinite(value).all() and (value >= 0).all(), (value, t)

    def test_each_cell_reads_its_own_position(self) -> None:
        field = self.make_field()
        p = self.positions(torch.float64)
        for t in self.times:
            whole = field(p, t)
            assert torch.allclose(field(p[5:9], t), whole[5:9], rtol=1e-12, atol=0.0)
            # reversing the cells reverses the values
            assert torch.allclose(field(p.flip(0), t), whole.flip(0), rtol=1e-12, atol=0.0)

    def test_gradient_is_per_cell_and_matches_differences(self) -> None:
        """Where a field is smooth, its autograd gradient (the shape a gradient-reading body
        gets) equals central differences; cells on a kink (a floor, the peak of a cone) are
        left out by comparing only where the two one-sided differences agree."""
        field = self.make_field()
        p = self.positions(torch.float64).requires_grad_(True)
        t = self.times[-1]
        value = field(p, t)
        if not value.requires_grad:  # a constant field: no graph, a zero gradient
            assert torch.equal(value, field(p + 1.0, t))
            return
        (grad,) = torch.autograd.grad(value.sum(), p)
        assert grad.shape == (self.n, 2) and torch.isfinite(grad).all()
        h = 1e-5
        with torch.no_grad():
            for axis in range(2):
                step = torch.zeros(2, dtype=torch.float64)
                step[axis] = h
                up, mid, down = field(p + step, t), field(p, t), field(p - step, t)
                ahead, behind = (up - mid) / h, (mid - down) / h
                smooth = (ahead - behind).abs() <= 1e-4 * (ahead.abs() + behind.abs()) + 1e-9
                central = (up - down) / (2 * h)
                assert torch.allclose(grad[smooth, axis], central[smooth], rtol=1e-5, atol=1e-9)

    def test_distance_is_from_the_peak(self) -> None:
        field = self.make_field()
        p = self.positions(torch.float64)
        d = field.distance_from_peak(p)
        assert d.shape == (self.n,)
        want = (p - torch.tensor(field.peak, dtype=torch.float64)).norm(dim=-1)
        assert torch.allclose(d, want, rtol=1e-12)
        peak = torch.tensor([field.peak], dtype=torch.float64)
        assert field.distance_from_peak(peak).item() == 0.0

    def test_its_formula_is_what_it_computes(self) -> None:
        """A formula field's compiled kernels run the scalar code of its formula: that code
        (run here as Python) gives the values its torch call does."""
        field = self.make_field()
        if not isinstance(field, FormulaField):
            return  # a Python field: the compiled kernels refuse it (KernelUnsupported)
        # the kernels' helpers, as the dispatcher's module defines them (field_formula), and
        # the formula's scalar code, loaded as generated code is (a file, imported; no exec)
        source = "\n".join(["import math", "", "import numpy as np", "", "",
                             "def _hypot(a, b):", "    return np.sqrt(a * a + b * b)", "", "",
                             field.formula.numba_source("scalar")])  # fmt: skip
        scalar = load_generated(source, prefix="contract").scalar
        row = np.zeros(1 + len(field.formula.parameters))
        row[1:] = field.packed_parameters()
        p = self.positions(torch.float32)
        for t in self.times:
            want = field(p, t).double()
            got = torch.tensor(
                [float(scalar(np.float32(x), np.float32(y), float(t), row))
                 for x, y in p.tolist()],
                dtype=torch.float64,
            )  # fmt: skip
            assert torch.allclose(got, want, rtol=1e-5, atol=1e-12), (t, got - want)
