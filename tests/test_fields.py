"""Fields: values at known points, the L2 floor, L3 widening with time."""

from __future__ import annotations

import math

import pytest
import torch

from surrogate.errors import ConfigError
from surrogate.fields import (
    ConstantField,
    DynamicGaussianField,
    ExponentialField,
    ExpressionField,
    Field,
    GaussianField,
    LinearField,
)
from surrogate.testing import FieldContract


def pts(*xy: tuple[float, float]) -> torch.Tensor:
    return torch.tensor(xy, dtype=torch.float64)


def test_gaussian_l1_values() -> None:
    f = GaussianField()
    got = f(pts((0, 0), (2, 0), (1, 1), (0, -3)), 0.0)
    expected = [
        0.1,
        0.1 * math.exp(-0.5 * 4 / 3),
        0.1 * math.exp(-0.5 * 2 / 3),
        0.1 * math.exp(-1.5),
    ]
    assert got.tolist() == pytest.approx(expected, rel=1e-12)
    assert f(pts((2, 0)), 100.0).item() == pytest.approx(expected[1])  # static


def test_linear_l2_values_and_floor() -> None:
    f = LinearField()
    got = f(pts((0, 0), (5, 0), (0, 2), (3, 1)), 0.0)
    expected = [0.1, 0.1 - 0.05 * 1.0, 0.1 - 0.05 * 1.0, 0.1 - 0.05 * math.hypot(3 / 5, 1 / 2)]
    assert got.tolist() == pytest.approx(expected, rel=1e-12)
    # |A r| = 2 at (10, 0): 0.1 - 0.1 = 0 -> floor 1e-5; far away also the floor
    assert f(pts((10, 0), (100, 100)), 0.0).tolist() == pytest.approx([1e-5, 1e-5])


def test_dynamic_l3_widens_with_time() -> None:
    f = DynamicGaussianField()
    r = pts((2, 0))
    assert f(r, 0.0).item() == pytest.approx(GaussianField()(r, 0.0).item())
    # S(t) = 3 (t/50 + 1): at t = 50 the variance is 6
    assert f(r, 50.0).item() == pytest.approx(0.1 * math.exp(-0.5 * 4 / 6), rel=1e-12)
    values = [f(r, t).item() for t in (0, 100, 200, 400)]
    assert values == sorted(values)  # off-peak concentration rises as the drop spreads
    assert f(pts((0, 0)), 300.0).item() == pytest.approx(0.1)  # the peak stays


def test_distance_from_peak_and_offset_peak() -> None:
    f = GaussianField(peak=(1.0, 1.0))
    assert f(pts((1, 1)), 0).item() == pytest.approx(0.1)
    assert f.distance_from_peak(pts((4, 5))).item() == pytest.approx(5.0)


def test_zero_field_and_bad_parameters() -> None:
    assert ConstantField()(pts((3, 3), (0, 0)), 1.0).tolist() == [0.0, 0.0]
    with pytest.raises(ConfigError, match="field.variance"):
        GaussianField(variance=-1)
    with pytest.raises(ConfigError, match="field.floor"):
        LinearField(floor=0.5)


#: every shipped field, held to the field contract (:class:`FieldContract`)
SHIPPED = [GaussianField(peak=(1.0, -0.5)), LinearField(), DynamicGaussianField(),
           ConstantField(0.05), ExponentialField(length=2.0),
           ExpressionField("a * exp(-0.5 * ((x - 1)^2 + y^2) / (w * (1 + t / s))) + 0.01 * sin(y)^2",
                           {"a": 0.1, "w": 1.5, "s": 100.0})]  # fmt: skip


@pytest.mark.parametrize("field", SHIPPED, ids=lambda f: type(f).__name__)
class TestShippedFieldContract(FieldContract):
    @pytest.fixture(autouse=True)
    def _field(self, field: Field) -> None:
        self.field = field

    def make_field(self) -> Field:
        return self.field


class _Swapped(GaussianField):
    """A formula field whose Python call reads y for x: its kernels' code is not what it runs."""

    def __call__(self, position: torch.Tensor, t: float) -> torch.Tensor:
        return super().__call__(position.flip(-1), t)


def test_a_field_whose_call_is_not_its_formula_fails_the_contract() -> None:
    class Contract(FieldContract):
        def make_field(self) -> Field:
            return _Swapped(peak=(1.0, 0.0))

    with pytest.raises(AssertionError):
        Contract().test_its_formula_is_what_it_computes()
