"""What the engine asks of a model beyond the required protocol, detected in one way.

An :class:`~surrogate.models.base.InternalModel` must give ``input_names``, ``signal_names``,
``lump_names``, ``initial_state``, ``advance`` and ``phi``. Everything else is optional: a
model declares a capability by giving the attribute (a method, or a property returning a
callable), and declares it absent by leaving it out or setting it to None (a property may
return None, e.g. a network whose state space is too large to enumerate). The engine reads
each capability only through the functions here, never with ``hasattr``/``getattr`` of its
own, and falls back to the defaults below where a model gives none:

============================  ================================================  ==============
capability                    what it is                                        default
============================  ================================================  ==============
``feature_names``/``features``  derived inputs                                  none; columns of x
``concat_states``             several populations' states as one                cat per tensor
``fusable``/``fused_advance``/``randoms``  the pure window (fused step)          the eager step
``exact_psi``                 exact lumped ``P(phi' = 1 | phi)``                none
``exact_age_psi``             the same with a switch clock                      none
``signal_bounds``             ``{signal: (lo, hi)}`` where the signal lives     none
``class_names``/``class_lumps``/``classes``  K lumps: classes finer than phi    none
``class_bins``                each class's bin of a count both lumps share       none
``class_count``               the count the classes bin, and the binning         none
``exact_class_step``          exact one-window class-to-class law               none
``expected_class_next``       a window's expected class law                     none
``expected_phi_next``         a window's expected label                         none
``cell_step_seconds``         its cost per cell-step                            the base estimate
``burn_in``/``state_space``   simulated burn-in of the initial state            none
``reseed_streams``            a copied state with its own random streams        the copy as is
``lump_formula``/``lump_expr``  the lump as a formula (inspect's report)        none
============================  ================================================  ==============

:data:`OPTIONAL_MEMBERS` lists these names once; the readers below take their names from it.
Since a misspelt optional member would be silently absent, :func:`check_members` (run by
:func:`surrogate.config.build_model` on every model it builds) refuses a public attribute of an
internal model that is not part of the contract but is one or two edits from an optional name
(``exact_psy`` for ``exact_psi``).

A body's optional ``histogram_grids`` (``{observable: (lo, hi, width)}``) is read through
:func:`histogram_grids_of` (default: none, the recorder then builds a grid from the data), its
``start_size`` (coordinates of a start position) through :func:`start_size_of`. A
model's compiled per-cell kernel is a method of :class:`~surrogate.models.base.Model`
(``cell_kernel``, ``kernel_precompiler``) whose base raises/returns None; ``cell_kernel``
receives the decision layer packed by the engine (:mod:`surrogate.models.packed`), never the
layer itself.
"""

from __future__ import annotations

import difflib
import functools
import inspect
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor

from surrogate.errors import ConfigError
from surrogate.models.randoms import Randoms

#: per-cell tensors an internal model carries from window to window (opaque to the engine;
#: :mod:`surrogate.models.base` re-exports it)
InternalState = tuple[Tensor, ...]

#: what an internal model must give (:class:`~surrogate.models.base.InternalModel`)
REQUIRED_MEMBERS: tuple[str, ...] = ("input_names", "signal_names", "lump_names", "initial_state",
                                     "advance", "phi")  # fmt: skip
#: the optional members the engine reads of an internal model, all through this module (the
#: table above): the one list of them
OPTIONAL_MEMBERS: tuple[str, ...] = (
    "feature_names", "features", "concat_states", "fusable", "fused_advance", "randoms",
    "exact_psi", "exact_age_psi", "signal_bounds", "class_names", "class_lumps", "classes",
    "class_bins", "class_count", "exact_class_step", "expected_class_next", "expected_phi_next",
    "cell_step_seconds", "burn_in", "state_space", "lump_formula", "lump_expr", "reseed_streams",
)  # fmt: skip
#: the most edits (insert, delete, substitute, swap two neighbours) between an attribute and an
#: optional name for the attribute to be taken for a misspelling of it
MAX_EDITS = 2
_OPTIONAL = frozenset(OPTIONAL_MEMBERS)


def _optional(obj: Any, name: str, default: Any = None) -> Any:
    """``obj``'s optional member ``name`` (one of :data:`OPTIONAL_MEMBERS`), else ``default``."""
    if name not in _OPTIONAL:
        raise KeyError(f"{name!r} is not in capabilities.OPTIONAL_MEMBERS; add it there")
    return getattr(obj, name, default)


def _callable(obj: Any, name: str) -> Callable[..., Any] | None:
    value = _optional(obj, name)
    return value if callable(value) else None


def edit_distance(a: str, b: str) -> int:
    """Edits (insert, delete, substitute, swap of two neighbours) turning ``a`` into ``b``."""
    before, row = None, list(range(len(b) + 1))
    for i, ca in enumerate(a, 1):
        current = [i]
        for j, cb in enumerate(b, 1):
            cost = min(row[j] + 1, current[j - 1] + 1, row[j - 1] + (ca != cb))
            if before is not None and i > 1 and j > 1 and ca == b[j - 2] and a[i - 2] == cb:
                cost = min(cost, before[j - 2] + 1)
            current.append(cost)
        before, row = row, current
    return row[-1]


def misspelt_members(internal: Any) -> dict[str, str]:
    """``{attribute: optional name}`` for each public attribute of ``internal`` outside the
    contract that is at most :data:`MAX_EDITS` edits from an optional name (the closest, by
    :func:`difflib.get_close_matches`). Reads only the names (``dir``), never the values."""
    known = _OPTIONAL | set(REQUIRED_MEMBERS)
    out = {}
    for name in dir(internal):
        if name.startswith("_") or name in known:
            continue
        near = [o for o in OPTIONAL_MEMBERS
                if abs(len(o) - len(name)) <= MAX_EDITS and edit_distance(name, o) <= MAX_EDITS]  # fmt: skip
        if near:
            out[name] = (difflib.get_close_matches(name, near, n=1, cutoff=0.0) or near)[0]
    return out


def check_members(internal: Any, where: str = "model") -> None:
    """Refuse (ConfigError) an internal model with a public attribute that looks like a
    misspelt optional member (:func:`misspelt_members`): the engine would read the capability
    as absent and silently fall back to its default."""
    found = misspelt_members(internal)
    if found:
        names = "; ".join(f"{type(internal).__name__}.{name}: did you mean {meant!r}?"
                          for name, meant in found.items())  # fmt: skip
        raise ConfigError(
            f"{where}: not a member of the internal-model contract: {names} (a misspelt optional "
            f"member would be silently absent; rename it, or prefix it with '_' if it is the "
            f"model's own; the optional members: surrogate.models.capabilities.OPTIONAL_MEMBERS)"
        )


def exact_psi_of(internal: Any) -> Callable[[Tensor, float], Tensor] | None:
    """``exact_psi(signal (n x k), dt) -> n x 2`` of ``internal``, or None where it has none."""
    return _callable(internal, "exact_psi")


def has_exact_psi(internal: Any) -> bool:
    """Whether ``internal`` offers the exact lumped psi (:func:`exact_psi_of` is not None)."""
    return exact_psi_of(internal) is not None


def exact_age_psi_of(internal: Any) -> Callable[[Tensor, float, int], Tensor] | None:
    """``exact_age_psi(signal (n x k), dt, max_steps) -> n x 2 x (max_steps + 1)`` of
    ``internal`` (the exact psi with a switch clock), or None."""
    return _callable(internal, "exact_age_psi")


@dataclass(frozen=True)
class LumpClasses:
    """The K-lumps classes an internal model declares: finer than phi, each inside one lump.

    Attributes:
        names: ``C`` class names.
        lumps: ``C`` ints, the phi (0/1) of each class.
        classify: ``classes(state) -> (n,)`` int64, each cell's class.
    """

    names: tuple[str, ...]
    lumps: tuple[int, ...]
    classify: Callable[[InternalState], Tensor]


def lump_classes_of(internal: Any) -> LumpClasses | None:
    """``internal``'s K-lumps classes (``class_names``, ``class_lumps`` and ``classes(state)``),
    or None where it declares none; a declaration that does not add up is an error."""
    names = _optional(internal, "class_names")
    classify = _callable(internal, "classes")
    if not names or classify is None:
        return None
    lumps = tuple(int(v) for v in _optional(internal, "class_lumps", ()))
    if len(lumps) != len(names) or set(lumps) != {0, 1}:
        raise ValueError(
            f"{type(internal).__name__}: class_lumps must give phi (0/1) for each of its "
            f"{len(names)} class_names, both lumps present; got {lumps}"
        )
    return LumpClasses(tuple(str(n) for n in names), lumps, classify)


@dataclass(frozen=True)
class ClassCount:
    """The count an internal model's K-lumps classes are bins of, apart from the bins: a
    collection stores the count (:attr:`values`) so that the bins are applied when it is read
    (:attr:`classify`), and a change of bins alone reuses the collection.

    Attributes:
        variable: the count, e.g. a species id or ``"P + 2 * P2"`` (it defines the values).
        digest: a digest of the classes, bins included.
        values: ``values(state) -> (n,)`` float64, each cell's count.
        classify: ``classify(values (n,), phi (n,)) -> (n,)`` int64, the class of each count
            in lump phi (as ``classes(state)`` gives it).
    """

    variable: str
    digest: str
    values: Callable[[InternalState], Tensor]
    classify: Callable[[Tensor, Tensor], Tensor]


def class_count_of(internal: Any) -> ClassCount | None:
    """The count ``internal``'s classes bin (:class:`ClassCount`), or None where it declares
    none (no classes, or classes that are no bins of one count)."""
    count = _optional(internal, "class_count")
    return count if isinstance(count, ClassCount) else None


def class_bins_of(internal: Any) -> tuple[int, ...] | None:
    """Each class's bin of one count whose bins both lumps share (a flip keeps the bin), or
    None (:mod:`surrogate.gp.class_relaxation`)."""
    bins = _optional(internal, "class_bins")
    return None if bins is None else tuple(int(b) for b in bins)


def expected_class_next_of(
    internal: Any,
) -> Callable[[InternalState, Tensor, float], Tensor] | None:
    """``expected_class_next(state, x, dt) -> n x C``: the law of the class after a window
    given the state now (the K-lumps chain's expected label), or None."""
    return _callable(internal, "expected_class_next")


def exact_class_step_of(internal: Any) -> Callable[[Tensor, float], Tensor] | None:
    """``exact_class_step(signal (n x k), dt) -> n x C x C``: the exact class-to-class law of
    adapted cells over a window, or None."""
    return _callable(internal, "exact_class_step")


def signal_bounds_of(internal: Any) -> dict[str, tuple[float, float]] | None:
    """``{signal name: (lo, hi)}`` where ``internal``'s signal lives, or None where it declares
    none (an empty mapping counts as none)."""
    bounds = _optional(internal, "signal_bounds")
    return dict(bounds) if bounds else None


def expected_phi_next_of(internal: Any) -> Callable[[InternalState, Tensor, float], Tensor] | None:
    """``expected_phi_next(state, x, dt) -> (n,)``: P(phi = 1 after a window | state, x), the
    window's expected label, or None."""
    return _callable(internal, "expected_phi_next")


def cell_step_seconds_of(
    internal: Any, device: torch.device | str = "cpu"
) -> Callable[[float], float] | None:
    """``cell_step_seconds(dt) -> s``: ``internal``'s own estimate of one cell-step's cost on
    ``device`` (passed where its ``cell_step_seconds`` takes a ``device``), or None."""
    estimate = _callable(internal, "cell_step_seconds")
    if estimate is None or "device" not in inspect.signature(estimate).parameters:
        return estimate
    return functools.partial(estimate, device=device)


def burn_in_of(internal: Any) -> float:
    """Seconds of internal dynamics each cell's initial state is simulated for (``burn_in``,
    where the model draws its initial state by simulating from fixed counts: a network too
    large to enumerate; 0 where the stationary law is drawn exactly)."""
    seconds = float(_optional(internal, "burn_in", 0.0) or 0.0)
    if seconds <= 0 or _optional(internal, "state_space") is not None:
        return 0.0
    return seconds


def reseed_streams_of(internal: Any) -> Callable[[InternalState], InternalState] | None:
    """``reseed_streams(state) -> state``: the same state with fresh random streams drawn from
    torch's generator, for a model whose state carries its own random streams (a network on
    the compiled SSA), or None where the state holds none (its randomness comes from torch's
    generator at each window, so a copy of the state is already a run of its own)."""
    return _callable(internal, "reseed_streams")


def lump_formula_of(internal: Any) -> str | None:
    """The lump as the formula it was written as (``lump_formula``, e.g. ``"D >= 2"``), or
    None where the model's phi is its own code."""
    formula = _optional(internal, "lump_formula")
    return None if formula is None else str(formula)


def lump_expr_of(internal: Any) -> Any:
    """The lump's parsed expression (``lump_expr``, a :class:`~surrogate.ctmc.kinetics.Expr`
    over species counts), or None."""
    return _optional(internal, "lump_expr")


def feature_names_of(internal: Any) -> tuple[str, ...]:
    """The derived inputs ``internal`` can compute (``feature_names``; default none)."""
    return tuple(_optional(internal, "feature_names") or ())


def features_fn_of(internal: Any) -> Callable[[Tensor, Sequence[str]], Tensor]:
    """``features(x (n x d), names) -> n x len(names)`` of ``internal``: its own ``features``
    where it has one, else the named columns of ``x`` (a model without derived inputs)."""
    own = _callable(internal, "features")
    if own is not None:
        return own
    inputs = list(internal.input_names)

    def columns(x: Tensor, names: Sequence[str]) -> Tensor:
        unknown = [n for n in names if n not in inputs]
        if unknown:
            raise ValueError(f"{type(internal).__name__} has no features; unknown inputs {unknown}")
        return x[:, [inputs.index(n) for n in names]]

    return columns


def features_of(internal: Any, x: Tensor, names: Sequence[str]) -> Tensor:
    """Inputs or features ``names`` at inputs ``x`` (``n x d``) -> ``n x len(names)`` (see
    :func:`features_fn_of`)."""
    return features_fn_of(internal)(x, names)


def concat_states_of(internal: Any) -> Callable[[Sequence[InternalState]], InternalState]:
    """How ``internal`` joins several populations' states, cells in order: its own
    ``concat_states``, else :func:`concat_states` (each tensor concatenated along cells)."""
    return _callable(internal, "concat_states") or concat_states


def concat_states(states: Sequence[InternalState]) -> InternalState:
    """The default join: the i-th tensors of every state concatenated along dimension 0."""
    return tuple(torch.cat(parts) for parts in zip(*states, strict=True))


def is_fusable(internal: Any) -> bool:
    """Whether ``internal`` has a pure window (``fusable`` true and a ``fused_advance``);
    otherwise the simulator runs its eager ``advance``."""
    return (
        bool(_optional(internal, "fusable", False))
        and _callable(internal, "fused_advance") is not None
    )


def randoms_of(obj: Any, name: str = "randoms") -> Randoms:
    """The random rows a pure function of ``obj`` (an internal model or body) needs per cell
    and step: its ``name`` attribute (``randoms``, ``adapt_randoms``), default none."""
    value = getattr(obj, name, None)
    return value if isinstance(value, Randoms) else Randoms()


def start_size_of(body: Any) -> int | None:
    """How many coordinates a start position of ``body`` has (``start_size``, e.g. 2 for a
    body in the plane), checked when a stage reads its ``start``; None (the default): any
    non-empty list, left to the body's ``initial_state``."""
    size = getattr(body, "start_size", None)
    return None if size is None else int(size)


def histogram_grids_of(body: Any) -> dict[str, Any]:
    """``{observable: grid}`` a body declares for its histograms (``histogram_grids``, each
    ``(lo, hi, width)``, a mapping with those keys or a ``HistogramGrid``); default none."""
    grids = getattr(body, "histogram_grids", None)
    return dict(grids) if isinstance(grids, Mapping) else {}


__all__ = [
    "MAX_EDITS",
    "OPTIONAL_MEMBERS",
    "REQUIRED_MEMBERS",
    "ClassCount",
    "LumpClasses",
    "burn_in_of",
    "cell_step_seconds_of",
    "check_members",
    "class_bins_of",
    "class_count_of",
    "concat_states",
    "concat_states_of",
    "edit_distance",
    "exact_age_psi_of",
    "exact_class_step_of",
    "exact_psi_of",
    "expected_class_next_of",
    "expected_phi_next_of",
    "feature_names_of",
    "features_fn_of",
    "features_of",
    "has_exact_psi",
    "histogram_grids_of",
    "is_fusable",
    "lump_classes_of",
    "lump_expr_of",
    "lump_formula_of",
    "misspelt_members",
    "randoms_of",
    "reseed_streams_of",
    "signal_bounds_of",
    "start_size_of",
]
