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

Inside the range, training rows may still be few: a learned psi there is the GP's guess between
distant rows (an input range the training field crossed quickly, say). So a fit also stores
:class:`TrainingHistogram`: its rows per state over equal-width bins of the trained range (the
joint histogram for one or two inputs, each input's own for more). A bin is *sparse* for a
state that has fewer rows there than :func:`min_rows_of` asks (by default enough rows for 25
expected switches at that state's switching share, a relative standard error of 20 % on a rate
estimated from that bin alone), and the monitor also counts the sampled cell-steps inside the
range whose inputs fall in a bin sparse for their own state phi, the psi that decides their
next step (``share_sparse``: a running cell where tumbles were never trained is not), and where
the most visited sparse region lies (``sparse_where``). A fit made before the histogram was
stored is checked by range only.

A K-lumps chain (:class:`~surrogate.simulate.classes.ClassDecision`) decides a cell's next
step by its own class's law, learned from that class's rows; its fit also stores the rows per
class (:attr:`TrainedRange.class_histogram`), and each cell is checked against its own class's
rows (the layer's classes, :func:`classes_of`): a class rare in training inside a bin its lump
fills is sparse, and the report names the class (``sparse_class``, each region's ``class``).
A K-lumps fit made before that was stored is checked per state.

Example:
    >>> import torch
    >>> support = TrainedRange(("dG",), (-1.0,), (1.0,))
    >>> monitor = SupportMonitor([(slice(0, 4), None, support)])
    >>> monitor.observe(torch.tensor([[-2.0], [0.0], [0.5], [3.0]]))
    >>> monitor.report()[0]["share_outside"]
    0.5
"""

from __future__ import annotations

import itertools
import json
import logging
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from torch import Tensor

log = logging.getLogger(__name__)

#: the default share of cell-steps outside the trained range (or in a sparsely trained bin)
#: above which a run warns
OUTSIDE_WARNING = 0.01

#: equal-width bins per input of a fit's :class:`TrainingHistogram`: one input (64), two
#: inputs (16 x 16, the joint), more (64 each, alone). At 10^5 rows per state that is ~1,560
#: rows per state and bin on average for one input, ~390 for two, against a default minimum
#: of 475 at a switching share of 0.05: with two inputs much of a range may read as sparse
#: (a rate from one bin's rows alone is that uncertain; the GP's smoothing across bins,
#: which this check does not credit, does better).
HISTOGRAM_BINS = {1: 64, 2: 16}
MARGINAL_BINS = 64

#: expected switches a bin's rows of a state must hold (by default) to count as trained: a
#: Bernoulli rate p estimated from n rows has relative standard error sqrt((1 - p) / (n p)),
#: <= 1 / sqrt(25) = 20 % at n >= 25 (1 - p) / p
MIN_SWITCHES = 25

#: the rows a bin needs of a state that never (or always) switched in training, where the
#: rule above has no rate to go by
MIN_ROWS_NO_RATE = 100


def bin_edges(lo: float, hi: float, bins: int, device: torch.device | str = "cpu") -> Tensor:
    """The ``bins + 1`` equal-width edges of ``[lo, hi]`` (float64), for reports."""
    steps = torch.arange(bins + 1, dtype=torch.float64, device=device)
    edges = lo + (hi - lo) * (steps / bins)
    edges[-1] = hi
    return edges


def bin_of(z: Tensor, lo: float, hi: float, bins: int) -> Tensor:
    """Each value's bin among ``bins`` equal-width bins of ``[lo, hi]``: ``floor((z - lo)
    bins / (hi - lo))`` (float64, correctly rounded alike on every device; the training rows
    and the monitor both bin by it), the last bin closed; values below ``lo`` (or NaN) give 0
    and above ``hi`` the last bin (the range check tells them apart). Arithmetic rather than
    ``bucketize``: 7x cheaper on a CPU at 10^6 cells."""
    scale = bins / (hi - lo) if hi > lo else 0.0
    pos = torch.nan_to_num((z.to(torch.float64) - lo) * scale, nan=0.0)
    return pos.floor_().clamp_(0, bins - 1).to(torch.int64)


@dataclass(frozen=True)
class TrainingHistogram:
    """A fit's training rows per state over equal-width bins of each input's trained range.

    Attributes:
        names: the inputs (in the fit's column order; a switch clock excluded).
        lo: each input's smallest training value (the range's, :class:`TrainedRange`).
        hi: each input's largest training value.
        bins: bins per input.
        joint: True: one histogram over all inputs (row-major flat index over ``bins``);
            False: each input's own, concatenated.
        counts: per state phi = 0, 1 (or per class, see ``classes``): the rows per bin
            (flat, as ``joint`` says).
        switching: per state: the share of its rows whose phi changed (the rate the default
            minimum of rows is derived from); per class: the share of its rows whose class
            changed (see :meth:`of_rows`).
        classes: the K-lumps classes the counts are per, in the chain's order (empty: per
            state phi = 0, 1).
    """

    names: tuple[str, ...]
    lo: tuple[float, ...]
    hi: tuple[float, ...]
    bins: tuple[int, ...]
    joint: bool
    counts: tuple[tuple[int, ...], ...]
    switching: tuple[float, ...]
    classes: tuple[str, ...] = ()

    @classmethod
    def of_rows(
        cls,
        values: Any,
        phi: Any,
        switched: Any,
        names: Sequence[str],
        classes: Sequence[str] | None = None,
        windows: Any = None,
    ) -> TrainingHistogram:
        """The histogram of training rows ``values`` (``n x d``, columns ``names``), their
        states ``phi`` (0/1) and whether each switched; with ``windows`` (``n``, a collection
        that keeps every switch), each row counted as the windows it stands for, in the counts
        and the switching shares alike (their product: the switches the fit read).

        With ``classes`` (a K-lumps fit's class names), ``phi`` is each row's class at the
        window's start (an index into ``classes``, collect's ``phi_class``) and ``switched``
        whether its class changed over the window (``phi_class_next`` differs): the counts
        and switching shares are per class. The rows a class needs in a bin
        (:meth:`min_rows`) then follow :func:`min_rows_of` at the class's share of rows that
        *leave it*: the chain's decision for a cell is its class's whole one-window law
        ``P(class' | class, z)``, learned from the rows of that class, and the events that
        law is learned from are its moves out of the class (any destination, a change of
        lump or not). So the rule asks, as the per-state one does of phi's switches, for
        25 expected moves per bin (a leaving rate within 20 %), and it is the per-state
        rule itself for a chain whose classes are phi's two lumps. Rarer destinations
        among those moves are not credited separately: their share of a bin is the GP's
        smoothing across bins, which this check does not claim to measure either."""
        z = torch.tensor(np.asarray(values, dtype=np.float64)).reshape(-1, len(names))
        state = torch.tensor(np.asarray(phi, dtype=np.int64)).reshape(-1)
        moved = torch.tensor(np.asarray(switched, dtype=bool)).reshape(-1)
        w = (torch.ones(moved.shape[0], dtype=torch.float64) if windows is None
             else torch.tensor(np.asarray(windows, dtype=np.float64)).reshape(-1))  # fmt: skip
        d = len(names)
        joint = d <= 2
        bins = (HISTOGRAM_BINS[d],) * d if joint else (MARGINAL_BINS,) * d
        lo = z.min(0).values.tolist() if z.shape[0] else [0.0] * d
        hi = z.max(0).values.tolist() if z.shape[0] else [0.0] * d
        hist = cls(tuple(names), tuple(lo), tuple(hi), bins, joint, ((),), ())
        flat = hist.flat_bins(z)
        size = hist.n_bins
        counts, switching = [], []
        for s in range(len(classes) if classes is not None else 2):
            mine = state == s
            # joint: one flat bin a row; else d, one in each input's own histogram
            mine_flat = flat[mine]
            per_bin = w[mine] if joint else w[mine].unsqueeze(1).expand_as(mine_flat)
            c = torch.bincount(mine_flat.reshape(-1), weights=per_bin.reshape(-1), minlength=size)
            counts.append(tuple(round(v) for v in c.tolist()))
            n = float(w[mine].sum())
            switching.append(float(w[mine & moved].sum()) / n if n else 0.0)
        return cls(tuple(names), tuple(lo), tuple(hi), bins, joint, tuple(counts),
                   tuple(switching), tuple(classes or ()))  # fmt: skip

    @property
    def n_bins(self) -> int:
        """The flat length of one state's counts."""
        return math.prod(self.bins) if self.joint else sum(self.bins)

    def edges(self, device: torch.device | str = "cpu") -> list[Tensor]:
        """Each input's bin edges."""
        return [bin_edges(lo, hi, b, device)
                for lo, hi, b in zip(self.lo, self.hi, self.bins, strict=True)]  # fmt: skip

    def flat_bins(self, z: Tensor) -> Tensor:
        """Each row's flat bin: ``n`` (joint) or ``n x d`` (each input's, offset into the
        concatenation); ``z`` float64 ``n x d``."""
        idx = [bin_of(z[:, i], lo, hi, b)
               for i, (lo, hi, b) in enumerate(zip(self.lo, self.hi, self.bins, strict=True))]  # fmt: skip
        if self.joint:
            flat = idx[0]
            for i, b in zip(idx[1:], self.bins[1:], strict=True):
                flat = flat * b + i
            return flat
        offsets = [0, *itertools.accumulate(self.bins)][:-1]
        return torch.stack([i + o for i, o in zip(idx, offsets, strict=True)], 1)

    @property
    def groups(self) -> tuple[str, ...]:
        """What the counts are per: the class names, else the states ``0``, ``1``."""
        return self.classes or ("0", "1")

    def min_rows(self, min_rows: int | None = None) -> tuple[int, ...]:
        """Per state (or class), the rows a bin needs (:func:`min_rows_of`)."""
        return tuple(min_rows_of(p, min_rows) for p in self.switching)

    def sparse_by_state(self, min_rows: int | None = None) -> tuple[tuple[bool, ...], ...]:
        """Per state (or class), per flat bin: whether it has fewer rows there than it needs
        (:meth:`min_rows`)."""
        need = self.min_rows(min_rows)
        return tuple(tuple(v < n for v in c) for c, n in zip(self.counts, need, strict=True))

    def sparse(self, min_rows: int | None = None) -> tuple[bool, ...]:
        """Per flat bin: whether any state has fewer rows there than :meth:`min_rows`."""
        return tuple(any(col) for col in zip(*self.sparse_by_state(min_rows), strict=True))

    def as_dict(self) -> dict[str, Any]:
        """A plain dict for a manifest (:meth:`from_dict` reads it back); ``classes`` only
        where the counts are per class."""
        out = {"inputs": list(self.names), "lo": list(self.lo), "hi": list(self.hi),
               "bins": list(self.bins), "joint": self.joint,
               "counts": [list(c) for c in self.counts],
               "switching": list(self.switching)}  # fmt: skip
        if self.classes:
            out["classes"] = list(self.classes)
        return out

    @classmethod
    def from_dict(cls, obj: Mapping[str, Any]) -> TrainingHistogram:
        """The histogram :meth:`as_dict` wrote; ArtefactError-free: a KeyError/ValueError for
        anything else (the caller falls back to the range)."""
        hist = cls(tuple(str(n) for n in obj["inputs"]), tuple(float(v) for v in obj["lo"]),
                   tuple(float(v) for v in obj["hi"]), tuple(int(b) for b in obj["bins"]),
                   bool(obj["joint"]), tuple(tuple(int(v) for v in c) for c in obj["counts"]),
                   tuple(float(p) for p in obj["switching"]),
                   tuple(str(c) for c in obj.get("classes", ())))  # fmt: skip
        groups = len(hist.groups)
        if len(hist.counts) != groups or any(len(c) != hist.n_bins for c in hist.counts):
            raise ValueError("the histogram's counts do not match its bins")
        if len(hist.switching) != groups:
            raise ValueError("the histogram's switching shares do not match its counts")
        return hist


def min_rows_of(switching: float, min_rows: int | None = None) -> int:
    """The rows a bin needs of a state whose training rows switched at share ``switching``:
    ``min_rows`` where given, else ``ceil(MIN_SWITCHES (1 - p) / p)`` (a rate near p from
    that many rows has a relative standard error <= 20 %), ``MIN_ROWS_NO_RATE`` where p is 0
    or 1."""
    if min_rows is not None:
        return int(min_rows)
    if not 0.0 < switching < 1.0:
        return MIN_ROWS_NO_RATE
    return math.ceil(round(MIN_SWITCHES * (1.0 - switching) / switching, 6))  # 475.0000001: 475


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
    #: the training rows' histogram over the same inputs (None: a fit made before it was
    #: stored, checked by range only)
    histogram: TrainingHistogram | None = None
    #: the rows a bin needs per state (None: :func:`min_rows_of`'s default)
    min_rows: int | None = None
    #: a K-lumps fit's training rows per class over the same inputs (None: checked per state;
    #: a two-state fit, or one made before it was stored): each cell is checked against its
    #: own class's rows
    class_histogram: TrainingHistogram | None = None

    @classmethod
    def from_domain(
        cls,
        domain: Mapping[str, Sequence[float]],
        names: Sequence[str],
        histogram: Mapping[str, Any] | None = None,
        min_rows: int | None = None,
        class_histogram: Mapping[str, Any] | None = None,
        classes: Sequence[str] | None = None,
    ) -> TrainedRange:
        """From a fit's ``domain`` (``{name: (min, max)}``) over the inputs ``names`` and its
        ``support_histogram`` (:meth:`TrainingHistogram.as_dict`; ignored where absent, not
        readable or over other inputs: the range alone is checked then) and, for a K-lumps
        fit, its ``support_class_histogram`` (per class; ignored likewise, or where its classes
        are not ``classes``, the chain's: the per-state check then)."""
        missing = [n for n in names if n not in domain]
        if missing:
            raise KeyError(f"the fit's domain has no range for {missing}")
        hist = _histogram_of(histogram, names, "support histogram", "the trained range only")
        per_class = _histogram_of(class_histogram, names, "per-class support histogram",
                                  "per state instead")  # fmt: skip
        if per_class is not None and (
            not per_class.classes or (classes is not None and per_class.classes != tuple(classes))
        ):
            per_class = None  # not the chain's classes: per state
        return cls(tuple(names), tuple(float(domain[n][0]) for n in names),
                   tuple(float(domain[n][1]) for n in names), hist, min_rows,
                   per_class)  # fmt: skip


def _histogram_of(
    obj: Mapping[str, Any] | None, names: Sequence[str], what: str, instead: str
) -> TrainingHistogram | None:
    """The histogram a manifest stored (None: absent, unreadable, warned, or over other inputs
    than ``names``)."""
    if obj is None:
        return None
    try:
        hist = TrainingHistogram.from_dict(obj)
    except (KeyError, TypeError, ValueError) as exc:
        log.warning("the fit's %s is unreadable (%s): checking %s", what, exc, instead)
        return None
    return hist if hist.names == tuple(names) else None  # over other inputs than the decision's


def trained_range_of(decision: object) -> TrainedRange | None:
    """The trained range a stage attached to a learned decision layer (None: not learned)."""
    value = getattr(decision, "trained_range", None)
    return value if isinstance(value, TrainedRange) else None


def classes_of(decision: object) -> Tensor | None:
    """Each cell's K-lumps class now (``(n,)`` int64) for the decision layer of a whole
    population: a K-lumps chain's ``cls`` (:class:`~surrogate.simulate.classes.ClassDecision`),
    a batch's members' side by side (0 in a member without classes, which no per-class block
    reads); None where no layer has classes. A view of the layer's own tensor where there is
    one layer: no copy."""
    members = getattr(decision, "members", None)
    if members is not None:  # a DecisionBatch: block i of sizes[i] cells is members[i]'s
        parts = [classes_of(m) for m in members]
        if all(p is None for p in parts):
            return None
        like = next(p for p in parts if p is not None)
        return torch.cat([p if p is not None else like.new_zeros(n)
                          for p, n in zip(parts, decision.sizes, strict=True)])  # type: ignore[attr-defined]  # fmt: skip
    value = getattr(decision, "cls", None)
    return value if isinstance(value, Tensor) else None


class SupportMonitor:
    """Counts of sampled cell-steps outside each block's trained range, and inside it in a
    sparsely trained bin where the fit stored its histogram (see the module doc).

    Args:
        blocks: per run, ``(cells, featurize, trained range)``: its slice of the population,
            its decision layer's ``featurize`` (``x (n x d_x) -> z (n x d)``; None: identity)
            and the range its ``z`` was trained on (with its histogram, where stored; with
            its per-class histogram, a K-lumps fit's, each cell is checked against its class's
            rows).
    """

    def __init__(
        self,
        blocks: Sequence[tuple[slice, Callable[[Tensor], Tensor] | None, TrainedRange]],
    ) -> None:
        self.blocks = list(blocks)
        self._counts: list[dict[str, Tensor]] | None = None
        #: per block: its histogram's sparse bins on the device, per state or class (None:
        #: range only)
        self._density: list[Tensor | None] = []

    @property
    def needs_classes(self) -> bool:
        """Whether a block checks its cells per class (:meth:`observe` wants ``classes``)."""
        return any(density_of(r)[1] for _, _, r in self.blocks)

    def observe(self, x: Tensor, phi: Tensor | None = None, classes: Tensor | None = None) -> None:
        """Count the cells of every block whose features of ``x`` (``n x d_x``, the body's
        inputs of the last step) lie outside the block's trained range, or inside it in a bin
        sparse for their state ``phi`` (``(n,)``, 0/1: the psi that decides their next step;
        None: sparse for either state) or, in a block with a per-class histogram, for their
        class ``classes`` (``(n,)`` int64, the K-lumps chain's classes: the law that decides
        their next step; None: sparse for any class); batched tensor ops on ``x``'s device, no
        host sync."""
        if self._counts is None:
            self._counts = [self._zeros(r, x.device) for _, _, r in self.blocks]
            self._density = [self._sparse_bins(r, x.device) for _, _, r in self.blocks]
        blocks = zip(self.blocks, self._counts, self._density, strict=True)
        for (cells, featurize, trained), acc, density in blocks:
            xb = x[cells]
            if xb.shape[0] == 0:
                continue
            z = (xb if featurize is None else featurize(xb)).to(torch.float64)
            lo = torch.tensor(trained.lo, dtype=torch.float64, device=z.device)
            hi = torch.tensor(trained.hi, dtype=torch.float64, device=z.device)
            below, above = z < lo, z > hi
            out = (below | above).any(1)
            acc["below"] += below.sum(0)
            acc["above"] += above.sum(0)
            acc["outside"] += out.sum()
            acc["rows"] += z.shape[0]
            acc["min"] = torch.minimum(acc["min"], z.min(0).values)
            acc["max"] = torch.maximum(acc["max"], z.max(0).values)
            if density is None:
                continue
            hist, by_class = density_of(trained)
            assert hist is not None  # a density is made from it
            flat = hist.flat_bins(z)  # n (joint) or n x d (each alone)
            inside = ~out
            label = classes if by_class else phi
            if label is None:
                group = None
                bad = density.any(0)[flat]
            else:  # each cell against its own state's (or class's) rows
                group = label[cells].to(torch.int64)
                group = group if flat.dim() == 1 else group[:, None]
                bad = density[group, flat]
            bad = bad & (inside if flat.dim() == 1 else inside[:, None])
            acc["sparse"] += (bad if bad.dim() == 1 else bad.any(1)).sum()
            # the sparse cell-steps per bin (each input's own where not joint): the regions';
            # per class and bin with classes (a cell of unknown class: its bin's any sparse one)
            if by_class:
                if group is None:  # a cell of unknown class: the first class sparse there
                    group = density.to(torch.int64).argmax(0)[flat]
                flat = group * hist.n_bins + flat
            acc["visits"].index_add_(0, flat.reshape(-1), bad.reshape(-1).to(torch.int64))

    @staticmethod
    def _sparse_bins(trained: TrainedRange, device: torch.device) -> Tensor | None:
        hist, _ = density_of(trained)
        if hist is None:
            return None
        return torch.tensor(hist.sparse_by_state(trained.min_rows), dtype=torch.bool,
                            device=device)  # fmt: skip

    @staticmethod
    def _zeros(trained: TrainedRange, device: torch.device) -> dict[str, Tensor]:
        d = len(trained.names)
        acc = {
            "below": torch.zeros(d, dtype=torch.int64, device=device),
            "above": torch.zeros(d, dtype=torch.int64, device=device),
            "outside": torch.zeros((), dtype=torch.int64, device=device),
            "rows": torch.zeros((), dtype=torch.int64, device=device),
            "min": torch.full((d,), math.inf, dtype=torch.float64, device=device),
            "max": torch.full((d,), -math.inf, dtype=torch.float64, device=device),
        }
        hist, by_class = density_of(trained)
        if hist is not None:
            size = hist.n_bins * (len(hist.classes) if by_class else 1)
            acc["sparse"] = torch.zeros((), dtype=torch.int64, device=device)
            acc["visits"] = torch.zeros(size, dtype=torch.int64, device=device)
        return acc

    def report(self) -> list[dict[str, Any] | None]:
        """Per block: ``sampled_cell_steps``, ``share_outside`` (any input outside) and per
        input ``share_below``, ``share_above``, ``seen`` ``[min, max]`` and ``trained``
        ``[lo, hi]``; where the fit stored its histogram also ``share_sparse`` (inside the
        range, in a sparse bin), ``sparse_regions`` (every visited connected region of sparse
        bins, ``{"where": {input: [lo, hi]}, "share": cell-steps there}``, most visited
        first), ``sparse_where`` and ``sparse_where_share`` (the first's; None and 0 where
        none was visited) and ``min_rows`` (per state, the rows a bin needed). Checked per
        class (a K-lumps fit's per-class histogram), each region names its ``class`` too,
        ``sparse_class`` is the first's, ``min_rows`` is per class and ``classes`` names them.
        None for a block never observed."""
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
            report: dict[str, Any] = {
                "sampled_cell_steps": rows,
                "share_outside": int(acc["outside"]) / rows,
                "inputs": {
                    name: {"share_below": below[i] / rows, "share_above": above[i] / rows,
                           "seen": [lo[i], hi[i]], "trained": [trained.lo[i], trained.hi[i]]}
                    for i, name in enumerate(trained.names)
                },
            }  # fmt: skip
            hist, by_class = density_of(trained)
            if hist is not None and by_class:
                regions = class_regions(hist, hist.sparse_by_state(trained.min_rows),
                                        acc["visits"].tolist(), rows)  # fmt: skip
                report.update(sparse_keys(int(acc["sparse"]) / rows, regions,
                                          list(hist.min_rows(trained.min_rows)),
                                          hist.classes))  # fmt: skip
            elif hist is not None:
                regions = [{"where": w, "share": n / rows} for w, n in sparse_regions(
                    hist, hist.sparse(trained.min_rows), acc["visits"].tolist())]  # fmt: skip
                report.update(sparse_keys(int(acc["sparse"]) / rows, regions,
                                          list(hist.min_rows(trained.min_rows))))  # fmt: skip
            out.append(report)
        return out


def density_of(trained: TrainedRange) -> tuple[TrainingHistogram | None, bool]:
    """The histogram a block's cells are checked against and whether it is per class: a
    K-lumps fit's per-class one where stored, else the per-state one (None: range only)."""
    if trained.class_histogram is not None:
        return trained.class_histogram, True
    return trained.histogram, False


def class_regions(
    hist: TrainingHistogram, sparse: Sequence[Sequence[bool]], visits: Sequence[int], rows: int
) -> list[dict[str, Any]]:
    """Per class, its visited connected regions of bins sparse for it (:func:`sparse_regions`
    over its row of ``sparse`` and its ``hist.n_bins`` of ``visits``), as report entries
    ``{"where": .., "class": name, "share": visits / rows}``, most visited first."""
    size, found = hist.n_bins, []
    for c, name in enumerate(hist.classes):
        mine = visits[c * size : (c + 1) * size]
        for where, n in sparse_regions(hist, sparse[c], mine):
            found.append(({"where": where, "class": name, "share": n / rows}, n))
    return [r for r, _ in sorted(found, key=lambda r: -r[1])]


def sparse_regions(
    hist: TrainingHistogram, sparse: Sequence[bool], visits: Sequence[int]
) -> list[tuple[dict[str, list[float]], int]]:
    """The visited connected regions of sparse bins (sides touching; each input alone where the
    histogram is not joint), most visited first: ``({input: [lo, hi]}, visits)``, the span of
    all the region's bins (the same for every run of the fit, so runs' regions add up)."""
    from scipy import ndimage

    mask, seen = np.asarray(sparse, dtype=bool), np.asarray(visits, dtype=np.int64)
    edges = [e.tolist() for e in hist.edges()]
    if hist.joint:
        parts = [(tuple(range(len(hist.names))), mask.reshape(hist.bins),
                  seen.reshape(hist.bins))]  # fmt: skip
    else:
        stops = list(itertools.accumulate(hist.bins))
        parts = [((i,), mask[stop - b:stop], seen[stop - b:stop])
                 for i, (b, stop) in enumerate(zip(hist.bins, stops, strict=True))]  # fmt: skip
    regions = []
    for axes, m, v in parts:
        labels, n = ndimage.label(m)
        for k in range(1, n + 1):
            region = labels == k
            total = int(v[region].sum())
            if total > 0:
                span = np.nonzero(region)
                regions.append(({hist.names[a]: [edges[a][int(w.min())], edges[a][int(w.max()) + 1]]
                                 for a, w in zip(axes, span, strict=True)}, total))  # fmt: skip
    return sorted(regions, key=lambda r: -r[1])


def merge_reports(reports: Sequence[Mapping[str, Any] | None]) -> dict[str, Any] | None:
    """One report for runs of the same abstraction (e.g. a run's shards): shares weighted by
    each run's sampled cell-steps, the ranges seen joined. Where every run counted sparse bins
    too, ``share_sparse`` and each sparse region's share are weighted the same way (a region
    spans all its bins, the same in every run of one fit). None where no run was observed."""
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
    merged: dict[str, Any] = {"sampled_cell_steps": total,
                              "share_outside": share("share_outside"), "inputs": inputs}  # fmt: skip
    if all("sparse_regions" in r for r in seen):
        # the same region of every run, by its span (and its class, checked per class)
        regions: dict[str, list[Any]] = {}
        for n, r in zip(rows, seen, strict=True):
            for region in r["sparse_regions"]:
                ident = {k: v for k, v in region.items() if k != "share"}
                key = json.dumps(ident, sort_keys=True)
                regions.setdefault(key, [ident, 0.0])[1] += n * float(region["share"])
        joined = sorted(({**ident, "share": c / total} for ident, c in regions.values()),
                        key=lambda g: -g["share"])  # fmt: skip
        merged.update(sparse_keys(share("share_sparse"), joined, list(seen[0]["min_rows"]),
                                  seen[0].get("classes")))  # fmt: skip
    return merged


def sparse_keys(
    share: float,
    regions: Sequence[Mapping[str, Any]],
    min_rows: Sequence[int],
    classes: Sequence[str] | None = None,
) -> dict[str, Any]:
    """A report's density keys: the share in sparse bins, the regions (most visited first),
    the first's ``sparse_where`` and ``sparse_where_share``, and the rows a bin needed; checked
    per class (``classes``), also the first's ``sparse_class`` and the ``classes``
    ``min_rows`` is per."""
    first = regions[0] if regions else {"where": None, "share": 0.0}
    keys = {"share_sparse": share, "sparse_where": first["where"],
            "sparse_where_share": first["share"], "sparse_regions": list(regions),
            "min_rows": list(min_rows)}  # fmt: skip
    if classes:
        keys["sparse_class"] = first.get("class")
        keys["classes"] = list(classes)
    return keys


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


def describe_where(where: Mapping[str, Sequence[float]] | None) -> str:
    """``dG in [4, 7]`` (and ``, x in [..]``) for a ``sparse_where``; ``nowhere`` for None."""
    if not where:
        return "nowhere"
    return ", ".join(f"{n} in [{v[0]:.4g}, {v[1]:.4g}]" for n, v in where.items())


def describe_sparse_where(report: Mapping[str, Any]) -> str:
    """The most visited sparse region of a report: :func:`describe_where` of its
    ``sparse_where``, after its class where checked per class (``class on|P2<12 at dG in
    [4, 7]``)."""
    where = describe_where(report.get("sparse_where"))
    cls = report.get("sparse_class")
    return f"class {cls} at {where}" if cls is not None else where


def describe_sparse(report: Mapping[str, Any]) -> str:
    """One line: the share inside the range in sparse bins, the most visited sparse region (and
    its class, checked per class) and its share, and the rows a bin needed."""
    need = "/".join(str(n) for n in report.get("min_rows", []))
    per = (f"rows of the cell's own class ({', '.join(report['classes'])})"
           if report.get("classes") else "rows per state phi = 0/1")  # fmt: skip
    return (f"{100 * report['share_sparse']:.3g} % of {report['sampled_cell_steps']} sampled "
            f"cell-steps inside the trained range where its training rows are sparse (fewer than "
            f"{need} {per} in the input's bin), most at {describe_sparse_where(report)} "
            f"({100 * report.get('sparse_where_share', 0.0):.3g} %)")  # fmt: skip


def sparse_share(report: Mapping[str, Any] | None) -> float | None:
    """A report's ``share_sparse`` (None: a run of a fit without its histogram, or none)."""
    if report is None or report.get("share_sparse") is None:
        return None
    return float(report["share_sparse"])


def warn_outside(report: Mapping[str, Any] | None, threshold: float, what: str) -> bool:
    """Log ONE warning when more than ``threshold`` of the sampled cell-steps of ``what`` had an
    input outside the trained range, or inside it in a sparsely trained bin; return whether it
    warned."""
    if report is None:
        return False
    outside = report["share_outside"] > threshold
    sparse = (sparse_share(report) or 0.0) > threshold
    if not (outside or sparse):
        return False
    parts = []
    if outside:
        parts.append(
            f"the abstraction ran outside its training data in {describe_outside(report)}. The "
            f"lookup clamps there, so those steps use the psi at the range's edge, not a learned "
            f"value: collect transitions where these cells go (e.g. collect in this field, or a "
            f"wider collection), or check this run against the full model."
        )
    if sparse and report.get("sparse_class") is not None:
        parts.append(
            f"the abstraction ran where its training rows of a class are sparse in "
            f"{describe_sparse(report)}. The chain's law from that class there is the fit's "
            f"guess between few of its rows: collect more rows (`collect.n_per_state`; a rare "
            f"class's rows grow in proportion) or use coarser classes (`model.classes`: fewer, "
            f"wider bins, each with more rows), or train with rows there (a training field or "
            f"`model.body.perturbation` that reaches "
            f"{describe_where(report.get('sparse_where'))}), or check this run against the "
            f"full model."
        )
    elif sparse:
        parts.append(
            f"the abstraction ran where its training rows are sparse in "
            f"{describe_sparse(report)}. Its psi there is the fit's guess between few rows: "
            f"train with rows there (a training field, or a perturbation design, "
            f"`model.body.perturbation`, that reaches "
            f"{describe_where(report.get('sparse_where'))}; more rows, `collect.n_per_state`, "
            f"fill it only in proportion), or check this run against the full model."
        )
    log.warning("%s: %s", what, " Also, ".join(parts))
    return True


__all__ = [
    "OUTSIDE_WARNING",
    "SupportMonitor",
    "TrainedRange",
    "TrainingHistogram",
    "class_regions",
    "classes_of",
    "density_of",
    "describe_outside",
    "describe_sparse",
    "describe_sparse_where",
    "describe_where",
    "merge_reports",
    "min_rows_of",
    "sparse_keys",
    "sparse_regions",
    "sparse_share",
    "trained_range_of",
    "warn_outside",
]
