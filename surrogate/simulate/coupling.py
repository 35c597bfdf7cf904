"""The simulator's side of a coupled field (:mod:`surrogate.grid`): which cells change which
field, and the runs a coupled field cannot take part in yet.

The order within a step, the same for every decision layer: the agents read the field
(``body.inputs``), the decision layer gives phi after the window, the body moves, then each
coupled field takes its step with its cells' new positions and phi
(:meth:`~surrogate.grid.CoupledField.step`: their uptake and secretion, then diffusion).
"""

from __future__ import annotations

import itertools
from typing import Any

from torch import Tensor

from surrogate.errors import ConfigError
from surrogate.fields import Field, FieldBatch
from surrogate.grid.coupled import CoupledField, is_coupled
from surrogate.models.base import BodyState

__all__ = ["check_coupled_run", "coupled_blocks", "positions_of"]


def coupled_blocks(field: Field) -> list[tuple[CoupledField, slice]]:
    """Each coupled field of ``field`` and the cells that change it (all cells for a single
    field; a :class:`~surrogate.fields.FieldBatch`'s block for each of its fields).

    Raises:
        ConfigError: one coupled field object serving two blocks of a batch apart (their
            cells would share one state; give each replicate its own field).
    """
    if is_coupled(field):
        return [(field, slice(0, None))]  # type: ignore[list-item]
    if not isinstance(field, FieldBatch):
        return []
    starts = [0, *itertools.accumulate(field.sizes)][:-1]
    blocks = [(f, slice(a, a + n)) for f, a, n in zip(field.fields, starts, field.sizes,
                                                       strict=True) if is_coupled(f)]  # fmt: skip
    ids = [id(f) for f, _ in blocks]
    if len(set(ids)) < len(ids):
        raise ConfigError(
            "one coupled field object serves two blocks of a batch: its state would mix two "
            "replicates' cells; give each replicate its own field (copy.deepcopy)"
        )
    return blocks  # type: ignore[return-value]


def check_coupled_run(field: Any, *, dt: float, shards: int = 1) -> None:
    """Refuse, by name, the settings a coupled field cannot run with: population shards, and a
    dt beyond the field's own limit (:meth:`~surrogate.grid.CoupledField.validate`). Nothing
    for a given field.

    Every loop runs: the torch step, eager or ``compile=true`` (the compiled kernel is the
    agents' step: the field is read before it and stepped after it, eagerly,
    :meth:`~surrogate.simulate.Simulator.step`), and the per-cell kernel (one step per call,
    the field read before and stepped after each, :meth:`~surrogate.simulate.Simulator.advance`).
    """
    if not is_coupled(field):
        return
    name = type(field).__name__
    if shards != 1:
        raise ConfigError(
            f"shard.count={shards}: a population in a coupled field ({name}: the agents change "
            f"it every step) cannot be split into independent shards (every cell changes the "
            f"field the others read); run it whole (shard.count=1)"
        )
    field.validate(dt)


def positions_of(body: BodyState, field: CoupledField) -> Tensor:
    """The cells' ``position`` (``(n, 2)``) for a coupled field's exchange.

    Raises:
        ConfigError: the body keeps no ``position``.
    """
    position = body.get("position")
    if position is None:
        raise ConfigError(
            f"a coupled field ({type(field).__name__}) needs a body whose state has a "
            f"'position' (n x 2, mm); this body's state has {sorted(body)}"
        )
    return position
