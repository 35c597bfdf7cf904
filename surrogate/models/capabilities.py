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
``exact_class_step``          exact one-window class-to-class law               none
``expected_class_next``       a window's expected class law                     none
``expected_phi_next``         a window's expected label                         none
``cell_step_seconds``         its cost per cell-step                            the base estimate
============================  ================================================  ==============

A body's optional ``histogram_grids`` (``{observable: (lo, hi, width)}``) is read through
:func:`histogram_grids_of` (default: none, the recorder then builds a grid from the data), its
``start_size`` (coordinates of a start position) through :func:`start_size_of`. A
model's compiled per-cell kernel is a method of :class:`~surrogate.models.base.Model`
(``cell_kernel``, ``kernel_precompiler``) whose base raises/returns None; ``cell_kernel``
receives the decision layer packed by the engine (:mod:`surrogate.models.packed`), never the
layer itself.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import torch
from torch import Tensor

from surrogate.models.randoms import Randoms

if TYPE_CHECKING:
    from surrogate.models.base import InternalState


def _callable(obj: Any, name: str) -> Callable[..., Any] | None:
    value = getattr(obj, name, None)
    return value if callable(value) else None


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
    names = getattr(internal, "class_names", None)
    classify = _callable(internal, "classes")
    if not names or classify is None:
        return None
    lumps = tuple(int(v) for v in getattr(internal, "class_lumps", ()))
    if len(lumps) != len(names) or set(lumps) != {0, 1}:
        raise ValueError(
            f"{type(internal).__name__}: class_lumps must give phi (0/1) for each of its "
            f"{len(names)} class_names, both lumps present; got {lumps}"
        )
    return LumpClasses(tuple(str(n) for n in names), lumps, classify)


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
    bounds = getattr(internal, "signal_bounds", None)
    return dict(bounds) if bounds else None


def expected_phi_next_of(internal: Any) -> Callable[[InternalState, Tensor, float], Tensor] | None:
    """``expected_phi_next(state, x, dt) -> (n,)``: P(phi = 1 after a window | state, x), the
    window's expected label, or None."""
    return _callable(internal, "expected_phi_next")


def cell_step_seconds_of(internal: Any) -> Callable[[float], float] | None:
    """``cell_step_seconds(dt) -> s``: ``internal``'s own estimate of one cell-step's cost, or
    None."""
    return _callable(internal, "cell_step_seconds")


def burn_in_of(internal: Any) -> float:
    """Seconds of internal dynamics each cell's initial state is simulated for (``burn_in``,
    where the model draws its initial state by simulating from fixed counts: a network too
    large to enumerate; 0 where the stationary law is drawn exactly)."""
    seconds = float(getattr(internal, "burn_in", 0.0) or 0.0)
    if seconds <= 0 or getattr(internal, "state_space", None) is not None:
        return 0.0
    return seconds


def feature_names_of(internal: Any) -> tuple[str, ...]:
    """The derived inputs ``internal`` can compute (``feature_names``; default none)."""
    return tuple(getattr(internal, "feature_names", None) or ())


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
        bool(getattr(internal, "fusable", False))
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
    "LumpClasses",
    "burn_in_of",
    "cell_step_seconds_of",
    "concat_states",
    "concat_states_of",
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
    "randoms_of",
    "signal_bounds_of",
    "start_size_of",
]
