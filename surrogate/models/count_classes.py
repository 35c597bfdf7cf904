"""Classes finer than phi for any reaction network: bins of a count (K lumps for networks).

The two-state chain over phi forgets everything but phi; a network whose switching depends on a
slowly changing hidden count (a protein reservoir that drains for minutes) cannot be held by it.
:class:`CountClasses` splits each lump into bins of one count (a species, or a formula over the
species such as ``"P + 2 * P2"``), so the K-lumps chain (``gp=classes``) carries where in that
count a cell is. A model declares them (yaml ``classes: {species: P2, edges: [...]}``, edges
shared by both lumps or per lump name), or lets :func:`choose_count_classes` choose them:

* **How**: the network alone is simulated at fixed inputs from its initial state for its
  burn-in, then ``windows`` windows of ``dt`` for ``cells`` cells (seeded). The inputs are the
  SBML file's parameter values, or (``classes: {auto: {over: {<input>: [lo, hi]}}}``, what the
  inspector recommends from the inputs the fields give) spread evenly over those ranges, one
  value per cell, so the bins cover the counts the population will carry rather than those at
  one input: with bins chosen at one input, cells at the range's ends all sit in an open-ended
  bin whose mix the training data does not share (measured in docs/fidelity.md). Every species
  with more than one value is a candidate count, and so is every combination of species that
  the network's *fast* reactions leave unchanged (:func:`slow_combinations`: reactions firing
  at least once per window on average in the sample jitter their species within a window; the
  integer basis of their stoichiometry's null space, e.g. the auto-regulatory network's total
  protein, which dimerisation conserves while P2 alone jitters across its bins). Its bins (``bins``) are placed where the chance
  of leaving each lump varies least (``placement: homogeneous``, the default) and are **shared
  by both lumps**, so a flip of phi keeps the count's bin (where no two bins would hold both
  lumps, because the count decides phi, as a threshold on it does, each lump gets its own bins
  the same way: a flip then moves the count's bin anyway); with each lump's own edges
  (``placement: quantiles`` keeps them), a cell whose phi flickers every few windows (the auto-regulatory
  network's P crossing its threshold) is reclassified by the other lump's bins at every flip,
  and the chain's hidden count diffuses far faster than the slow count it stands for
  (measured: the top P2 class held 1 % of the full model's cells throughout and 4 % of the
  chain's 2.5 s after the start, 6-7 % from 5 s on; docs/fidelity.md). Each
  candidate is scored by how much better its classes predict the next phi than phi alone: the
  held-out log-likelihood gain per window of P(phi' | class) over P(phi' | phi), both estimated
  on every other cell and scored on the rest, with a standard error from the per-cell means.
  The candidate with the largest gain is chosen; ``report["significant"]`` says whether its gain
  exceeds two standard errors (if not, the two-state chain holds about as much).
* The choice is deterministic (seeded) and cached on disk by everything it depends on, so every
  stage of a pipeline sees the same classes; its digest is part of the model's identity.
"""

from __future__ import annotations

import hashlib
import itertools
import json
import logging
import math
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from surrogate.ctmc.kinetics import Expr, species_ref, torch_function
from surrogate.errors import ConfigError
from surrogate.io import write_text
from surrogate.sbml.formula import parse_formula
from surrogate.validation import known_keys

log = logging.getLogger(__name__)

#: the chooser's version: part of its cache key and of the model's identity (4: slow
#: combinations of species among the candidates; 5: each lump its own bins where no shared
#: bins hold both lumps)
CHOOSER_VERSION = 5
#: a reaction firing at least this many times per window on average (in the chooser's sample)
#: is fast: combinations of species its firings leave unchanged are candidate counts
FAST_FIRINGS_PER_WINDOW = 1.0
#: the default bins per lump of ``classes: auto``
AUTO_BINS = 8
#: how ``classes: auto`` places its bin edges (see :func:`choose_count_classes`)
PLACEMENTS = ("quantiles", "homogeneous")
AUTO_PLACEMENT = "homogeneous"
#: the fine quantile bins :func:`_homogeneous_edges` merges
FINE_BINS = 64
#: the fewest sampled windows of each lump a shared bin of :func:`_homogeneous_edges` holds
MIN_BIN_WINDOWS = 100


@dataclass(frozen=True, eq=False)
class CountClasses:
    """Each lump split into bins of one count: class = (phi, bin of the count in that lump).

    Args:
        variable: the count's formula over the species (a species id or e.g. ``"P + 2 * P2"``).
        edges: per lump (phi = 0, 1), the increasing bin edges: bin ``j`` holds values in
            ``[edges[j - 1], edges[j])`` (the first bin everything below ``edges[0]``, the last
            everything from ``edges[-1]`` on), so ``len(edges) + 1`` bins per lump.
        lump_names: the names of phi = 0 and 1 (for the class names).
    """

    variable: str
    edges: tuple[tuple[float, ...], tuple[float, ...]]
    lump_names: tuple[str, str] = ("off", "on")

    @property
    def names(self) -> tuple[str, ...]:
        """``C`` names, e.g. ``on|P2<12``, ``on|12<=P2<30``, ``on|P2>=30``."""
        out = []
        for phi in (0, 1):
            e = self.edges[phi]
            bounds = [-math.inf, *e, math.inf]
            for lo, hi in itertools.pairwise(bounds):
                if lo == -math.inf and hi == math.inf:
                    what = "all"
                elif lo == -math.inf:
                    what = f"{self.variable}<{hi:g}"
                elif hi == math.inf:
                    what = f"{self.variable}>={lo:g}"
                else:
                    what = f"{lo:g}<={self.variable}<{hi:g}"
                out.append(f"{self.lump_names[phi]}|{what}")
        return tuple(out)

    @property
    def lumps(self) -> tuple[int, ...]:
        """The phi (0/1) of each class."""
        return tuple(phi for phi in (0, 1) for _ in range(len(self.edges[phi]) + 1))

    @property
    def bins(self) -> tuple[int, ...] | None:
        """Each class's bin where both lumps share the edges (a flip keeps the bin), else
        None."""
        if self.edges[0] != self.edges[1]:
            return None
        return tuple(b for phi in (0, 1) for b in range(len(self.edges[phi]) + 1))

    def to_config(self) -> dict[str, Any]:
        """The yaml form: ``{expression: ..., edges: {<lump>: [...], ...}}``."""
        return {"expression": self.variable,
                "edges": {self.lump_names[p]: list(self.edges[p]) for p in (0, 1)}}  # fmt: skip

    def digest(self) -> str:
        """A short digest of the classes (part of the model's identity)."""
        blob = json.dumps(self.to_config(), sort_keys=True)
        return hashlib.sha256(blob.encode()).hexdigest()[:16]


class CountClassifier:
    """``classify(counts (n x S), phi (n,)) -> (n,)`` int64 class indices of
    :class:`CountClasses` over a network's species; picklable (compiled on first use)."""

    def __init__(self, classes: CountClasses, species: Sequence[str], where: str) -> None:
        symbols = {name: species_ref(s, name) for s, name in enumerate(species)}
        self.expr: Expr = parse_formula(classes.variable, symbols, where, "real", what="species")
        self.classes = classes
        self._function: Any = None

    def values(self, counts: Tensor) -> Tensor:
        """The count's value per cell, float64 ``(n,)``."""
        if self._function is None:
            self._function = torch_function([self.expr])
        return self._function(counts, counts.new_zeros((counts.shape[0], 0)))[:, 0].double()

    def __call__(self, counts: Tensor, phi: Tensor) -> Tensor:
        return self.bin(self.values(counts), phi)

    def bin(self, value: Tensor, phi: Tensor) -> Tensor:
        """The class ``(n,)`` int64 of each count ``value`` ``(n,)`` in its lump ``phi``
        ``(n,)``: the bins of the count applied apart from computing it."""
        value = value.double()
        out = torch.empty(value.shape[0], dtype=torch.int64, device=value.device)
        offset = 0
        for p in (0, 1):
            edges = torch.tensor(self.classes.edges[p], dtype=torch.float64, device=value.device)
            bins = torch.bucketize(value, edges, right=True)  # edges[j-1] <= v < edges[j] -> j
            out = torch.where(phi == p, offset + bins, out)
            offset += len(self.classes.edges[p]) + 1
        return out

    def __getstate__(self) -> dict:
        return {**self.__dict__, "_function": None}


def parse_classes(
    value: Any, species: Sequence[str], lump_names: tuple[str, str], where: str = "model.classes"
) -> CountClasses:
    """A declared ``classes`` mapping (``species`` or ``expression``, and ``edges``: one list
    for both lumps or ``{<lump name>: [...]}``), validated; ``auto`` is resolved elsewhere."""
    value = known_keys(value, ("species", "expression", "edges"), where, required=("edges",),
                       shape="auto or a mapping {species: <id>, edges: [...]} (or expression: "
                       "<formula over species>)")  # fmt: skip
    if ("species" in value) == ("expression" in value):
        raise ConfigError(f"{where} needs exactly one of species (a species id) or expression "
                          f"(a formula over the species), got {sorted(value)}")  # fmt: skip
    variable = value.get("species", value.get("expression"))
    if not isinstance(variable, str) or not variable.strip():
        raise ConfigError(f"{where}: the count must be a species id or formula, got {variable!r}")
    if "species" in value and variable not in species:
        raise ConfigError(f"{where}.species={variable!r} is not a species of the network "
                          f"{list(species)}")  # fmt: skip
    edges = value.get("edges")
    if isinstance(edges, Mapping):
        missing = [n for n in lump_names if n not in edges]
        extra = sorted(set(edges) - set(lump_names))
        if missing or extra:
            raise ConfigError(f"{where}.edges by lump needs exactly the lumps {list(lump_names)}, "
                              f"got {sorted(edges)}")  # fmt: skip
        per_lump = [edges[n] for n in lump_names]
    else:
        per_lump = [edges, edges]
    checked = []
    for name, e in zip(lump_names, per_lump, strict=True):
        if not isinstance(e, Sequence) or isinstance(e, str | bytes):
            raise ConfigError(f"{where}.edges ({name}) must be a list of numbers, got {e!r}")
        nums = []
        for v in e:
            if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
                raise ConfigError(f"{where}.edges ({name}) must be finite numbers, got {v!r}")
            nums.append(float(v))
        if any(b <= a for a, b in itertools.pairwise(nums)):
            raise ConfigError(f"{where}.edges ({name}) must increase strictly, got {nums}")
        checked.append(tuple(nums))
    if not checked[0] and not checked[1]:
        raise ConfigError(f"{where}.edges is empty: the classes would be the lumps themselves "
                          "(the two-state chain, gp=svgp)")  # fmt: skip
    classes = CountClasses(variable.strip(), (checked[0], checked[1]), lump_names)
    CountClassifier(classes, species, where)  # the formula parses over the species
    return classes


def threshold_of(expr: Expr | None) -> tuple[str, int, bool] | None:
    """``(species, edge, upper)`` where a lump expression is a threshold on one species count:
    phi = 1 iff ``count >= edge`` (``upper``) or ``count < edge``; None for any other lump."""
    if expr is None or expr.op not in ("geq", "gt", "leq", "lt"):
        return None
    a, b = expr.args
    op = expr.op
    if a.op == "species" and b.is_const:
        species, c = a, float(b.value)
    elif b.op == "species" and a.is_const:
        species, c = b, float(a.value)
        op = {"geq": "leq", "gt": "lt", "leq": "geq", "lt": "gt"}[op]
    else:
        return None
    edge = {"geq": math.ceil(c), "gt": math.floor(c) + 1, "leq": math.floor(c) + 1,
            "lt": math.ceil(c)}[op]  # fmt: skip
    return str(species.name), int(edge), op in ("geq", "gt")


def impossible_classes(classes: CountClasses, threshold: tuple[str, int, bool] | None) -> list[str]:
    """The classes no cell can be in: where the lump is a threshold on the classes' own count
    (``threshold``, :func:`threshold_of`), a bin of one lump that holds no count (a
    non-negative integer) on that lump's side of the threshold, e.g. ``low|21<=P<22`` where
    ``low`` is ``P < 21``. No collection can give such a class rows, so its fit fails after
    the whole collection; refused before it instead."""
    if threshold is None or classes.variable != threshold[0]:
        return []
    _, edge, upper = threshold
    out = []
    names = iter(classes.names)
    for phi in (0, 1):
        # the lump's counts: [edge, inf) for phi = 1 of an upper threshold, else [0, edge)
        lo_lump, hi_lump = (edge, math.inf) if (phi == 1) == upper else (0, edge)
        for lo, hi in itertools.pairwise([-math.inf, *classes.edges[phi], math.inf]):
            name = next(names)
            if math.ceil(max(lo, lo_lump, 0)) >= min(hi, hi_lump):
                out.append(name)
    return out


def is_auto(value: Any) -> bool:
    """Whether a ``classes`` setting asks for a chosen set (``auto`` or ``{auto: ...}``)."""
    return value == "auto" or (isinstance(value, Mapping) and "auto" in value)


def parse_auto_classes(
    value: Any, input_names: Sequence[str]
) -> tuple[dict[int, tuple[float, float]], int, str, bool]:
    """``classes: auto`` or ``{auto: {over: {<input>: [lo, hi]}, bins: K, shared: true}}``
    (``auto: {}`` or ``auto: true`` as plain auto) -> (ranges by input index, bins per lump,
    placement, whether the bins must be shared by both lumps), validated. ``shared: true`` is
    what ``gp.class_moves=relaxation`` needs: only counts whose bins hold both lumps are
    candidates (never a threshold lump's own count, whose bins hold one lump each)."""
    where = "model.classes"
    if value == "auto":
        return {}, AUTO_BINS, AUTO_PLACEMENT, False
    if set(value) != {"auto"}:
        raise ConfigError(f"{where}: auto takes its options inside it, "
                          f"{{auto: {{over: {{<input>: [lo, hi]}}, bins: K}}}}; got the "
                          f"extra key(s) {sorted(set(value) - {'auto'})}")  # fmt: skip
    options = value["auto"]
    if options is True or options is None:
        options = {}
    options = known_keys(options, ("over", "bins", "placement", "shared"), f"{where}.auto",
                         shape="a mapping {over: {<input>: [lo, hi]}, bins: K}")  # fmt: skip
    shared = options.get("shared", False)
    if not isinstance(shared, bool):
        raise ConfigError(f"{where}.auto.shared must be true or false, got {shared!r}")
    if shared and options.get("placement", AUTO_PLACEMENT) != "homogeneous":
        raise ConfigError(f"{where}.auto.shared needs placement: homogeneous (quantile bins "
                          f"are each lump's own)")  # fmt: skip
    placement = options.get("placement", AUTO_PLACEMENT)
    if placement not in PLACEMENTS:
        raise ConfigError(f"{where}.auto.placement must be one of {list(PLACEMENTS)}, got "
                          f"{placement!r}")  # fmt: skip
    bins = options.get("bins", AUTO_BINS)
    if isinstance(bins, bool) or not isinstance(bins, int) or not 2 <= bins <= 20:
        raise ConfigError(f"{where}.auto.bins must be an integer from 2 to 20 (bins per lump), "
                          f"got {bins!r}")  # fmt: skip
    over = options.get("over", {})
    if not isinstance(over, Mapping):
        raise ConfigError(f"{where}.auto.over must map input parameters to [lo, hi], got "
                          f"{over!r}")  # fmt: skip
    ranges: dict[int, tuple[float, float]] = {}
    for name, span in over.items():
        if name not in input_names:
            raise ConfigError(f"{where}.auto.over.{name}: not an input parameter of the network "
                              f"{list(input_names)}")  # fmt: skip
        ok = (isinstance(span, Sequence) and not isinstance(span, str) and len(span) == 2
              and all(isinstance(v, int | float) and not isinstance(v, bool)
                      and math.isfinite(v) for v in span))  # fmt: skip
        if not ok or not 0 <= span[0] < span[1]:
            raise ConfigError(f"{where}.auto.over.{name} must be [lo, hi] with 0 <= lo < hi "
                              f"(the kinetic input's range the fields give), got "
                              f"{span!r}")  # fmt: skip
        ranges[list(input_names).index(name)] = (float(span[0]), float(span[1]))
    return ranges, bins, placement, shared


def shared_auto(value: Any) -> Any:
    """A ``classes: auto`` setting (:func:`is_auto`) asking for bins both lumps share
    (``{auto: {..., shared: true}}``, its other options kept): what ``gp.class_moves=relaxation``
    needs, for the chooser would otherwise give a threshold lump's own count bins that hold one
    lump each. Refused where the setting says otherwise (``shared: false``, or
    ``placement: quantiles``, each lump's own bins); a malformed one is returned as it is, for
    :func:`parse_auto_classes` to refuse by name."""
    options = {} if value == "auto" else value.get("auto")
    if options is True or options is None:
        options = {}
    if not isinstance(options, Mapping):
        return value
    needs = "gp.class_moves=relaxation needs bins of one count that both lumps share"
    if options.get("shared", True) is False:
        raise ConfigError(f"model.classes.auto.shared is false, but {needs}: set shared: true "
                          f"(or use gp.class_moves=learned)")  # fmt: skip
    if options.get("placement", AUTO_PLACEMENT) == "quantiles":
        raise ConfigError(f"model.classes.auto.placement is quantiles (each lump's own bins), "
                          f"but {needs}: use placement: homogeneous with shared: true (or "
                          f"gp.class_moves=learned)")  # fmt: skip
    return {"auto": {**options, "shared": True}}


# ----------------------------------------------------------------------------------------------
# choosing them


@dataclass(frozen=True)
class CountBinning:
    """How :func:`choose_count_classes` bins each candidate count.

    Attributes:
        bins: bins per lump.
        placement: ``quantiles`` (each lump's own bins, equal windows per bin) or
            ``homogeneous`` (bins shared by both lumps over which the chance of leaving each
            lump varies least, :func:`_homogeneous_edges`).
        shared: only counts whose bins are shared by both lumps (``gp.class_moves=relaxation``
            needs them); a ConfigError where none has such bins.
    """

    bins: int = AUTO_BINS
    placement: str = AUTO_PLACEMENT
    shared: bool = False


def choose_count_classes(
    internal: Any,
    kinetic_inputs: Tensor,
    dt: float,
    *,
    cells: int = 200,
    windows: int = 1000,
    binning: CountBinning = CountBinning(),
    seed: int = 0,
    cache_dir: Path | None = None,
) -> tuple[CountClasses, dict[str, Any]]:
    """Choose the count and its bins that best carry the memory phi alone forgets (see the
    module docstring); cached on disk.

    Args:
        internal: a :class:`~surrogate.models.network.NetworkInternalModel`.
        kinetic_inputs: ``(P,)`` the network's input parameters, held fixed, or ``cells x P``:
            each cell's own (e.g. :func:`spread_inputs`).
        dt: the window (s).
        cells, windows: the simulated sample: ``cells`` cells, ``windows`` windows each.
        binning: the bins per lump, their placement, whether both lumps must share them
            (:class:`CountBinning`).
        seed: the simulation's seed.
        cache_dir: where the choice is cached (default ``$SURROGATE_CACHE_DIR`` or
            ``~/.cache/surrogate``, under ``classes/``).

    Returns:
        ``(classes, report)``: the report has every candidate's gain (nats per window) and
        standard error, the chosen one, whether its gain is significant, and the sample.
    """
    bins, placement, shared = binning.bins, binning.placement, binning.shared
    kinetic_inputs = kinetic_inputs.to(torch.float64)
    if kinetic_inputs.dim() == 2 and kinetic_inputs.shape[0] != cells:
        raise ValueError(f"kinetic_inputs: {kinetic_inputs.shape[0]} rows for {cells} cells")
    key = {"version": CHOOSER_VERSION, "kinetics": _kinetics_digest(internal),
           "lump": str(getattr(internal, "lump_formula", internal._lump)),
           "initial": internal.initial_counts.tolist(), "burn_in": internal.burn_in,
           "inputs": kinetic_inputs.tolist(), "dt": float(dt),
           "cells": cells, "windows": windows, "bins": bins, "seed": seed}  # fmt: skip
    key["placement"] = placement
    if shared:  # absent otherwise: earlier choices keep their cache key
        key["shared"] = True
    digest = hashlib.sha256(json.dumps(key, sort_keys=True).encode()).hexdigest()[:20]
    root = cache_dir or _cache_dir()
    path = root / f"{digest}.json"
    if path.exists():
        saved = json.loads(path.read_text())
        classes = CountClasses(saved["variable"], (tuple(saved["edges"][0]),
                                                   tuple(saved["edges"][1])),
                               internal.lump_names)  # fmt: skip
        return classes, saved["report"]
    counts, phi = _sample(internal, kinetic_inputs, dt, cells, windows, seed)
    combinations, fast = slow_combinations(internal, counts, kinetic_inputs, dt)
    stoich = internal.reactions.stoichiometry.numpy()
    names = list(internal.reactions.reaction_names)
    rows = [names.index(n) for n in fast]
    jittery = {sp for j, sp in enumerate(internal.species) if (stoich[rows, j] != 0).any()}
    classes, report = _choose(counts, phi, internal.species, internal.lump_names, binning,
                              combinations, jittery)  # fmt: skip
    report["fast_reactions"] = fast
    spread = kinetic_inputs.reshape(-1, kinetic_inputs.shape[-1])
    report["sample"] = {"cells": cells, "windows": windows, "dt": dt, "seed": seed,
                        "inputs_min": spread.min(0).values.tolist(),
                        "inputs_max": spread.max(0).values.tolist()}  # fmt: skip
    root.mkdir(parents=True, exist_ok=True)
    write_text(path, json.dumps({"variable": classes.variable,
                                 "edges": [list(e) for e in classes.edges],
                                 "report": report}, indent=1))  # fmt: skip
    return classes, report


def spread_inputs(
    defaults: Sequence[float], ranges: Mapping[int, tuple[float, float]], cells: int
) -> Tensor:
    """``cells x P`` kinetic inputs: each input at its default, those in ``ranges`` (by index)
    spread evenly over ``[lo, hi]`` (cell ``i`` at ``lo + (i + 1/2) (hi - lo) / cells``; with
    several ranged inputs each is spread independently, in a seeded shuffled order, so their
    pairs cover the box rather than its diagonal)."""
    out = torch.tensor(list(defaults), dtype=torch.float64).reshape(1, -1).repeat(cells, 1)
    gen = torch.Generator().manual_seed(0)
    for k, (j, (lo, hi)) in enumerate(sorted(ranges.items())):
        grid = lo + (torch.arange(cells, dtype=torch.float64) + 0.5) * (hi - lo) / cells
        out[:, j] = grid if k == 0 else grid[torch.randperm(cells, generator=gen)]
    return out


def _cache_dir() -> Path:
    root = os.environ.get("SURROGATE_CACHE_DIR")
    return (Path(root) if root else Path.home() / ".cache" / "surrogate") / "classes"


def _kinetics_digest(internal: Any) -> str:
    kin = internal.kinetics
    blob = json.dumps({"species": list(internal.species), "source": kin.numba_source},
                      sort_keys=True)  # fmt: skip
    return hashlib.sha256(blob.encode()).hexdigest()[:20]


def slow_combinations(
    internal: Any, counts: np.ndarray, kinetic_inputs: Tensor, dt: float, samples: int = 20
) -> tuple[list[tuple[str, np.ndarray]], list[str]]:
    """Combinations of species that the network's fast reactions leave unchanged.

    A reaction is fast where its mean propensity over the sample (``samples`` evenly spaced
    windows of every cell) times ``dt`` is at least :data:`FAST_FIRINGS_PER_WINDOW`; the
    combinations are the integer basis of the null space of the fast reactions' net
    stoichiometry (exact, by sympy's rational row reduction), each scaled to coprime integers
    with its first coefficient positive. A combination of one species (already a candidate) is
    left out.

    Args:
        internal: a :class:`~surrogate.models.network.NetworkInternalModel`.
        counts: ``(W + 1) x n x S`` sampled counts.
        kinetic_inputs: ``(P,)`` or ``n x P`` the inputs they were sampled at.
        dt: the window (s).

    Returns:
        ``[(formula, coefficients (S,))]`` and the fast reactions' names.
    """
    import sympy

    species = list(internal.species)
    n_cells = counts.shape[1]
    rows = np.linspace(0, counts.shape[0] - 1, min(samples, counts.shape[0])).round().astype(int)
    state = torch.from_numpy(counts[rows].reshape(-1, counts.shape[2]))
    inputs = kinetic_inputs.to(torch.float64)
    inputs = inputs.reshape(1, -1).expand(n_cells, -1) if inputs.dim() == 1 else inputs
    inputs = inputs.repeat(len(rows), 1)
    mean = internal.kinetics.propensities(state, inputs).mean(0)
    fast = (mean * dt >= FAST_FIRINGS_PER_WINDOW).numpy()
    names = [n for n, f in zip(internal.reactions.reaction_names, fast, strict=True) if f]
    if not fast.any():
        return [], names
    stoich = internal.reactions.stoichiometry.numpy()
    conserved = [c for c in map(_integers, sympy.Matrix(stoich.tolist()).nullspace())
                 if min(c) >= 0]  # fmt: skip
    out = []
    for vector in sympy.Matrix(stoich[fast].tolist()).nullspace():
        ints = _readable(_integers(vector), conserved)
        if sum(v != 0 for v in ints) < 2:
            continue
        out.append((_formula(ints, species), np.asarray(ints, dtype=np.int64)))
    return out, names


def _integers(vector: Any) -> list[int]:
    """A rational sympy vector scaled to coprime integers."""
    import sympy

    scale = sympy.ilcm(*[sympy.fraction(sympy.nsimplify(v))[1] for v in vector])
    ints = [int(v * scale) for v in vector]
    g = math.gcd(*ints) or 1
    return [v // g for v in ints]


def _readable(ints: list[int], conserved: Sequence[list[int]]) -> list[int]:
    """The same count up to sign and a constant: more positive than negative coefficients, and
    a negative one cancelled by adding a non-negative conserved combination of the whole
    network where that leaves none negative (``2 Gene - P`` with ``Gene + P2Gene`` conserved
    reads ``P + 2 P2Gene``, less a constant)."""
    if sum(v > 0 for v in ints) < sum(v < 0 for v in ints):
        ints = [-v for v in ints]
    for c in conserved:
        need = [math.ceil(-v / w) for v, w in zip(ints, c, strict=True) if v < 0 and w > 0]
        if need:
            shifted = [v + max(need) * w for v, w in zip(ints, c, strict=True)]
            if min(shifted) >= 0:
                ints = shifted
    if ints and next(v for v in ints if v != 0) < 0:
        ints = [-v for v in ints]
    return ints


def _formula(coefficients: Sequence[int], species: Sequence[str]) -> str:
    """``[1, 2, 0]`` over ``[P, P2, R]`` -> ``"P + 2 * P2"``."""
    terms: list[str] = []
    for c, name in zip(coefficients, species, strict=True):
        if c == 0:
            continue
        mag = f"{abs(c)} * {name}" if abs(c) != 1 else name
        terms.append((("- " if c < 0 else "+ ") if terms else ("-" if c < 0 else "")) + mag)
    return " ".join(terms)


def _sample(
    internal: Any, kinetic_inputs: Tensor, dt: float, cells: int, windows: int, seed: int
) -> tuple[np.ndarray, np.ndarray]:
    """``windows + 1`` states of ``cells`` cells at fixed inputs after the burn-in: counts
    ``(W + 1) x n x S`` and phi ``(W + 1) x n``."""
    gen_state = torch.random.get_rng_state()
    try:
        torch.manual_seed(seed)
        inputs = kinetic_inputs.to(torch.float64)
        inputs = inputs if inputs.dim() == 2 else inputs.reshape(1, -1)
        inputs = inputs.expand(cells, -1).contiguous()
        state = internal.burn_in_at(inputs)
        counts = [state[0].clone()]
        for _ in range(windows):
            state = internal.advance_at(state, inputs, dt)
            counts.append(state[0].clone())
    finally:
        torch.random.set_rng_state(gen_state)
    stacked = torch.stack(counts)
    phi = torch.stack([internal._lump(c) for c in counts]).to(torch.int8)
    return stacked.numpy(), phi.numpy()


def _choose(
    counts: np.ndarray,
    phi: np.ndarray,
    species: Sequence[str],
    lump_names: tuple[str, str],
    binning: CountBinning,
    combinations: Sequence[tuple[str, np.ndarray]] = (),
    jittery: frozenset[str] | set[str] = frozenset(),
) -> tuple[CountClasses, dict[str, Any]]:
    bins, placement, shared = binning.bins, binning.placement, binning.shared
    n_cells = counts.shape[1]
    # every other cell: with inputs spread over a range (cell i at the i-th value) both halves
    # span it
    train = np.arange(n_cells) % 2 == 0
    before, after = phi[:-1], phi[1:]
    occupancy = float(phi.mean())
    if min(occupancy, 1 - occupancy) * phi.size < 10 * bins:
        raise ConfigError(
            f"choosing classes: phi is 1 in {100 * occupancy:.3g} % of {phi.size} sampled "
            "windows at the sampled inputs, too few of one lump to bin; declare "
            "model.classes={species: ..., edges: [...]} (scripts/inspect_model.py measures "
            "the occupancy across the inputs)"
        )
    base = _loglik(before, after, before.astype(np.int64), train)
    candidates: list[dict[str, Any]] = []
    counted = [(name, counts[:-1, :, j].astype(np.float64)) for j, name in enumerate(species)]
    counted += [(formula, (counts[:-1].astype(np.float64) @ vector.astype(np.float64)))
                for formula, vector in combinations]  # fmt: skip
    for name, values in counted:
        if values.min() == values.max():
            continue
        if placement == "quantiles":
            edges = tuple(_edges(values[:, train][before[:, train] == p], bins) for p in (0, 1))
        else:  # shared: a flip of phi keeps the count's bin (see the module docstring)
            both = _homogeneous_edges(values[:, train], before[:, train], after[:, train], bins)
            edges = (both, both)
            if not both and shared:  # per-lump bins are what the caller cannot use
                continue
            if not both:
                # no two bins hold both lumps: the count (nearly) decides phi, as a threshold
                # on it does, so a flip moves its bin anyway; each lump gets its own bins
                held, was, now = values[:, train], before[:, train], after[:, train]
                edges = tuple(
                    _homogeneous_edges(held[was == p], was[was == p], now[was == p], bins, (p,))
                    for p in (0, 1)
                )  # fmt: skip
        cls = _classify(values, before, edges)
        gain = _loglik(before, after, cls, train) - base
        mean, se = _per_cell(gain, ~train)
        candidates.append({"species": name, "edges": [list(e) for e in edges],
                           "gain_nats_per_window": mean, "se": se,
                           "fast_changed": name in jittery})  # fmt: skip
    if not candidates and shared:
        raise ConfigError(
            "choosing classes (model.classes.auto.shared, what gp.class_moves=relaxation "
            "needs): no count has bins that hold both lumps (each count decides phi, as a "
            "threshold on it does); use gp.class_moves=learned with model.classes=auto"
        )
    if not candidates:
        raise ConfigError("choosing classes: no count changes in the sampled windows")
    best = max(candidates, key=lambda c: c["gain_nats_per_window"])
    # a count the fast reactions change jitters across its bins within windows, which a chain
    # over the bins turns into a random walk: a steady count whose gain is within two standard
    # errors of the best is preferred (measured: P2's bins 8 of 24 fidelity checks, the total
    # protein's 14 of 24 with the same learned law; docs/fidelity.md)
    floor = best["gain_nats_per_window"] - 2 * best["se"]
    steady = [c for c in candidates
              if not c["fast_changed"] and c["gain_nats_per_window"] >= floor]  # fmt: skip
    if best["fast_changed"] and steady:
        best = max(steady, key=lambda c: c["gain_nats_per_window"])
    classes = CountClasses(best["species"], (tuple(best["edges"][0]), tuple(best["edges"][1])),
                           lump_names)  # fmt: skip
    report = {"chosen": best["species"], "candidates": candidates, "occupancy": occupancy,
              "significant": best["gain_nats_per_window"] > 2 * best["se"]}  # fmt: skip
    return classes, report


def _homogeneous_edges(
    values: np.ndarray,
    before: np.ndarray,
    after: np.ndarray,
    bins: int,
    lumps: Sequence[int] = (0, 1),
) -> tuple[float, ...]:
    """Interior edges of at most ``bins`` bins of the count, shared by ``lumps``, in which the
    chance of leaving each lump varies least: the count's values are first cut at
    ``FINE_BINS`` quantiles, each fine bin's log-odds of leaving each lump estimated, and the
    fine bins merged into contiguous groups minimising the windows-weighted within-group
    variance of those log-odds summed over the lumps (exact, by dynamic programming), each group
    holding at least :data:`MIN_BIN_WINDOWS` windows of every lump so every class occurs. A bin
    over which the chance of leaving is flat holds no memory a different mix of its cells could
    reveal; quantile bins put as much mass in a steep tail as in a flat middle."""
    fine = _edges(values.ravel(), FINE_BINS)
    idx = np.searchsorted(np.asarray(fine), values, side="right")
    m = len(fine) + 1
    sums = []  # per lump: prefix sums of windows, n * logit and n * logit^2 over the fine bins
    for phi in lumps:
        mask = before == phi
        left = (after[mask] != phi).astype(np.float64)
        n = np.bincount(idx[mask], minlength=m).astype(np.float64)
        k = np.bincount(idx[mask], weights=left, minlength=m)
        p = (k + 0.5) / (n + 1.0)
        logit = np.log(p) - np.log1p(-p)
        sums.append(tuple(np.concatenate([[0.0], np.cumsum(x)]) for x in (n, n * logit,
                                                                          n * logit**2)))  # fmt: skip

    def cost(i: np.ndarray, j: int) -> np.ndarray:
        total = np.zeros(i.shape)
        for c_n, c_x, c_xx in sums:
            w = c_n[j] - c_n[i]
            sx = c_x[j] - c_x[i]
            ss = (c_xx[j] - c_xx[i]) - sx**2 / np.maximum(w, 1e-300)
            total = total + np.where(w >= MIN_BIN_WINDOWS, ss, np.inf)
        return total

    best = np.full((bins + 1, m + 1), np.inf)
    arg = np.zeros((bins + 1, m + 1), dtype=np.int64)
    best[0, 0] = 0.0
    for g in range(1, bins + 1):
        for j in range(1, m + 1):
            i = np.arange(j)
            total = best[g - 1, i] + cost(i, j)
            arg[g, j] = int(np.argmin(total))
            best[g, j] = total[arg[g, j]]
    groups = int(np.argmin(best[1:, m])) + 1  # fewer bins where every bin cannot hold both lumps
    if not np.isfinite(best[groups, m]):
        return ()
    cuts, j = [], m
    for g in range(groups, 0, -1):
        j = int(arg[g, j])
        cuts.append(j)
    return tuple(fine[c - 1] for c in sorted(cuts) if c > 0)


def _edges(values: np.ndarray, bins: int) -> tuple[float, ...]:
    """Interior bin edges at the quantiles of ``values`` (integers: counts), unique."""
    if values.size == 0:
        return ()
    qs = np.quantile(values, [k / bins for k in range(1, bins)])
    edges = sorted({float(math.ceil(q)) for q in qs if values.min() < math.ceil(q) <= values.max()})
    return tuple(edges)


def _classify(
    values: np.ndarray, phi: np.ndarray, edges: tuple[tuple[float, ...], ...]
) -> np.ndarray:
    out = np.empty(values.shape, dtype=np.int64)
    offset = 0
    for p in (0, 1):
        bins = np.searchsorted(np.asarray(edges[p]), values, side="right")
        out = np.where(phi == p, offset + bins, out)
        offset += len(edges[p]) + 1
    return out


def _loglik(
    before: np.ndarray, after: np.ndarray, cls: np.ndarray, train: np.ndarray
) -> np.ndarray:
    """Per window (``W x n``): log P(phi' | class) with P estimated on the training cells
    (add-one smoothing)."""
    k = int(cls.max()) + 1
    on = np.bincount(cls[:, train].ravel(), weights=after[:, train].ravel(), minlength=k)
    total = np.bincount(cls[:, train].ravel(), minlength=k)
    p1 = (on + 1) / (total + 2)
    p = p1[cls]
    return np.where(after == 1, np.log(p), np.log1p(-p))


def _per_cell(values: np.ndarray, cells: np.ndarray) -> tuple[float, float]:
    """Mean over the held-out cells' windows, and its standard error over cells."""
    per_cell = values[:, cells].mean(0)
    return float(per_cell.mean()), float(per_cell.std(ddof=1) / math.sqrt(len(per_cell)))


__all__ = [
    "AUTO_BINS",
    "AUTO_PLACEMENT",
    "CHOOSER_VERSION",
    "PLACEMENTS",
    "CountBinning",
    "CountClasses",
    "CountClassifier",
    "choose_count_classes",
    "impossible_classes",
    "is_auto",
    "parse_auto_classes",
    "parse_classes",
    "shared_auto",
    "slow_combinations",
    "spread_inputs",
    "threshold_of",
]
