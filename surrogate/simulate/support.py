"""Where an abstraction runs outside the inputs it was trained on.

A learned psi is only known where its training transitions lie; its lookup table clamps its
inputs at the grid's edges, so a cell whose inputs leave the trained range is simulated with the
edge's value, silently. :class:`SupportMonitor` counts, for every run with a learned decision
layer, the cell-steps whose abstraction inputs (the decision's features of the body's inputs)
fall outside the range its training data covered (:class:`TrainedRange`: each input's min and
max over the training rows, ``PsiClassifier.domain``), per input and side, with the range the
run saw. It samples the population once per :meth:`SupportMonitor.observe` call (the drivers call
it every record interval or chunk of steps), on the device, with no host sync until
:meth:`SupportMonitor.report`; the share is the fraction of the sampled cell-steps, an unbiased
estimate of the share of all cell-steps.

Example:
    >>> import torch
    >>> support = TrainedRange(("dG",), (-1.0,), (1.0,))
    >>> monitor = SupportMonitor([(slice(0, 4), None, support)])
    >>> monitor.observe(torch.tensor([[-2.0], [0.0], [0.5], [3.0]]))
    >>> monitor.report()[0]["share_outside"]
    0.5
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor

log = logging.getLogger(__name__)

#: the default share of cell-steps outside the trained range above which a run warns
OUTSIDE_WARNING = 0.01


@dataclass(frozen=True)
class TrainedRange:
    """The range each abstraction input covered in the training data.

    Attributes:
        names: the ``d`` inputs (the decision layer's features, in column order).
        lo: each input's smallest training value.
        hi: each input's largest training value.
    """

    names: tuple[str, ...]
    lo: tuple[float, ...]
    hi: tuple[float, ...]

    @classmethod
    def from_domain(
        cls, domain: Mapping[str, Sequence[float]], names: Sequence[str]
    ) -> TrainedRange:
        """From a fit's ``domain`` (``{name: (min, max)}``) over the inputs ``names``."""
        missing = [n for n in names if n not in domain]
        if missing:
            raise KeyError(f"the fit's domain has no range for {missing}")
        return cls(tuple(names), tuple(float(domain[n][0]) for n in names),
                   tuple(float(domain[n][1]) for n in names))  # fmt: skip


def trained_range_of(decision: object) -> TrainedRange | None:
    """The trained range a stage attached to a learned decision layer (None: not learned)."""
    value = getattr(decision, "trained_range", None)
    return value if isinstance(value, TrainedRange) else None


class SupportMonitor:
    """Counts of sampled cell-steps outside each block's trained range (see the module doc).

    Args:
        blocks: per run, ``(cells, featurize, trained range)``: its slice of the population,
            its decision layer's ``featurize`` (``x (n x d_x) -> z (n x d)``; None: identity)
            and the range its ``z`` was trained on.
    """

    def __init__(
        self,
        blocks: Sequence[tuple[slice, Callable[[Tensor], Tensor] | None, TrainedRange]],
    ) -> None:
        self.blocks = list(blocks)
        self._counts: list[dict[str, Tensor]] | None = None

    def observe(self, x: Tensor) -> None:
        """Count the cells of every block whose features of ``x`` (``n x d_x``, the body's
        inputs of the last step) lie outside the block's trained range."""
        if self._counts is None:
            self._counts = [self._zeros(r, x.device) for _, _, r in self.blocks]
        for (cells, featurize, trained), acc in zip(self.blocks, self._counts, strict=True):
            xb = x[cells]
            if xb.shape[0] == 0:
                continue
            z = (xb if featurize is None else featurize(xb)).to(torch.float64)
            lo = torch.tensor(trained.lo, dtype=torch.float64, device=z.device)
            hi = torch.tensor(trained.hi, dtype=torch.float64, device=z.device)
            below, above = z < lo, z > hi
            acc["below"] += below.sum(0)
            acc["above"] += above.sum(0)
            acc["outside"] += (below | above).any(1).sum()
            acc["rows"] += z.shape[0]
            acc["min"] = torch.minimum(acc["min"], z.min(0).values)
            acc["max"] = torch.maximum(acc["max"], z.max(0).values)

    @staticmethod
    def _zeros(trained: TrainedRange, device: torch.device) -> dict[str, Tensor]:
        d = len(trained.names)
        return {
            "below": torch.zeros(d, dtype=torch.int64, device=device),
            "above": torch.zeros(d, dtype=torch.int64, device=device),
            "outside": torch.zeros((), dtype=torch.int64, device=device),
            "rows": torch.zeros((), dtype=torch.int64, device=device),
            "min": torch.full((d,), math.inf, dtype=torch.float64, device=device),
            "max": torch.full((d,), -math.inf, dtype=torch.float64, device=device),
        }

    def report(self) -> list[dict[str, Any] | None]:
        """Per block: ``sampled_cell_steps``, ``share_outside`` (any input outside) and per
        input ``share_below``, ``share_above``, ``seen`` ``[min, max]`` and ``trained``
        ``[lo, hi]``; None for a block never observed."""
        if self._counts is None:
            return [None] * len(self.blocks)
        out: list[dict[str, Any] | None] = []
        for (_, _, trained), acc in zip(self.blocks, self._counts, strict=True):
            rows = int(acc["rows"])
            if rows == 0:
                out.append(None)
                continue
            below, above = acc["below"].tolist(), acc["above"].tolist()
            lo, hi = acc["min"].tolist(), acc["max"].tolist()
            out.append({
                "sampled_cell_steps": rows,
                "share_outside": int(acc["outside"]) / rows,
                "inputs": {
                    name: {"share_below": below[i] / rows, "share_above": above[i] / rows,
                           "seen": [lo[i], hi[i]], "trained": [trained.lo[i], trained.hi[i]]}
                    for i, name in enumerate(trained.names)
                },
            })  # fmt: skip
        return out


def merge_reports(reports: Sequence[Mapping[str, Any] | None]) -> dict[str, Any] | None:
    """One report for runs of the same abstraction (e.g. a run's shards): shares weighted by
    each run's sampled cell-steps, the ranges seen joined. None where no run was observed."""
    seen = [r for r in reports if r is not None]
    if not seen:
        return None
    rows = [int(r["sampled_cell_steps"]) for r in seen]
    total = sum(rows)

    def share(*path: str) -> float:  # the reports' r[path[0]][path[1]]... weighted by rows
        out = 0.0
        for n, r in zip(rows, seen, strict=True):
            value: Any = r
            for key in path:
                value = value[key]
            out += n * float(value)
        return out / total

    inputs = {}
    for name, first in seen[0]["inputs"].items():
        mine = [r["inputs"][name] for r in seen]
        inputs[name] = {
            "share_below": share("inputs", name, "share_below"),
            "share_above": share("inputs", name, "share_above"),
            "seen": [min(m["seen"][0] for m in mine), max(m["seen"][1] for m in mine)],
            "trained": list(first["trained"]),
        }
    return {"sampled_cell_steps": total,
            "share_outside": share("share_outside"), "inputs": inputs}  # fmt: skip


def describe_outside(report: Mapping[str, Any]) -> str:
    """One line: the share outside and, per input that left its range, the range seen against
    the range trained."""
    parts = []
    for name, r in report["inputs"].items():
        if r["share_below"] or r["share_above"]:
            parts.append(f"{name} seen [{r['seen'][0]:.4g}, {r['seen'][1]:.4g}] vs trained "
                         f"[{r['trained'][0]:.4g}, {r['trained'][1]:.4g}] ({100 * r['share_below']:.2g} % "
                         f"below, {100 * r['share_above']:.2g} % above)")  # fmt: skip
    return (f"{100 * report['share_outside']:.3g} % of {report['sampled_cell_steps']} sampled "
            f"cell-steps outside the trained range" + (": " + "; ".join(parts) if parts else ""))  # fmt: skip


def warn_outside(report: Mapping[str, Any] | None, threshold: float, what: str) -> bool:
    """Log ONE warning when more than ``threshold`` of the sampled cell-steps of ``what`` had an
    input outside the trained range; return whether it warned."""
    if report is None or not report["share_outside"] > threshold:
        return False
    log.warning("%s: the abstraction ran outside its training data in %s. The lookup clamps "
                "there, so those steps use the psi at the range's edge, not a learned value: "
                "collect transitions where these cells go (e.g. collect in this field, or a "
                "wider collection), or check this run against the full model.", what,
                describe_outside(report))  # fmt: skip
    return True


__all__ = [
    "OUTSIDE_WARNING",
    "SupportMonitor",
    "TrainedRange",
    "describe_outside",
    "trained_range_of",
    "warn_outside",
]
