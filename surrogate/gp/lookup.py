"""A dense table of psi over 1-3 declared input axes with multilinear interpolation.

Evaluating the GP costs O(M) kernel evaluations per query; the table costs 2^d gathers and
2^d - 1 lerps, with no Python loop over cells and no host sync, so it suits 1e5-1e6 cells per
step. Beyond three inputs use the classifier itself (``decision.mode=classifier``).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from typing import Any

import torch
from torch import Tensor

from surrogate.errors import ArtefactError, ConfigError, NumericalError

#: ``psi(phi (n,), z (n x d)) -> p(phi' = 1) (n,)``
PsiFunction = Callable[[Tensor, Tensor], Tensor]

STATE_FORMAT = "surrogate.gp.lookup/2"
MAX_AXES = 3

Range = tuple[float, float]


class PsiLookupTable:
    """Multilinear interpolation of psi on a regular grid over a box of ``d`` <= 3 inputs.

    Args:
        table: ``2 x n_1 [x n_2 [x n_3]]`` values of p(phi' = 1); index 0: phi = 0, 1: phi = 1.
        ranges: ``d`` pairs (lo, hi): node i of axis a is ``lo + i (hi - lo) / (n_a - 1)``.
        input_names: names of the ``d`` input columns (what the table is a function of).

    Example:
        >>> table = PsiLookupTable.from_function(lambda phi, z: z[:, 0].sigmoid(),
        ...                                      [(-5.0, 5.0)], ("dG",), size=(101,))
        >>> table(torch.tensor([1]), torch.tensor([[0.0]]))
        tensor([0.5000])
    """

    #: each row's value depends on that row's inputs only, bit for bit, whatever the number of
    #: rows (elementwise interpolation): cells of several runs may share one call
    rowwise = True

    def __init__(
        self, table: Tensor, ranges: Sequence[Range], input_names: Sequence[str] | None = None
    ) -> None:
        d = table.dim() - 1
        if not 1 <= d <= MAX_AXES or table.shape[0] != 2 or min(table.shape[1:]) < 2:
            raise ConfigError(
                f"lookup table must have shape (2, n_1, ..., n_d) with 1 <= d <= {MAX_AXES} and "
                f"every n >= 2, got {tuple(table.shape)}"
            )
        if len(ranges) != d:
            raise ConfigError(f"lookup table has {d} axes but {len(ranges)} ranges")
        for r in ranges:
            _check_range(r)
        self.table = table.to(torch.float32).contiguous()
        self.ranges: list[Range] = [(float(lo), float(hi)) for lo, hi in ranges]
        self.input_names = tuple(input_names) if input_names else tuple(f"x{i}" for i in range(d))
        if len(self.input_names) != d:
            raise ConfigError(f"lookup table has {d} axes but names {self.input_names}")
        # (lo, nodes per unit) per axis as a tensor, not Python floats: torch.compile would
        # bake floats into the graph, so every newly trained table (other data range) would
        # miss the compile cache
        self._scale = [
            (n - 1) / (hi - lo) for n, (lo, hi) in zip(self.shape, self.ranges, strict=True)
        ]
        self._affine = torch.tensor(
            [[lo, sc] for (lo, _), sc in zip(self.ranges, self._scale, strict=True)],
            dtype=torch.float32, device=self.table.device,
        )  # fmt: skip
        strides = []
        stride = 1
        for n in reversed(self.shape):
            strides.append(stride)
            stride *= n
        self._strides = list(reversed(strides))
        self._layer = stride  # elements per phi layer
        self.check_finite = True
        #: axes whose inputs only take node values (a switch clock ticking by steps, noded at
        #: every step): :meth:`max_deviation` checks them at their nodes, not between them
        self.node_axes: tuple[int, ...] = ()

    @property
    def shape(self) -> tuple[int, ...]:
        """Grid nodes per axis."""
        return tuple(int(s) for s in self.table.shape[1:])

    @property
    def device(self) -> torch.device:
        """Device of the table."""
        return self.table.device

    @property
    def affine(self) -> Tensor:
        """``d x 2`` float32 (a copy): per axis its low end and grid nodes per unit, the map
        from an input ``v`` to grid units ``(v - lo) * nodes_per_unit`` that
        :meth:`evaluate` uses."""
        return self._affine.clone()

    @property
    def strides(self) -> tuple[int, ...]:
        """Elements between neighbouring nodes of each axis in a layer of the flat table."""
        return tuple(self._strides)

    @property
    def layer_size(self) -> int:
        """Elements per phi layer of the flat table (``prod(shape)``)."""
        return int(self._layer)

    @property
    def domain(self) -> dict[str, Range]:
        """``{input name: (lo, hi)}`` of the grid box."""
        return dict(zip(self.input_names, self.ranges, strict=True))

    def nodes(self) -> list[Tensor]:
        """Node coordinates per axis (float64 CPU tensors)."""
        return [
            torch.linspace(lo, hi, n, dtype=torch.float64)
            for (lo, hi), n in zip(self.ranges, self.shape, strict=True)
        ]

    @classmethod
    @torch.no_grad()
    def from_function(
        cls,
        psi: PsiFunction,
        ranges: Sequence[Range],
        input_names: Sequence[str] | None = None,
        size: Sequence[int] | None = None,
    ) -> PsiLookupTable:
        """Tabulate ``psi(phi, z)`` (a classifier, the exact psi, ...) on a regular grid.

        ``size`` defaults to 256 nodes per axis (4,096 for one axis). The table lives on
        ``psi.device`` when it has one, else on the CPU. A ``psi`` with a ``tabulator()``
        method (:meth:`PsiClassifier.tabulator <surrogate.gp.predictor.PsiClassifier.tabulator>`)
        is tabulated through the function it returns, a faster form of the same values.
        """
        d = len(ranges)
        if size is None:
            size = (4096,) if d == 1 else (256,) * d
        size = tuple(int(s) for s in size)
        if len(size) != d or min(size) < 2:
            raise ConfigError(f"lookup size must be {d} integers >= 2, got {size}")
        for r in ranges:
            _check_range(r)
        device = getattr(psi, "device", torch.device("cpu"))
        tabulator = getattr(psi, "tabulator", None)
        evaluate = tabulator() if callable(tabulator) else psi
        grid = grid_nodes(ranges, size).to(device)
        layers = []
        for phi in (0, 1):
            phis = torch.full((grid.shape[0],), phi, dtype=torch.long, device=device)
            values = evaluate(phis, grid.to(torch.float32))
            layers.append(values.to(device, torch.float32).reshape(size))
        return cls(torch.stack(layers), ranges, input_names)

    def to(self, device: torch.device | str) -> PsiLookupTable:
        """Move the table to ``device`` in place; return self."""
        self.table = self.table.to(device)
        self._affine = self._affine.to(device)
        return self

    def __call__(self, phi: Tensor, z: Tensor) -> Tensor:
        """Interpolated p(phi' = 1), float32, on the input's device; refuses NaN/inf inputs while
        ``check_finite`` is true (a host sync per call)."""
        if self.check_finite and not bool(torch.isfinite(z).all()):
            raise NumericalError(f"PsiLookupTable got NaN or infinite inputs {self.input_names}")
        return self.evaluate(phi, z)

    def evaluate(self, phi: Tensor, z: Tensor) -> Tensor:
        """Pure interpolation (no checks, no host sync): inputs outside the box are clamped to
        its edge; NaN inputs give NaN out, never a bad index. ``phi`` 0/1 is not checked."""
        dev = self.table.device
        out_device = z.device
        z = z.to(dev, torch.float32).reshape(-1, len(self.shape))
        base = phi.to(dev).reshape(-1).long() * self._layer
        origin = [self._affine[a, 0] for a in range(len(self.shape))]
        scale = [self._affine[a, 1] for a in range(len(self.shape))]
        out = _interpolate(self.table.view(-1), self.shape, self._strides, base, z, origin, scale)
        return out.to(out_device)

    def evaluate_at_last_node(self, phi: Tensor, z: Tensor, node: Tensor) -> Tensor:
        """Interpolation over every axis but the last, at node ``node`` of the last (e.g. a
        switch clock in whole steps on a table with a node per step): one lerp per lead axis
        instead of two, the same numbers as :meth:`evaluate` at that node's coordinate.

        Args:
            phi: ``(n,)`` 0/1.
            z: ``n x (d - 1)`` the lead inputs.
            node: ``(n,)`` integer node indices of the last axis (clamped into the grid).
        """
        dev = self.table.device
        out_device = z.device
        d = len(self.shape) - 1
        z = z.to(dev, torch.float32).reshape(-1, d)
        k = node.to(dev).reshape(-1).long().clamp(0, self.shape[-1] - 1)
        base = phi.to(dev).reshape(-1).long() * self._layer + k * self._strides[-1]
        origin = [self._affine[a, 0] for a in range(d)]
        scale = [self._affine[a, 1] for a in range(d)]
        out = _interpolate(self.table.view(-1), self.shape[:-1], self._strides[:-1], base, z,
                           origin, scale)  # fmt: skip
        return out.to(out_device)

    @torch.no_grad()
    def max_deviation(self, psi: PsiFunction, n_check: int | None = 4096, seed: int = 0) -> float:
        """Max |table - psi| over cell centres (midway between nodes on every axis but
        :attr:`node_axes`, at their nodes), where multilinear interpolation error peaks for
        smooth surfaces; all centres of both layers when ``n_check`` is None or larger than
        their number, else a random subset.

        A clock axis is checked at its nodes: a cell's clock is a whole number of steps, each
        a node, so psi between two steps is never read (Tyson's clock at 1 s: 1.3e-2 midway
        between steps, 5.5e-6 at them; an error the chain never makes)."""
        mids = [g if a in self.node_axes else 0.5 * (g[:-1] + g[1:])
                for a, g in enumerate(self.nodes())]  # fmt: skip
        counts = [len(m) for m in mids]
        total = 2
        for c in counts:
            total *= c
        if n_check is None or n_check >= total:
            flat = torch.arange(total)
        else:
            if n_check < 1:
                raise ConfigError(f"n_check must be >= 1, got {n_check}")
            flat = torch.randperm(total, generator=torch.Generator().manual_seed(seed))[:n_check]
        cols = []
        rest = flat.clone()
        for m, c in zip(reversed(mids), reversed(counts), strict=True):
            cols.append(m[rest % c])
            rest = rest // c
        phi = rest
        z = torch.stack(list(reversed(cols)), -1).to(torch.float32)
        device = getattr(psi, "device", self.device)
        exact = psi(phi.to(device), z.to(device)).to("cpu", torch.float64)
        approx = self.evaluate(phi, z).to("cpu", torch.float64)
        return float((approx - exact).abs().max())

    def to_state(self) -> dict[str, Any]:
        """Tensors and plain values only (``torch.load(weights_only=True)``-safe)."""
        return {
            "format": STATE_FORMAT,
            "table": self.table.detach().cpu().clone(),
            "ranges": [list(r) for r in self.ranges],
            "input_names": list(self.input_names),
        }

    @classmethod
    def from_state(
        cls, state: Mapping[str, Any], device: torch.device | str = "cpu"
    ) -> PsiLookupTable:
        """Inverse of :meth:`to_state`."""
        if state.get("format") != STATE_FORMAT:
            raise ArtefactError(
                f"not a psi lookup table state (format {state.get('format')!r}, "
                f"expected {STATE_FORMAT!r})"
            )
        ranges = [tuple(r) for r in state["ranges"]]
        return cls(state["table"].to(device), ranges, state["input_names"])


def grid_nodes(ranges: Sequence[Range], size: Sequence[int]) -> Tensor:
    """Every node of a regular grid, ``prod(size) x d`` float64, the last axis fastest."""
    axes = [
        torch.linspace(float(lo), float(hi), int(n), dtype=torch.float64)
        for (lo, hi), n in zip(ranges, size, strict=True)
    ]
    return torch.stack([g.reshape(-1) for g in torch.meshgrid(*axes, indexing="ij")], -1)


def _check_range(r: Sequence[float]) -> None:
    lo, hi = (float(v) for v in r)
    if not lo < hi:
        raise ConfigError(f"lookup range must satisfy lo < hi, got {tuple(r)}")


def _interpolate(
    flat: Tensor,
    shape: Sequence[int],
    strides: Sequence[int],
    base: Tensor,
    z: Tensor,
    origin: Sequence[Tensor],
    scale: Sequence[Tensor],
) -> Tensor:
    """Multilinear interpolation in the flat table ``flat`` at ``z`` (``n x d``): ``base``
    (``n``, long) is each query's layer offset, node coordinates along axis a are
    ``(z[:, a] - origin[a]) * scale[a]`` (0-d or per-query ``(n,)`` tensors)."""
    fracs, offsets = [], []
    for a, n in enumerate(shape):
        u = ((z[:, a] - origin[a]) * scale[a]).clamp(0.0, n - 1)
        # lower node kept <= n - 2 so the upper one exists (u = n - 1 gets frac 1). Clamped
        # as an integer so the compiler can prove the bounds and a fused step keeps its loop
        # vectorised (a NaN test here made it scalar, 2-3x). A NaN's integer is unspecified
        # in C++ (x86 and CUDA give INT64_MIN or 0); the clamp brings any value into range, and
        # NaN still reaches the output through the fraction (tested eager and compiled)
        i = u.floor().long().clamp(0, n - 2)
        fracs.append(u - i)
        base = base + i * strides[a]
        offsets.append(strides[a])
    # gather the 2^d corners (last axis fastest), then lerp along the last axis first
    corners = [base]
    for off in offsets:
        corners = [c for b in corners for c in (b, b + off)]
    values = [flat[c] for c in corners]
    for frac in reversed(fracs):
        values = [torch.lerp(values[i], values[i + 1], frac) for i in range(0, len(values), 2)]
    return values[0]


class StackedPsiLookup:
    """Several lookup tables of one grid shape over the same inputs, each for a contiguous
    block of cells: one interpolation over all the blocks' cells instead of one per table.

    Cell j of block k is interpolated in ``tables[k]`` with that table's own box, exactly as
    ``tables[k].evaluate`` would (the same arithmetic, bit for bit).

    Args:
        tables: the tables (same shape, input names and device).
        sizes: cells per block, in order (the queries' first dimension is ``sum(sizes)``).

    Example:
        >>> a = PsiLookupTable.from_function(lambda phi, z: z[:, 0].sigmoid(), [(-5.0, 5.0)],
        ...                                  ("dG",), size=(101,))
        >>> b = PsiLookupTable.from_function(lambda phi, z: 0.5 + 0 * z[:, 0], [(0.0, 1.0)],
        ...                                  ("dG",), size=(101,))
        >>> StackedPsiLookup([a, b], [1, 1])(torch.tensor([1, 1]), torch.zeros(2, 1))
        tensor([0.5000, 0.5000])
    """

    check_finite = False
    rowwise = True  # as PsiLookupTable

    def __init__(self, tables: Sequence[PsiLookupTable], sizes: Sequence[int]) -> None:
        if not tables or len(tables) != len(sizes):
            raise ValueError("StackedPsiLookup needs one size per table")
        first = tables[0]
        for t in tables[1:]:
            if (t.shape, t.input_names, t.device) != (first.shape, first.input_names, first.device):
                raise ValueError(
                    "stacked lookup tables need one shape, input names and device; got "
                    f"{t.shape} {t.input_names} {t.device} vs "
                    f"{first.shape} {first.input_names} {first.device}"
                )
        self.tables = list(tables)
        self.sizes = [int(n) for n in sizes]
        self.input_names = first.input_names
        self.shape = first.shape
        self._strides = first._strides
        dev = first.device
        self.table = torch.stack([t.table for t in tables]).contiguous()  # (K, 2, *shape)
        block = torch.repeat_interleave(
            torch.arange(len(tables), device=dev), torch.tensor(self.sizes, device=dev)
        )
        self._block_base = block * (2 * first._layer)  # (n,) offset of each cell's table
        self._layer = first._layer
        affine = torch.stack([t._affine for t in tables])[block]  # (n, d, 2)
        self._origin = [affine[:, a, 0].contiguous() for a in range(len(self.shape))]
        self._scale = [affine[:, a, 1].contiguous() for a in range(len(self.shape))]

    @property
    def device(self) -> torch.device:
        """Device of the tables."""
        return self.table.device

    def evaluate(self, phi: Tensor, z: Tensor) -> Tensor:
        """Pure interpolation of every cell in its block's table (see
        :meth:`PsiLookupTable.evaluate`); ``phi`` and ``z`` cover all blocks' cells."""
        dev = self.table.device
        out_device = z.device
        z = z.to(dev, torch.float32).reshape(-1, len(self.shape))
        base = self._block_base + phi.to(dev).reshape(-1).long() * self._layer
        flat = self.table.view(-1)
        out = _interpolate(flat, self.shape, self._strides, base, z, self._origin, self._scale)
        return out.to(out_device)

    def evaluate_at_last_node(self, phi: Tensor, z: Tensor, node: Tensor) -> Tensor:
        """:meth:`PsiLookupTable.evaluate_at_last_node` for every cell in its block's table."""
        dev = self.table.device
        out_device = z.device
        d = len(self.shape) - 1
        z = z.to(dev, torch.float32).reshape(-1, d)
        k = node.to(dev).reshape(-1).long().clamp(0, self.shape[-1] - 1)
        base = (self._block_base + phi.to(dev).reshape(-1).long() * self._layer
                + k * self._strides[-1])  # fmt: skip
        flat = self.table.view(-1)
        out = _interpolate(flat, self.shape[:-1], self._strides[:-1], base, z,
                           self._origin[:-1], self._scale[:-1])  # fmt: skip
        return out.to(out_device)

    __call__ = evaluate


__all__ = ["PsiFunction", "PsiLookupTable", "StackedPsiLookup", "grid_nodes"]
