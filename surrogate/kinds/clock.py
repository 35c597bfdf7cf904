"""The switch clock (``gp.history=age``, ``decision.history=age``) as one kind module: the chain
over phi whose psi also reads the time since phi last changed, capped at ``gp.max_age``. It
holds all the clock kind decides: its gp keys (:data:`GP_CLOCK`), its refusals and its clock
axis (:meth:`SwitchClock.configure`, :meth:`~SwitchClock.check_exact_history`), its training
rows, its learned layer (:meth:`~SwitchClock.decision_layer`) and its exact one
(:func:`exact_clock_decision`). The engine's blocks it builds them from stay in
:mod:`surrogate.simulate.memory` (:class:`MemoryDecision`, :func:`tabulate_with_clock`,
:func:`exact_age_table`, :func:`clock_rows`)."""

from __future__ import annotations

import logging
import math
from collections.abc import Mapping
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import pandas as pd
import torch
from torch import Tensor

from surrogate.errors import ArtefactError, ConfigError
from surrogate.gp import load_psi
from surrogate.gp.training import GPSettings
from surrogate.kinds.base import (
    PROBABILITY_FLOOR,
    ChainKind,
    LayerRequest,
    bernoulli_log_likelihood,
    register_chain_kind,
)
from surrogate.kinds.decision import DecisionMode
from surrogate.kinds.files import PSI
from surrogate.kinds.layers import psi_decision
from surrogate.models.base import FeatureMap, Model
from surrogate.simulate.decision import DecisionLayer
from surrogate.simulate.memory import (
    AGE,
    SETTLED,
    MemoryDecision,
    can_age,
    clock_rows,
    exact_age_table,
    tabulate_with_clock,
)

log = logging.getLogger(__name__)

#: keys of the gp group that only a fit with a switch clock reads (gp.history=age)
GP_CLOCK = ("history", "max_age", "clock_bins", "clock_knee")


def clock_knee(gp_config: Mapping[str, Any]) -> float | None:
    """``gp.clock_knee`` validated: None (the clock read in seconds, a linear axis) or the knee
    (s) of a log axis, ``log(1 + a / knee)``: the clock's bins and psi's lengthscale then
    resolve short ages finely and long ones coarsely, so a long cap (a slow tail) keeps the
    resolution a short one had (a period's peak)."""
    knee = gp_config.get("clock_knee")
    if knee is None:
        return None
    if (isinstance(knee, bool) or not isinstance(knee, int | float) or not math.isfinite(knee)
            or not knee > 0):  # fmt: skip
        raise ConfigError(f"gp.clock_knee must be a number of seconds > 0 (a log clock axis, "
                          f"log(1 + age / knee)) or null (linear), got {knee!r}")  # fmt: skip
    return float(knee)


@register_chain_kind
@dataclass(frozen=True)
class SwitchClock(ChainKind):
    """The chain over phi whose psi also reads the time since phi last changed
    (``gp.history=age``, capped at ``gp.max_age``): train records the clocks, simulate keeps
    one per cell (:mod:`surrogate.simulate.memory`)."""

    history = "age"
    gp_keys = GP_CLOCK
    title = "switch clock"
    clock = True
    complexity = 1
    candidate = True

    def configure(
        self,
        gp_config: Mapping[str, Any],
        gp: GPSettings,
        inputs: tuple[str, ...],
        internal: Any,
        model_name: str,
    ) -> tuple[GPSettings, tuple[str, ...]]:
        """The switch clock is psi's last input, with its own bin count (``gp.clock_bins``),
        in seconds or on a log axis (``gp.clock_knee``, :func:`clock_knee`)."""
        clock_knee(gp_config)
        if isinstance(gp.bins, int) and gp.bins:  # the clock's axis has its own bin count
            clock_bins = gp_config.get("clock_bins", gp.bins)
            gp = replace(gp, bins=(*[gp.bins] * len(inputs), clock_bins))  # validated again
        return gp, (*inputs, AGE)

    def fit_identity(self, gp: Mapping[str, Any], *args: Any, **kwargs: Any) -> dict[str, Any]:
        """The base's, without ``clock_knee: null`` (a linear clock keeps the identity it had
        before the log axis existed)."""
        out = super().fit_identity(gp, *args, **kwargs)
        if out.get("clock_knee", 0) is None:
            del out["clock_knee"]
        return out

    def input_warps(self, gp_config: Mapping[str, Any]) -> dict[str, float]:
        """The clock on a log axis where ``gp.clock_knee`` is set (:func:`clock_knee`)."""
        knee = clock_knee(gp_config)
        return {} if knee is None else {AGE: knee}

    @classmethod
    def check_exact_history(cls, mode: DecisionMode, internal: Any, model_name: str) -> None:
        """An exact psi with a clock needs a table and the model's ``exact_age_psi``."""
        if not mode.table or not can_age(internal):
            raise ConfigError(
                f"decision.history=age needs decision.mode=lookup and a model with an exact "
                f"psi over one signal with a clock (exact_age_psi); model "
                f"{model_name!r}, mode {mode.name!r}"
            )

    def training_rows(
        self, table: pd.DataFrame, max_age: float, where: str, source: Any
    ) -> pd.DataFrame:
        """The rows whose clock is known, clipped at ``max_age`` (:func:`clock_rows`)."""
        try:
            return clock_rows(table, max_age)
        except KeyError as exc:
            raise ArtefactError(
                f"{where} has no switch clocks ({exc.args[0]}) for gp.history=age: it was "
                f"collected before collect recorded them; delete it and re-run "
                f"`{getattr(source, 'command', lambda: 'python3 scripts/collect.py')()}`"
            ) from exc

    def decision_layer(
        self, request: LayerRequest, directory: Path
    ) -> tuple[DecisionLayer, dict[str, Any]]:
        """psi with its switch clock (its last input) as a layer that keeps one clock per cell,
        capped at ``request.max_age`` s and ticking every ``request.dt``: a table with a clock
        node at every step (each cell reads its clock's node; ``request.size`` sizes the lead
        inputs) or the classifier (:class:`MemoryDecision`)."""
        model, dt, max_age, size = request.model, request.dt, request.max_age, request.size
        psi, _ = load_psi(Path(directory) / PSI, device=request.device)
        featurize = model.featurizer(psi.input_names[:-1])
        lead = tuple(size[:-1]) if size else None
        return psi_decision(
            psi, request.mode, request.device,
            lambda run: MemoryDecision(run, model.internal, featurize, max_age, dt=dt),
            lambda ranges: tabulate_with_clock(psi, ranges[:-1], psi.input_names, dt, max_age,
                                               lead),
        )  # fmt: skip

    def window_log_likelihoods(
        self, layer: DecisionLayer, inputs: Tensor, phi: Tensor, dt: float
    ) -> Tensor:
        """log Bernoulli(phi_{t+1}; psi_{phi_t}(x_t, a_t)), the clock ``a_t`` computed
        from the observed phi history: it starts settled (at the cap) as the layer's does,
        since the time since the last switch before a sequence is unknown
        (:meth:`marginal_window_log_likelihoods` marginalises it instead)."""
        if not isinstance(layer, MemoryDecision):
            raise TypeError(f"the switch clock scores a MemoryDecision, got {layer!r}")
        n, steps, d = inputs.shape
        phi = phi.to(torch.float32)
        # the clock in steps before each window: settled, then 0 after a change, else +1
        changed = (phi[:, 1:] != phi[:, :-1]).to(torch.float32)
        age = torch.empty(n, steps, dtype=torch.float32, device=phi.device)
        age[:, 0] = SETTLED
        for t in range(1, steps):  # over windows (cells in the batch): a recurrence
            age[:, t] = torch.where(changed[:, t - 1] > 0, 0.0, age[:, t - 1] + 1.0)
        p = layer.probability_at(phi[:, :-1].reshape(-1), inputs.reshape(n * steps, d),
                                 age.clamp(max=SETTLED).reshape(-1), dt)  # fmt: skip
        return bernoulli_log_likelihood(p, phi[:, 1:].reshape(-1)).reshape(n, steps)

    def marginal_window_log_likelihoods(
        self,
        layer: DecisionLayer,
        inputs: Tensor,
        phi: Tensor,
        dt: float,
        ranked: Tensor | None = None,
    ) -> Tensor:
        """:meth:`window_log_likelihoods` (``ranked`` where already computed) with the clock
        up to each sequence's first switch marginalised over its unknown age
        (:func:`unknown_age_windows`), the windows after it as they are."""
        settled = super().marginal_window_log_likelihoods(layer, inputs, phi, dt, ranked)
        if not isinstance(layer, MemoryDecision):  # given ``ranked``, nothing has checked it
            raise TypeError(f"the switch clock scores a MemoryDecision, got {layer!r}")
        unknown, before = unknown_age_windows(layer, inputs, phi.to(torch.float32), dt)
        return torch.where(before, unknown, settled)

    def exact_layer(self, request: LayerRequest) -> tuple[DecisionLayer, dict[str, Any]]:
        """The exact psi with a switch clock (:func:`exact_clock_decision`, a table)."""
        return exact_clock_decision(request.model, request.dt, request.max_age,
                                    request.device), {}  # fmt: skip


def unknown_age_windows(
    layer: MemoryDecision, inputs: Tensor, phi: Tensor, dt: float
) -> tuple[Tensor, Tensor]:
    """The clock's log-likelihood of each window up to and including a sequence's first switch,
    the clock unknown: the forward algorithm over its ages ``0 .. A`` steps (``A`` the cap's
    node, an absorbing "settled" age), started from its stationary law within the first
    phi's lump at the first window's inputs (an age ``a < A`` in proportion to the chance of
    lasting ``a`` windows, ``A`` that chance over its switching probability), as the hidden
    phases and K lumps start from theirs. Read settled at the cap instead (as a run's layer
    starts), a sequence's unknown first sojourn favours a longer cap with no memory behind
    it: Vilar's clocks at 22, 44 and 88 s scored -0.0224, -0.0211 and -0.0204 per window,
    and after each cell's first switch -0.01395 to -0.01396 alike (docs/choice.md).

    Args:
        layer: the clock's layer.
        inputs: ``n x T x d`` the model's inputs in each window.
        phi: ``n x (T + 1)`` phi (0/1) before the first window and after each.
        dt: the window (s).

    Returns:
        ``n x T`` float64 log p(phi_t+1 | phi_0..t, inputs) with the clock unknown (0 past
        the first switch), and ``n x T`` bool: the windows up to the first switch.
    """
    n, steps = inputs.shape[:2]
    device = inputs.device
    nodes = layer.clock_nodes
    top = int(nodes) if nodes is not None else max(1, math.ceil(layer.max_age / dt - 1e-9))
    ages = torch.arange(top + 1, dtype=torch.float32, device=device)
    changed = phi[:, 1:] != phi[:, :-1]
    first = torch.where(changed.any(1), changed.to(torch.float32).argmax(1),
                        torch.full((n,), steps, device=device, dtype=torch.long))  # fmt: skip
    before = torch.arange(steps, device=device).unsqueeze(0) <= first.unsqueeze(1)
    terms = torch.zeros(n, steps, dtype=torch.float64, device=device)
    origin = phi[:, 0]

    def switching(cells: Tensor, t: int) -> Tensor:  # (m, A + 1): leaving phi_0 at each age
        m = cells.numel()
        p = layer.probability_at(origin[cells].repeat_interleave(top + 1),
                                 inputs[cells, t].repeat_interleave(top + 1, 0),
                                 ages.repeat(m), dt).reshape(m, top + 1).to(torch.float64)  # fmt: skip
        leave = torch.where(origin[cells].unsqueeze(1) > 0, 1.0 - p, p)
        return leave.clamp(PROBABILITY_FLOOR, 1.0 - PROBABILITY_FLOOR)

    cells = torch.arange(n, device=device)
    if n == 0 or steps == 0:
        return terms, before
    p = switching(cells, 0)
    # the stationary law at the first inputs: lasting a windows, and the settled age's tail
    last = torch.cumprod(1.0 - p, 1)
    law = torch.cat([torch.ones(n, 1, dtype=torch.float64, device=device), last[:, :-1]], 1)
    law[:, top] = law[:, top] / p[:, top]
    law = law / law.sum(1, keepdim=True)
    for t in range(steps):  # over windows; the cells not yet switched in the batch
        if t > 0:
            p = switching(cells, t)
        went = changed[cells, t]
        stay, go = law * (1.0 - p), law * p
        terms[cells, t] = torch.where(went, go.sum(1), stay.sum(1)).log()
        kept = ~went
        cells, stay = cells[kept], stay[kept]
        if cells.numel() == 0:
            break
        law = torch.zeros_like(stay)
        law[:, 1:] = stay[:, :-1]
        law[:, top] += stay[:, top]
        law = law / law.sum(1, keepdim=True)
    return terms, before


def exact_clock_decision(
    model: Model, dt: float, max_age: float, device: torch.device, name: str = "exact"
) -> MemoryDecision:
    """The chain driven by the exact psi with a switch clock (``decision.history=age``): a
    table over the signal and the clock, capped at ``max_age`` s; ``name`` labels the layer."""
    table = exact_age_table(model.internal, dt, max_age).to(device)
    featurize = FeatureMap(model.internal, model.internal.signal_names)
    log.info("exact psi with a switch clock: table %s over %s", table.shape, table.input_names)
    return MemoryDecision(table, model.internal, featurize, max_age, name, dt)
