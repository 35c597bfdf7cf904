"""A dense (phi, m, L) table of psi with bilinear interpolation, for fast per-step simulation.

Evaluating the GP costs O(M) kernel evaluations per query; the table costs four gathers and
three lerps, with no Python loop and no host sync, so it suits 1e5-1e6 cells per step.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any

import torch
from torch import Tensor

from surrogate.errors import ArtefactError, ConfigError, NumericalError

PsiFunction = Callable[[Tensor, Tensor, Tensor], Tensor]

STATE_FORMAT = "surrogate.gp.lookup/1"


class PsiLookupTable:
    """Bilinear interpolation of psi on a regular grid over the box ``m_range`` x ``L_range``.

    Args:
        table: (2, n_m, n_L) values of p(RUN next); index 0 = phi TUMBLE, 1 = phi RUN.
        m_range, L_range: the grid box; node i of m is ``m_lo + i * (m_hi - m_lo) / (n_m - 1)``.
    """

    def __init__(
        self, table: Tensor, m_range: tuple[float, float], L_range: tuple[float, float]
    ) -> None:
        if table.dim() != 3 or table.shape[0] != 2 or table.shape[1] < 2 or table.shape[2] < 2:
            raise ConfigError(
                f"lookup table must have shape (2, n_m >= 2, n_L >= 2), got {tuple(table.shape)}"
            )
        _check_range("m_range", m_range)
        _check_range("L_range", L_range)
        self.table = table.to(torch.float32).contiguous()
        self.m_range = (float(m_range[0]), float(m_range[1]))
        self.L_range = (float(L_range[0]), float(L_range[1]))
        # Python floats, so the hot path needs no device tensors beyond the table itself.
        n_m, n_L = self.shape
        self._m_scale = (n_m - 1) / (self.m_range[1] - self.m_range[0])
        self._L_scale = (n_L - 1) / (self.L_range[1] - self.L_range[0])
        self.check_finite = True

    @property
    def shape(self) -> tuple[int, int]:
        """(n_m, n_L)."""
        return int(self.table.shape[1]), int(self.table.shape[2])

    @property
    def device(self) -> torch.device:
        """Device of the table."""
        return self.table.device

    def grid(self) -> tuple[Tensor, Tensor]:
        """The node coordinates (m nodes, L nodes) as float64 CPU tensors."""
        n_m, n_L = self.shape
        return (
            torch.linspace(*self.m_range, n_m, dtype=torch.float64),
            torch.linspace(*self.L_range, n_L, dtype=torch.float64),
        )

    @classmethod
    @torch.no_grad()
    def from_classifier(
        cls,
        psi: PsiFunction,
        m_range: tuple[float, float],
        L_range: tuple[float, float],
        size: tuple[int, int] = (256, 256),
    ) -> PsiLookupTable:
        """Tabulate ``psi(phi, m, L)`` (e.g. a :class:`~surrogate.gp.PsiClassifier`) on a grid.

        The table lives on ``psi.device`` when it has one, else on the CPU.
        """
        n_m, n_L = (int(s) for s in size)
        if n_m < 2 or n_L < 2:
            raise ConfigError(f"lookup size must be at least (2, 2), got {tuple(size)}")
        _check_range("m_range", m_range)
        _check_range("L_range", L_range)
        device = getattr(psi, "device", torch.device("cpu"))
        m_nodes = torch.linspace(float(m_range[0]), float(m_range[1]), n_m, dtype=torch.float64)
        L_nodes = torch.linspace(float(L_range[0]), float(L_range[1]), n_L, dtype=torch.float64)
        mm, ll = torch.meshgrid(m_nodes, L_nodes, indexing="ij")
        mm, ll = mm.reshape(-1).to(device), ll.reshape(-1).to(device)
        layers = []
        for phi in (0, 1):
            phis = torch.full_like(mm, phi, dtype=torch.long)
            layers.append(psi(phis, mm, ll).to(device, torch.float32).reshape(n_m, n_L))
        return cls(torch.stack(layers), m_range, L_range)

    def to(self, device: torch.device | str) -> PsiLookupTable:
        """Move the table to ``device`` in place; return self."""
        self.table = self.table.to(device)
        return self

    def __call__(self, phi: Tensor, m: Tensor, L: Tensor) -> Tensor:
        """Interpolated p(RUN next), float32, on the input's device (like the classifier).

        Inputs outside the box are clamped to its edge. ``phi`` must be 0/1 (or bool) and is not
        checked. NaN/inf in m or L raise :class:`NumericalError` while ``check_finite`` is true (a
        host sync per call; the simulation loop turns it off and checks its state at record
        times instead); unchecked, NaN gives NaN out, never a bad index.
        """
        if self.check_finite and not bool(torch.isfinite(m).all() & torch.isfinite(L).all()):
            raise NumericalError("PsiLookupTable got NaN or infinite inputs (m or L)")
        n_m, n_L = self.shape
        dev = self.table.device
        out_device = m.device
        m = m.to(dev, torch.float32).reshape(-1)
        L = L.to(dev, torch.float32).reshape(-1)
        u = ((m - self.m_range[0]) * self._m_scale).clamp_(0.0, n_m - 1)
        v = ((L - self.L_range[0]) * self._L_scale).clamp_(0.0, n_L - 1)
        # Lower node index, kept <= n - 2 so the upper neighbour exists (u = n - 1 gets frac 1).
        # NaN -> 0 only for the index (u == u is False for NaN; cheaper than nan_to_num inside a
        # compiled step): NaN still flows into the fractions and out.
        i = torch.where(u == u, u, 0.0).floor_().clamp_(max=n_m - 2)
        j = torch.where(v == v, v, 0.0).floor_().clamp_(max=n_L - 2)
        fu = u - i
        fv = v - j
        base = phi.to(dev).reshape(-1).long() * (n_m * n_L) + i.long() * n_L + j.long()
        flat = self.table.view(-1)
        v00 = flat[base]
        v01 = flat[base + 1]
        v10 = flat[base + n_L]
        v11 = flat[base + (n_L + 1)]
        out = torch.lerp(torch.lerp(v00, v01, fv), torch.lerp(v10, v11, fv), fu)
        return out.to(out_device)  # no-op in the usual case of inputs on the table's device

    @torch.no_grad()
    def max_deviation(self, psi: PsiFunction, n_check: int | None = None, seed: int = 0) -> float:
        """Max |table - psi| over cell centres (midway between nodes in both m and L).

        Cell centres are where bilinear interpolation error peaks for smooth surfaces. All
        2 * (n_m - 1) * (n_L - 1) centres are checked when ``n_check`` is None, else a random
        subset of ``n_check`` of them (fixed by ``seed``).
        """
        n_m, n_L = self.shape
        m_nodes, L_nodes = self.grid()
        m_mid = 0.5 * (m_nodes[:-1] + m_nodes[1:])
        L_mid = 0.5 * (L_nodes[:-1] + L_nodes[1:])
        n_cells = 2 * (n_m - 1) * (n_L - 1)
        if n_check is None or n_check >= n_cells:
            flat = torch.arange(n_cells)
        else:
            if n_check < 1:
                raise ConfigError(f"n_check must be >= 1, got {n_check}")
            gen = torch.Generator().manual_seed(seed)
            flat = torch.randperm(n_cells, generator=gen)[:n_check]
        phi = flat // ((n_m - 1) * (n_L - 1))
        rest = flat % ((n_m - 1) * (n_L - 1))
        m = m_mid[rest // (n_L - 1)]
        L = L_mid[rest % (n_L - 1)]
        device = getattr(psi, "device", self.device)
        exact = psi(phi.to(device), m.to(device), L.to(device)).to("cpu", torch.float64)
        approx = self(phi, m, L).to("cpu", torch.float64)  # CPU inputs: CPU output
        return float((approx - exact).abs().max())

    def to_state(self) -> dict[str, Any]:
        """Tensors and plain values only (``torch.load(weights_only=True)``-safe)."""
        return {
            "format": STATE_FORMAT,
            "table": self.table.detach().cpu().clone(),
            "m_range": list(self.m_range),
            "L_range": list(self.L_range),
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
        return cls(state["table"].to(device), tuple(state["m_range"]), tuple(state["L_range"]))


def _check_range(name: str, r: tuple[float, float]) -> None:
    lo, hi = (float(v) for v in r)
    if not lo < hi:
        raise ConfigError(f"lookup {name} must satisfy lo < hi, got {tuple(r)}")


__all__ = ["PsiFunction", "PsiLookupTable"]
