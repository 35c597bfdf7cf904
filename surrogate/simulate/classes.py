"""K lumps: a chain over classes finer than phi (``gp.lumps=classes``).

The two-state chain keeps only phi; a clock (:mod:`surrogate.simulate.memory`) adds the time
since phi last changed. The K-lumps route keeps more of the internal state: the model declares
``C`` classes, each inside one lump (E. coli: phi and the number of CCW motors, 7 classes), and
the abstraction is a chain over the classes whose one-window law ``P(class' | class, z)`` is
learned per origin class (:func:`surrogate.gp.classes.fit_class_chain`) or, for a model with a
small state space, computed exactly for adapted cells (:func:`exact_class_table`). The agent
still moves by phi, the class's lump.

* :class:`ClassTable`: the law tabulated on a grid of the abstraction's inputs. A cell draws its
  next class at the grid node picked by *stochastic rounding* (per input axis, the upper node
  with probability equal to the cell's fractional position): the drawn class then has exactly
  the multilinear interpolation of the nodes' laws, for one uniform per axis, and the draw reads
  one row of ``C`` cumulative probabilities.
* :class:`ClassDecision`: the decision layer (eager and fused; one int64 class per cell).

Measured (docs/fidelity.md, "Memory"): on L1 with the exact law the 7-class chain is within the
full model's noise at 1e5 cells (distance KS <= 0.008, 5 % critical value 0.0105) where the
two-state chain and the clock are not (0.024 and 0.020).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import Any, ClassVar

import torch
from torch import Tensor

from surrogate.models.base import InternalModel, Randoms
from surrogate.models.capabilities import (
    ClassCount,
    exact_class_step_of,
    lump_classes_of,
    signal_bounds_of,
)
from surrogate.simulate.stateful import StatefulDecision, carried_alias

#: where a chain's cells start: the internal model's initial law, or the chain's stationary law
STARTS = ("internal", "stationary")
#: repeated squarings of a node's law for its stationary law (2^40 windows at most)
STATIONARY_SQUARINGS = 40

#: collect's class columns (the class at the window's start and end)
CLASS, CLASS_NEXT = "phi_class", "phi_class_next"
#: collect's columns of the count the classes bin, where the model gives it
#: (:func:`~surrogate.models.capabilities.class_count_of`): the window's start and end, so the
#: bins are applied when the table is read (:func:`reclassify`)
CLASS_COUNT, CLASS_COUNT_NEXT = "phi_class_count", "phi_class_count_next"


def expected_class_column(b: int) -> str:
    """Collect's column of P(class after the window = ``b`` | the state at its start)."""
    return f"{CLASS_NEXT}_expected_{b}"


def reclassify(table: Any, count: ClassCount) -> Any:
    """``table`` (a transitions DataFrame) with its class columns (:data:`CLASS`,
    :data:`CLASS_NEXT`) made from its count columns by ``count``'s bins, where it has them:
    the classes of the model reading it, whatever bins it was collected with. A table without
    count columns is returned as it is."""
    if CLASS_COUNT not in table.columns or CLASS_COUNT_NEXT not in table.columns:
        return table
    out = table.copy()
    for value, phi, column in ((CLASS_COUNT, "phi", CLASS), (CLASS_COUNT_NEXT, "phi_next",
                                                              CLASS_NEXT)):  # fmt: skip
        # copies: a DataFrame's arrays may be read-only
        classes = count.classify(torch.tensor(table[value].to_numpy(), dtype=torch.float64),
                                 torch.tensor(table[phi].to_numpy(), dtype=torch.int64))  # fmt: skip
        out[column] = classes.to(torch.int16).numpy()
    return out


#: gp.lumps choices
LUMPINGS = ("phi", "classes")


class ClassTable:
    """A K-state chain's one-window law over a grid of the abstraction's inputs.

    Args:
        probabilities: ``C x n_1 x ... x n_d x C``: ``[a, i_1..i_d, b]`` = P(class' = b |
            class = a, z at node (i_1..i_d)); rows are renormalised (negatives clamped to 0).
        bounds: ``d`` pairs ``(lo, hi)``: the grid's span per input (nodes evenly spaced; an
            axis of one node is constant); inputs outside are clamped to it.
        input_names: the ``d`` inputs' names (the abstraction's z columns).
        class_names: the ``C`` classes' names.
        class_lumps: the phi (0/1) of each class.
        dt: the window the law is for (s).

    Example:
        >>> p = torch.tensor([[0.9, 0.1], [0.2, 0.8]]).reshape(2, 1, 2).expand(2, 3, 2)
        >>> table = ClassTable(p, [(0.0, 1.0)], ("z",), ("off", "on"), (0, 1), 0.05)
        >>> nxt = table.draw(torch.tensor([0, 1]), torch.tensor([[0.5], [0.5]]), torch.rand(2, 2))
    """

    def __init__(
        self,
        probabilities: Tensor,
        bounds: Sequence[tuple[float, float]],
        input_names: Sequence[str],
        class_names: Sequence[str],
        class_lumps: Sequence[int],
        dt: float,
    ) -> None:
        c = len(class_names)
        d = len(input_names)
        shape = tuple(probabilities.shape[1:-1])
        if (
            probabilities.dim() != d + 2
            or probabilities.shape[0] != c
            or probabilities.shape[-1] != c
            or len(bounds) != d
            or len(class_lumps) != c
        ):
            raise ValueError(
                f"a class table needs probabilities C x n_1..n_d x C for C={c} classes and "
                f"d={d} inputs (with d bounds and C lumps); got {tuple(probabilities.shape)}, "
                f"{len(bounds)} bounds, {len(class_lumps)} lumps"
            )
        if not torch.isfinite(probabilities).all():
            raise ValueError("class table: probabilities must be finite")
        p = probabilities.detach().to(torch.float64).clamp_min(0.0)
        total = p.sum(-1, keepdim=True)
        if bool((total <= 0).any()):
            raise ValueError("class table: every row needs some probability")
        cdf = (p / total).cumsum(-1)
        cdf[..., -1] = 1.0  # a uniform in [0, 1) never passes the last class
        self.cdf = cdf.to(torch.float32).reshape(-1, c).contiguous()  # (C * prod(shape), C)
        self.shape = shape
        self.bounds = [(float(lo), float(hi)) for lo, hi in bounds]
        self.input_names = tuple(input_names)
        self.class_names = tuple(class_names)
        self.class_lumps = tuple(int(v) for v in class_lumps)
        self.dt = float(dt)
        strides, s = [], 1
        for n in reversed(shape):
            strides.append(s)
            s *= n
        self._strides = tuple(reversed(strides))
        self._origin_stride = s
        self.lumps = torch.tensor(self.class_lumps, dtype=torch.float32)
        self._start_cdf: Tensor | None = None  # the stationary law's rows, made when drawn

    @property
    def n_classes(self) -> int:
        """``C``."""
        return len(self.class_names)

    @property
    def strides(self) -> tuple[int, ...]:
        """Rows of :attr:`cdf` between neighbouring nodes of each input axis."""
        return self._strides

    @property
    def origin_stride(self) -> int:
        """Rows of :attr:`cdf` per origin class (the grid's node count)."""
        return self._origin_stride

    @property
    def device(self) -> torch.device:
        """Where the table lives."""
        return self.cdf.device

    def to(self, device: torch.device | str) -> ClassTable:
        """Move the table to ``device`` in place; return self."""
        self.cdf = self.cdf.to(device)
        self.lumps = self.lumps.to(device)
        return self

    def probabilities(self) -> Tensor:
        """The tabulated law ``C x n_1..n_d x C`` (float32, from the cumulative rows)."""
        cdf = self.cdf.reshape(self.n_classes, *self.shape, self.n_classes)
        return torch.diff(cdf, dim=-1, prepend=torch.zeros_like(cdf[..., :1]))

    def _positions(self, z: Tensor) -> list[tuple[Tensor, Tensor]]:
        """Per axis: the lower node (int64) and the fraction towards the next one.

        A NaN input gets node 0 and a NaN fraction (never rounded up), as the compiled
        kernel does: the draw reads the first node's law and :meth:`law` is NaN; the NaN
        reaches :meth:`Simulator.check_state` through the body's check of its inputs.
        """
        out = []
        for j, n in enumerate(self.shape):
            lo, hi = self.bounds[j]
            if n == 1 or hi <= lo:
                zero = torch.zeros(z.shape[0], dtype=torch.int64, device=z.device)
                out.append((zero, torch.zeros(z.shape[0], device=z.device)))
                continue
            pos = ((z[:, j].to(torch.float32) - lo) * ((n - 1) / (hi - lo))).clamp(0.0, n - 1.0)
            node = pos.floor().clamp(max=n - 2)
            # NaN stays NaN through clamp and floor; as an index it would be undefined
            out.append((node.nan_to_num(0.0).long(), pos - node))
        return out

    def draw(self, origin: Tensor, z: Tensor, u: Tensor) -> Tensor:
        """Each cell's next class.

        Args:
            origin: ``(n,)`` int64 classes now.
            z: ``n x d`` the abstraction's inputs.
            u: ``(d + 1) x n`` uniforms in [0, 1): one per axis (stochastic rounding to a
                node), the last for the categorical draw.

        Returns:
            ``(n,)`` int64 classes after the window.
        """
        index = origin * self._origin_stride
        for j, (node, frac) in enumerate(self._positions(z)):
            index = index + (node + (u[j] < frac).long()) * self._strides[j]
        # class' = how many cumulative probabilities the uniform passes: one gather per class
        # (a fused loop when compiled, no n x C intermediate); the last is 1, never passed
        flat, base, last = self.cdf.reshape(-1), index * self.n_classes, u[-1]
        nxt = (last >= flat[base]).long()
        for b in range(1, self.n_classes - 1):
            nxt = nxt + (last >= flat[base + b]).long()
        return nxt

    def law(self, origin: Tensor, z: Tensor) -> Tensor:
        """P(class' | class = ``origin``, z) ``n x C``: the multilinear interpolation of the
        nodes' laws (what :meth:`draw` samples)."""
        positions = self._positions(z)
        p = self.probabilities().reshape(-1, self.n_classes)
        out = torch.zeros(z.shape[0], self.n_classes, device=z.device)
        for corner in range(2 ** len(self.shape)):
            index, weight = origin * self._origin_stride, torch.ones(z.shape[0], device=z.device)
            for j, (node, frac) in enumerate(positions):
                up = (corner >> j) & 1
                index = index + (node + up) * self._strides[j]
                weight = weight * (frac if up else 1.0 - frac)
            out = out + weight.unsqueeze(1) * p[index]
        return out

    def stationary(self) -> Tensor:
        """Each node's stationary law ``n_1..n_d x C`` (float64): the law after infinitely many
        windows from uniform classes, by repeated squaring of the node's ``C x C`` law (2^k
        windows after k squarings; a relaxing bin keeps its class ~3e4 windows, so ~30 do)."""
        c = self.n_classes
        p = self.probabilities().double().reshape(c, -1, c).transpose(0, 1).cpu()
        for _ in range(STATIONARY_SQUARINGS):
            q = p @ p
            q = q / q.sum(-1, keepdim=True)
            converged = bool((q - p).abs().max() < 1e-12)
            p = q
            if converged:
                break
        return p.mean(1).reshape(*self.shape, c)

    def stationary_at(self, z: Tensor) -> Tensor:
        """The stationary law at the inputs ``z`` (``n x d``) ``n x C`` (float32): the
        multilinear interpolation of the nodes' laws (:meth:`stationary`), what
        :meth:`draw_start` samples."""
        return self.read(self.stationary().reshape(-1, self.n_classes).to(torch.float32), z)

    def read(self, nodes: Tensor, z: Tensor) -> Tensor:
        """Values at the grid's nodes read at the inputs ``z`` (``n x d``) as :meth:`draw`
        picks nodes: their multilinear interpolation ``n x k``.

        Args:
            nodes: ``prod(shape) x k`` one row per node (C order, as :attr:`strides`).
            z: ``n x d`` the abstraction's inputs.
        """
        nodes = nodes.to(z.device)
        out = torch.zeros(z.shape[0], nodes.shape[1], dtype=nodes.dtype, device=z.device)
        positions = self._positions(z)
        for corner in range(2 ** len(self.shape)):
            index = torch.zeros(z.shape[0], dtype=torch.int64, device=z.device)
            weight = torch.ones(z.shape[0], dtype=nodes.dtype, device=z.device)
            for j, (node, frac) in enumerate(positions):
                up = (corner >> j) & 1  # an axis of one node: weight 0 on its missing upper
                index = index + (node + up).clamp(max=self.shape[j] - 1) * self._strides[j]
                weight = weight * (frac if up else 1.0 - frac)
            out = out + weight.unsqueeze(1) * nodes[index]
        return out

    def draw_start(self, z: Tensor, u: Tensor) -> Tensor:
        """Each cell's class drawn from the chain's stationary law at its inputs (the node
        picked by stochastic rounding, as :meth:`draw` does).

        Args:
            z: ``n x d`` the abstraction's inputs.
            u: ``(d + 1) x n`` uniforms in [0, 1): one per axis, the last for the class.

        Returns:
            ``(n,)`` int64 classes.
        """
        if self._start_cdf is None or self._start_cdf.device != self.cdf.device:
            cdf = self.stationary().reshape(-1, self.n_classes).cumsum(-1)
            cdf[:, -1] = 1.0  # a uniform in [0, 1) never passes the last class
            self._start_cdf = cdf.to(torch.float32).to(self.cdf.device)
        index = self.node_index(z, u)
        return (u[-1][:, None] >= self._start_cdf[index][:, :-1]).sum(-1)

    def node_index(self, z: Tensor, u: Tensor) -> Tensor:
        """Each cell's grid node (flat, ``(n,)`` int64) picked by stochastic rounding, as
        :meth:`draw` picks it: ``z`` ``n x d`` the inputs, ``u`` ``(d + 1) x n`` uniforms (the
        first ``d`` rows read)."""
        index = torch.zeros(z.shape[0], dtype=torch.int64, device=z.device)
        for j, (node, frac) in enumerate(self._positions(z)):
            index = index + (node + (u[j] < frac).long()) * self._strides[j]
        return index

    def to_state(self) -> dict[str, Any]:
        """Plain tensors and lists (``torch.save``-able, loads with ``weights_only=True``)."""
        return {
            "probabilities": self.probabilities().cpu(),
            "bounds": [list(b) for b in self.bounds],
            "input_names": list(self.input_names),
            "class_names": list(self.class_names),
            "class_lumps": list(self.class_lumps),
            "dt": self.dt,
        }

    @classmethod
    def from_state(cls, state: dict[str, Any]) -> ClassTable:
        """The table :meth:`to_state` wrote."""
        return cls(state["probabilities"], [tuple(b) for b in state["bounds"]],
                   state["input_names"], state["class_names"], state["class_lumps"],
                   state["dt"])  # fmt: skip


class TableDecision(StatefulDecision):
    """A chain over the states of a :class:`ClassTable` (the K-lumps classes, the hidden
    phases): each window a cell draws its next state from the table's law at its inputs, and
    phi is the state's lump. The subclasses give the first state (:meth:`initialize`).

    Args:
        table: the chain's law over its states.
        internal: the internal model (where cells start from its initial law).
        featurize: ``x (n x d) -> z (n x k)``, the table's inputs; identity by default.
        name: the layer's name in logs and manifests.
        start: one of :data:`STARTS` (what each subclass's start reads).
    """

    #: the chain's name in messages
    what: ClassVar[str] = "class chain"

    def __init__(
        self,
        table: ClassTable,
        internal: InternalModel,
        featurize: Callable[[Tensor], Tensor] | None = None,
        name: str = "classes",
        start: str = "internal",
    ) -> None:
        if start not in STARTS:
            raise ValueError(f"start must be one of {list(STARTS)}, got {start!r}")
        self.table = table
        self.internal = internal
        self.featurize = featurize
        self.name = name
        self.start = start
        self.randoms = Randoms(uniform=len(table.input_names) + 1)

    def _inputs(self, x: Tensor) -> Tensor:
        if self.table.device != x.device:
            self.table.to(x.device)
        return x if self.featurize is None else self.featurize(x)

    def _check_dt(self, dt: float) -> None:
        if not math.isclose(dt, self.table.dt, rel_tol=1e-9):
            raise ValueError(f"a {self.what} built for dt={self.table.dt} stepped with dt={dt}")

    def _eager_step(
        self, phi: Tensor, x: Tensor, dt: float, carried: Tensor
    ) -> tuple[Tensor, Tensor]:
        """One categorical draw per cell (bool phi')."""
        self._check_dt(dt)
        z = self._inputs(x)
        u = torch.rand(len(self.table.input_names) + 1, z.shape[0], device=z.device)
        nxt = self.table.draw(carried, z, u)
        return self.table.lumps[nxt] > 0, nxt

    def _pure_step(
        self, phi: Tensor, x: Tensor, dt: float, u: Tensor, carried: Tensor
    ) -> tuple[Tensor, Tensor]:
        """State' from the uniforms ``u`` (``(d + 1) x n``); phi' as float 0/1."""
        nxt = self.table.draw(carried, self._inputs(x), u)
        return self.table.lumps[nxt], nxt


class ClassDecision(TableDecision):
    """The K-lumps chain: class' drawn from the table's law at each cell's inputs; phi is the
    class's lump.

    Args:
        table: the chain's law (learned or exact) over the abstraction's inputs.
        internal: the internal model; it declares the classes (``class_names``,
            ``class_lumps``, ``classes``), and cells start in the class of an internal state
            drawn from its stationary law at their inputs (as the full model's cells do).
        featurize: ``x (n x d) -> z (n x k)``, the table's inputs; identity by default.
        name: the layer's name in logs and manifests.
        start: where cells start: ``internal``, the class of an internal state from the
            model's initial law at their inputs (the full model's start; for a network, its
            burn-in), or ``stationary``, the chain's own stationary law at their inputs
            (:meth:`ClassTable.draw_start`: no internal state is simulated).
    """

    cls = carried_alias("(n,) int64: each cell's class; None before initialize.")

    def __init__(
        self,
        table: ClassTable,
        internal: InternalModel,
        featurize: Callable[[Tensor], Tensor] | None = None,
        name: str = "classes",
        start: str = "internal",
    ) -> None:
        declared = lump_classes_of(internal)
        if declared is None:
            raise ValueError(f"{type(internal).__name__} declares no classes (class_names)")
        if declared.names != table.class_names or declared.lumps != table.class_lumps:
            raise ValueError(
                f"the class table's classes {table.class_names} are not the model's "
                f"{declared.names}"
            )
        super().__init__(table, internal, featurize, name, start)
        self._classify = declared.classify

    def initialize(self, x: Tensor) -> Tensor:
        """Each cell's first class (see ``start``) at its inputs ``x`` (``n x d``)."""
        z = self._inputs(x)
        if self.start == "stationary":
            u = torch.rand(len(self.table.input_names) + 1, z.shape[0], device=z.device)
            self.cls = self.table.draw_start(z, u)
        else:
            self.cls = self._classify(self.internal.initial_state(x)).to(x.device)
        return self.table.lumps[self.cls] > 0


@torch.no_grad()
def exact_class_table(internal: InternalModel, dt: float, size: int = 1024) -> ClassTable:
    """The exact class-to-class law of adapted cells over the model's one signal (the K-lumps
    route's limit), tabulated on ``size`` nodes over its ``signal_bounds``.

    Args:
        internal: a model with classes, ``exact_class_step`` and ``signal_bounds``.
        dt: window length (s).
        size: signal nodes.
    """
    names = tuple(internal.signal_names)
    declared = lump_classes_of(internal)
    step = exact_class_step_of(internal)
    bounds = signal_bounds_of(internal)
    if len(names) != 1 or declared is None or step is None or bounds is None:
        raise ValueError(
            f"an exact class chain needs one signal, classes, exact_class_step and "
            f"signal_bounds: {type(internal).__name__} has signals {names}"
        )
    lo, hi = bounds[names[0]]
    signal = torch.linspace(lo, hi, size, dtype=torch.float64).unsqueeze(1)
    law = step(signal, dt)  # (size, C, C)
    return ClassTable(law.permute(1, 0, 2), [(lo, hi)], names, declared.names, declared.lumps, dt)


def can_classify(internal: object) -> bool:
    """Whether ``internal`` declares K-lumps classes."""
    return lump_classes_of(internal) is not None


__all__ = [
    "CLASS",
    "CLASS_NEXT",
    "LUMPINGS",
    "STARTS",
    "ClassDecision",
    "ClassTable",
    "TableDecision",
    "can_classify",
    "exact_class_table",
    "expected_class_column",
]
