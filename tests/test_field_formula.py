"""Fields as formulas: an ExpressionField computes its formula as the same Python field does, the
built-in fields (now formulas) compute what their hand-written torch code computed, bit for
bit, and a bad formula is refused naming what is wrong."""

from __future__ import annotations

import pytest
import torch

from surrogate.config import build_field
from surrogate.errors import ConfigError
from surrogate.field_formula import field_formula
from surrogate.fields import (
    ConstantField,
    DynamicGaussianField,
    ExponentialField,
    ExpressionField,
    Field,
    GaussianField,
    LinearField,
)


class _Ridge(Field):
    """The formula of RIDGE written as a Python field, in the same operation order."""

    def __call__(self, position: torch.Tensor, t: float) -> torch.Tensor:
        x, y = position[..., 0], position[..., 1]
        width = 1.5 * (1.0 + t / 100.0)
        return 0.1 * torch.exp(-0.5 * ((x - 1.0) ** 2 + y**2) / width) + 0.01 * torch.sin(y)


RIDGE = "a * exp(-0.5 * ((x - 1)^2 + y^2) / (w * (1 + t / s))) + 0.01 * sin(y)"


def _positions(n: int = 5000) -> torch.Tensor:
    torch.manual_seed(0)
    return torch.randn(n, 2) * 4.0


@pytest.mark.parametrize("t", [0.0, 7.45, 300.0])
def test_an_expression_field_equals_the_same_python_field(t: float) -> None:
    field = ExpressionField(RIDGE, {"a": 0.1, "w": 1.5, "s": 100.0})
    got = field(_positions(), t)
    assert got.dtype == torch.float32 and got.shape == (5000,)
    assert torch.equal(got, _Ridge()(_positions(), t))


# the built-in fields' torch code before they were formulas (the reference, bit for bit)
def _gaussian(f: GaussianField, p: torch.Tensor, t: float) -> torch.Tensor:
    return f.amplitude * torch.exp(f.offset(p).square().sum(-1) * (-0.5 / f.variance))


def _dynamic(f: DynamicGaussianField, p: torch.Tensor, t: float) -> torch.Tensor:
    return f.amplitude * torch.exp(f.offset(p).square().sum(-1) * (-0.5 / f.variance_at(t)))


def _linear(f: LinearField, p: torch.Tensor, t: float) -> torch.Tensor:
    scaled = f.offset(p) * p.new_tensor(f.scale)
    return (f.amplitude - f.slope * torch.linalg.vector_norm(scaled, dim=-1)).clamp_min(f.floor)


def _exponential(f: ExponentialField, p: torch.Tensor, t: float) -> torch.Tensor:
    return f.amplitude * torch.exp(torch.linalg.vector_norm(f.offset(p), dim=-1) * (-1 / f.length))


def _constant(f: ConstantField, p: torch.Tensor, t: float) -> torch.Tensor:
    return torch.full(p.shape[:-1], f.value, dtype=p.dtype)


BUILTINS = [
    (GaussianField(), _gaussian),
    (GaussianField(amplitude=0.2, variance=2.0, peak=(1.5, 0.5)), _gaussian),
    (DynamicGaussianField(spread_time=5.0), _dynamic),
    (DynamicGaussianField(peak=(-1.0, 2.0)), _dynamic),
    (LinearField(), _linear),
    (LinearField(peak=(0.3, -1.0), floor=0.02), _linear),
    (ExponentialField(), _exponential),
    (ExponentialField(length=2.0, peak=(1.0, -0.5)), _exponential),
    (ConstantField(0.05), _constant),
]


@pytest.mark.parametrize(
    ("field", "reference"), BUILTINS, ids=lambda v: getattr(v, "__name__", repr(v)[:40])
)
def test_builtin_fields_compute_their_former_torch_code_bit_for_bit(field, reference) -> None:
    for n in (7, 5000):
        for t in (0.0, 0.85, 7.45):
            assert torch.equal(field(_positions(n), t), reference(field, _positions(n), t))


def test_the_ridge_config_builds_and_peaks_on_its_ridge() -> None:
    from surrogate.config import field_config

    field = build_field(field_config("ridge"))
    assert isinstance(field, ExpressionField) and field.peak == (1.0, 0.0)
    on, off = field(torch.tensor([[1.0, 7.0], [3.0, 7.0]]), 0.0).tolist()
    assert on == pytest.approx(0.1) and off < on
    later = field(torch.tensor([[3.0, 7.0]]), 200.0).item()
    assert later < off  # the ridge sharpens in time


@pytest.mark.parametrize(
    ("expression", "message"),
    [
        ("a * exp(-z^2)", "unknown variable or parameter 'z'"),
        ("a * gauss(x)", "unknown function 'gauss'"),
        ("x > 1", "must be a number"),
        ("a * (x +", "cannot parse"),
        ("", "expected a formula"),
    ],
)
def test_a_bad_formula_is_a_config_error_naming_it(expression: str, message: str) -> None:
    with pytest.raises(ConfigError, match=message):
        ExpressionField(expression, {"a": 0.1})
    with pytest.raises(ConfigError, match=message):
        build_field({"_target_": "surrogate.fields.ExpressionField", "expression": expression,
                     "parameters": {"a": 0.1}})  # fmt: skip


def test_parameters_must_be_finite_and_not_named_like_variables() -> None:
    with pytest.raises(ConfigError, match=r"field.parameters.a must be finite"):
        ExpressionField("a * x", {"a": float("nan")})
    with pytest.raises(ConfigError, match="parameter names"):
        ExpressionField("t * x", {"t": 1.0})


def test_one_tree_gives_both_codes_and_no_user_text() -> None:
    """Torch and numba code come from the same tree; the formula's text is not in them."""
    formula = field_formula("0.1 * exp(-hypot(x, y) / len)", ("len",))
    torch_code, numba_code = formula.torch_source(), formula.numba_source("f")
    assert "vector_norm" in torch_code and "_hypot" in numba_code
    assert "len" not in torch_code + numba_code  # parameters are read by index


def test_builtin_parameter_names_match_their_values() -> None:
    for field, _ in BUILTINS:
        assert tuple(field.parameter_values()) == field.parameter_names
        assert field.formula.parameters == ("peak_x", "peak_y", *field.parameter_names)


def test_an_expression_field_pickles_and_reads_the_same() -> None:
    import pickle

    field = ExpressionField(RIDGE, {"a": 0.1, "w": 1.5, "s": 100.0}, peak=(1.0, 0.0))
    again = pickle.loads(pickle.dumps(field))
    assert repr(again) == repr(field) and "_formula" not in repr(field)
    assert torch.equal(again(_positions(), 3.0), field(_positions(), 3.0))


@pytest.mark.parametrize("field", [DynamicGaussianField(), ExpressionField(RIDGE, {"a": 0.1,
                                   "w": 1.5, "s": 100.0})])  # fmt: skip
def test_torch_compile_traces_a_formula_field_in_one_graph(field) -> None:
    """The compiled torch step keeps one graph: a call is only the generated code."""
    import torch._dynamo as dynamo

    explained = dynamo.explain(lambda p, t: field(p, t) * 2.0)(_positions(100), 0.5)
    assert explained.graph_count == 1 and explained.graph_break_count == 0


def test_an_infinite_constant_exponent_is_code_not_a_name() -> None:
    """``x ^ INF`` (a constant exponent torch raises to directly) is ``math.inf`` in the
    generated torch code, not the undefined name ``inf``: 0, 1 and inf as IEEE powers give."""
    field = ExpressionField("(x / 2) ^ INF", {})
    got = field(torch.tensor([[1.0, 0.0], [2.0, 0.0], [3.0, 0.0]]), 0.0)
    assert got.tolist() == [0.0, 1.0, float("inf")]
