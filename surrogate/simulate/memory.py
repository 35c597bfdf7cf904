"""Memory for the two-state chain: a switch clock per cell (``gp.history=age``).

The two-state chain phi' ~ Bernoulli(psi_phi(z)) forgets everything but phi and the current
inputs; the internal network does not. Right after a switch its hidden state sits at the lump's
entrance (E. coli: a run starts with just enough motors turned CCW, so it is likelier to end
soon), and it settles as the cell stays. A semi-Markov clock, ``a`` = the time since phi last
changed, carries that memory for any model: psi_phi(z, a) is learned from the full model's own
transitions, the clock is one float per cell, and the chain stays a chain over phi (plus ``a``).

* :class:`MemoryDecision`: the chain with the clock as psi's last input.
* :func:`tick`: the clock's rule (one place; collect, the decision layer and the tests use it).
* :func:`exact_age_table`: the exact psi_phi(signal, a) of cells adapted to their inputs, for an
  internal model with ``exact_age_psi`` (a small state space): the route's limit, measured.

The clock is capped at ``max_age``: beyond it psi is taken as flat in ``a``. For E. coli the
exact psi at ages 5 s and 20 s differs by <= 3e-5 over dG in [-1.5, 2.5] (docs/fidelity.md).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING

import numpy as np
import pandas as pd
import torch
from torch import Tensor

if TYPE_CHECKING:
    from surrogate.gp.lookup import PsiLookupTable

from surrogate.errors import ConfigError
from surrogate.models.base import InternalModel
from surrogate.models.capabilities import exact_age_psi_of, signal_bounds_of
from surrogate.simulate.decision import AbstractDecision, RunProbability
from surrogate.simulate.stateful import StatefulDecision, carried_alias

#: the clock's input column (collect records it in seconds; psi takes it as its last input)
AGE = "phi_age"
#: a clock beyond every cap (steps): float32 counts exactly to 2^24 and then stays put
SETTLED = float(2**24)
#: gp.history choices
HISTORIES = ("none", "age")


def tick(age: Tensor, phi: Tensor, phi_next: Tensor) -> Tensor:
    """The clocks (steps since phi last changed) after a window: 0 where phi changed, else +1.

    Args:
        age: ``(n,)`` float clocks in steps.
        phi, phi_next: ``(n,)`` phi before and after the window (bool or float 0/1).
    """
    return torch.where(phi_next != phi, 0.0, age + 1.0)


def clock_steps(dt: float, max_age: float) -> int:
    """The cap in whole steps: ``max_age / dt`` rounded down (at least 1)."""
    return max(1, int(max_age / dt + 1e-9))


def clock_nodes(run_probability: object, dt: float) -> int | None:
    """``A`` when ``run_probability`` is a lookup table (or stacked tables) whose last axis is
    the clock with a node at every step, ``0, dt, ..., A dt``: the chain then reads the node
    of each cell's clock (one lerp less per step); else None (interpolation in seconds)."""
    names = tuple(getattr(run_probability, "input_names", ()))
    if not has_history(names) or not hasattr(run_probability, "evaluate_at_last_node"):
        return None
    tables = getattr(run_probability, "tables", [run_probability])
    steps = int(run_probability.shape[-1]) - 1  # type: ignore[attr-defined]
    for t in tables:
        lo, hi = t.ranges[-1]
        if lo != 0.0 or abs(hi - steps * dt) > 1e-6 * max(1.0, hi):
            return None
    return steps


def tabulate_with_clock(
    psi: RunProbability,
    lead_ranges: list[tuple[float, float]],
    input_names: tuple[str, ...],
    dt: float,
    max_age: float,
    lead_size: tuple[int, ...] | None = None,
) -> PsiLookupTable:
    """``psi`` over (lead inputs, clock) as a lookup table with a clock node at every step up
    to the cap (:func:`clock_nodes`), the lead axes as :meth:`PsiLookupTable.from_function`
    sizes them (4,096 nodes for one axis, 256 each for more) unless ``lead_size`` is given.

    Args:
        psi: ``psi(phi, [z, a])``, the clock (s) last.
        lead_ranges: ``(lo, hi)`` of each lead input.
        input_names: every input's name, the clock (``AGE``) last.
    """
    from surrogate.gp.lookup import PsiLookupTable  # the engine imports gp only where it tabulates

    steps = clock_steps(dt, max_age)
    k = len(lead_ranges)
    if lead_size is None:
        lead_size = (4096,) if k == 1 else (256,) * k
    table = PsiLookupTable.from_function(psi, [*lead_ranges, (0.0, steps * dt)], input_names,
                                         (*lead_size, steps + 1))  # fmt: skip
    table.node_axes = (k,)  # a clock takes whole steps, each a node
    return table


def with_age(z: Tensor, age_steps: Tensor, dt: float, max_age: float) -> Tensor:
    """``[z, min(age dt, max_age)]``: the abstraction's inputs with the clock (s) appended.

    Args:
        z: ``n x k`` inputs.
        age_steps: ``(n,)`` clocks in steps.
    """
    a = (age_steps * dt).clamp(max=max_age).to(z.dtype)
    return torch.cat([z, a.unsqueeze(1)], 1)


def history_setting(
    history: object, max_age: object, group: str, histories: Sequence[str] = HISTORIES
) -> tuple[str, float]:
    """Validate ``<group>.history`` (one of ``histories``: none | age, or the registered chain
    kinds', :func:`surrogate.kinds.chains.fit_chain`) and ``<group>.max_age`` (s, > 0)."""
    if history is None:
        history = "none"
    if history not in histories:
        raise ConfigError(f"{group}.history must be one of {list(histories)}, got {history!r}")
    if isinstance(max_age, bool) or not isinstance(max_age, int | float) or not max_age > 0:
        raise ConfigError(f"{group}.max_age must be a number of seconds > 0, got {max_age!r}")
    return str(history), float(max_age)


def has_history(input_names: tuple[str, ...] | list[str]) -> bool:
    """Whether a psi over ``input_names`` takes the switch clock (its last input)."""
    return len(input_names) > 0 and input_names[-1] == AGE


#: column flagging a clock that is only a lower bound (no switch seen since recording began)
CENSORED = "phi_age_censored"


def clock_rows(table: pd.DataFrame, max_age: float) -> pd.DataFrame:
    """The rows of a transitions table whose switch clock is known up to the cap, clipped.

    A censored clock (``phi_age_censored``: no switch since recording began) is a lower bound:
    known once it reaches ``max_age``; earlier censored rows are dropped (a few seconds at the
    start of a collection).

    Args:
        table: rows with ``phi_age`` (s) and ``phi_age_censored``.
        max_age: the clock's cap (s).
    """
    missing = [c for c in (AGE, CENSORED) if c not in table.columns]
    if missing:
        raise KeyError(missing)
    age = table[AGE].to_numpy(np.float64)
    keep = ~table[CENSORED].to_numpy(bool) | (age >= max_age)
    out = table.loc[keep].copy()
    out[AGE] = np.minimum(out[AGE].to_numpy(np.float64), max_age)
    return out.reset_index(drop=True)


class MemoryDecision(StatefulDecision, AbstractDecision):
    """The chain with a switch clock: phi' ~ Bernoulli(psi_phi(z, a)).

    ``a`` is the time (s) since the cell's phi last changed (0 right after a window that changed
    it), clipped at ``max_age``. Each cell carries its clock in steps (float32); cells start
    settled (at the cap), which the stage's equilibration (10 s by default) then overwrites.

    Args:
        run_probability: ``psi(phi, [z, a])``, the clock as the last input column.
        internal: the internal model (initial phi).
        featurize: ``x (n x d) -> z (n x k)``, the abstraction's other inputs.
        max_age: the clock's cap (s).
        name: the layer's name in logs and manifests.
        dt: the window the chain will step (s): with a table that has a clock node at every
            step (:func:`tabulate_with_clock`) each cell reads its clock's node instead of
            interpolating in seconds (cheaper; the same values up to float rounding).

    Example:
        >>> psi = lambda phi, z: (z[:, -1] >= 1.0).float()  # switch once 1 s in a state
        >>> layer = MemoryDecision(psi, internal, max_age=2.0)  # doctest: +SKIP
    """

    age = carried_alias("(n,) float32: steps since phi last changed; None before initialize.")

    def __init__(
        self,
        run_probability: RunProbability,
        internal: InternalModel,
        featurize: Callable[[Tensor], Tensor] | None = None,
        max_age: float = 5.0,
        name: str = "abstract",
        dt: float | None = None,
    ) -> None:
        if not max_age > 0:
            raise ValueError(f"max_age must be > 0 s, got {max_age}")
        super().__init__(run_probability, internal, featurize, name)
        self.max_age = float(max_age)
        self.dt = dt
        #: the clock's last node (steps) when psi is a table with a node per step, else None
        self.clock_nodes = None if dt is None else clock_nodes(run_probability, dt)

    def restacked(self, run_probability: RunProbability, name: str) -> MemoryDecision:
        """The same chain with its clock over another psi (stacked tables)."""
        return MemoryDecision(run_probability, self.internal, self.featurize, self.max_age, name,
                              self.dt)  # fmt: skip

    def probability_at(self, phi: Tensor, x: Tensor, age: Tensor, dt: float) -> Tensor:
        """p(phi' = 1) ``(n,)`` at phi, inputs ``x`` (``n x d``) and clocks ``age`` (steps)."""
        z = x if self.featurize is None else self.featurize(x)
        if self.clock_nodes is not None:
            if dt != self.dt:
                raise ValueError(f"a chain built for dt={self.dt} stepped with dt={dt}")
            node = age.clamp(max=float(self.clock_nodes)).long()
            return self.run_probability.evaluate_at_last_node(phi, z, node)  # type: ignore[attr-defined]
        return self._psi(phi, with_age(z, age, dt, self.max_age))

    def initialize(self, x: Tensor) -> Tensor:
        """phi from the internal model's stationary law; clocks settled."""
        phi = super().initialize(x)
        self.start_at(x, phi)
        return phi

    def start_at(self, x: Tensor, phi: Tensor) -> None:
        """Clocks settled, as :meth:`initialize` starts them (phi given, not drawn)."""
        self.age = torch.full((x.shape[0],), SETTLED, dtype=torch.float32, device=x.device)

    def _eager_step(
        self, phi: Tensor, x: Tensor, dt: float, carried: Tensor
    ) -> tuple[Tensor, Tensor]:
        """One Bernoulli draw per cell; the clocks tick."""
        p = self.probability_at(phi, x, carried, dt)
        nxt = torch.rand_like(p) < p
        return nxt, tick(carried, phi.bool(), nxt)

    def _pure_step(
        self, phi: Tensor, x: Tensor, dt: float, u: Tensor, carried: Tensor
    ) -> tuple[Tensor, Tensor]:
        """phi' = [u < psi_phi(z, a)]; the clocks tick (phi as float 0/1)."""
        p = self.probability_at(phi, x, carried, dt)
        nxt = (u[0] < p).to(torch.float32)
        return nxt, tick(carried, phi.to(torch.float32), nxt)


def can_age(internal: object) -> bool:
    """Whether ``internal`` gives the exact psi with a clock (``exact_age_psi``, optional)."""
    return exact_age_psi_of(internal) is not None and signal_bounds_of(internal) is not None


@torch.no_grad()
def exact_age_table(
    internal: InternalModel, dt: float, max_age: float, size: int = 1024
) -> PsiLookupTable:
    """The exact psi_phi(signal, a) of adapted cells as a table over (signal, ``AGE``).

    The age axis has a node at every step ``k dt`` up to the cap (so a clock in whole steps
    reads its exact value); the signal axis ``size`` nodes over the model's signal bounds.

    Args:
        internal: a model with ``exact_age_psi(signal (n x 1), dt, max_steps) -> n x 2 x (A+1)``
            and ``signal_bounds`` over its one signal.
        dt: window length (s).
        max_age: the clock's cap (s); rounded down to whole steps.
        size: signal nodes.
    """
    from surrogate.gp.lookup import PsiLookupTable  # the engine imports gp only where it tabulates

    names = tuple(internal.signal_names)
    if len(names) != 1 or not can_age(internal):
        raise ValueError(f"an exact psi with a clock needs one signal and exact_age_psi: {names}")
    steps = clock_steps(dt, max_age)
    lo, hi = signal_bounds_of(internal)[names[0]]  # type: ignore[index]
    signal = torch.linspace(lo, hi, size, dtype=torch.float64).unsqueeze(1)
    psi = exact_age_psi_of(internal)(signal, dt, steps)  # type: ignore[misc]  # (size, 2, A+1)
    table = psi.permute(1, 0, 2).contiguous()
    return PsiLookupTable(table, [(lo, hi), (0.0, steps * dt)], (*names, AGE))


__all__ = [
    "AGE",
    "CENSORED",
    "HISTORIES",
    "SETTLED",
    "MemoryDecision",
    "can_age",
    "clock_nodes",
    "clock_rows",
    "clock_steps",
    "exact_age_table",
    "has_history",
    "history_setting",
    "tabulate_with_clock",
    "tick",
    "with_age",
]
