"""The remedies the verdict (:mod:`surrogate.diagnosis.advice`) prints: each a setting to change,
checked before it is printed and never advised again where a previous run applied it without a
gain; coarser classes as concrete edges; what the switch clock tries next; and, where the chain
was chosen by measurement (``gp=auto``), what widens or sharpens that choice rather than a kind
named around it (:func:`choice_remedies`)."""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from surrogate.kinds.scoring import LOG_CLOCK, candidate_cap, farthest_lump
from surrogate.models.count_classes import CountClasses


@dataclass(frozen=True)
class Remedy:
    """One next step a cause advises.

    Attributes:
        kind: what it changes, e.g. ``more_rows``, ``longer_clock`` (a remedy that did not
            help a run of the model is not advised again by kind, whatever its values).
        text: the step as printed.
        overrides: the settings it prints, as command-line overrides (checked before it is
            printed, :mod:`surrogate.stages.advice_check`); empty where it names no value.
    """

    kind: str
    text: str
    overrides: tuple[str, ...] = ()


#: checks a remedy's overrides: the refusal's message, or None (:func:`~surrogate.stages.
#: advice_check.checked` bound to the run's config)
Check = Callable[[Sequence[str], str], str | None]


class Advisor:
    """Keeps the remedies that run and were not tried without a gain; says why of the rest."""

    def __init__(self, check: Check | None, tried: Mapping[str, str] | None) -> None:
        self.check, self.tried = check, dict(tried or {})
        self.remedies: list[tuple[str, Remedy]] = []
        self.dropped: list[tuple[str, Remedy, str]] = []

    def step(self, cause: str, remedies: Sequence[Remedy], sep: str = "; or ",
             then: str = "") -> str:  # fmt: skip
        """The printed step of ``cause``: its remedies that pass, joined by ``sep``, then
        ``then``; a note names each one left out and why, and each one already advised under
        an earlier cause (printed once)."""
        kept, repeated, notes = [], [], []
        earlier = {(p.kind, p.overrides): c for c, p in self.remedies if p.overrides}
        for r in remedies:
            why = self.tried.get(r.kind)
            if why is None and r.overrides and self.check is not None:
                why = self.check(r.overrides, r.text)
            if why is None and earlier.get((r.kind, r.overrides), cause) != cause:
                repeated.append(f"also `{' '.join(r.overrides)}`, advised above under "
                                f"\"{earlier[(r.kind, r.overrides)]}\"")  # fmt: skip
            elif why is None:
                kept.append(r)
                self.remedies.append((cause, r))
            else:
                self.dropped.append((cause, r, why))
                notes.append(f"not advised: {' '.join(r.overrides) or r.kind} ({why})")
        text = sep.join(r.text for r in kept) + then if kept else \
            "the remedies advised above" if repeated else \
            "nothing this reading can advise runs or is untried"  # fmt: skip
        return text + "".join(f" [{n}]" for n in repeated + notes)


def more_rows(n_per_state: int | None, text: str = "more transitions ({more})") -> Remedy:
    """More collected rows: four times ``collect.n_per_state`` where it is known."""
    if n_per_state:
        more = f"`collect.n_per_state={4 * n_per_state}`"
        return Remedy("more_rows", text.format(more=more),
                      (f"collect.n_per_state={4 * n_per_state}",))  # fmt: skip
    return Remedy("more_rows", text.format(more="a larger `collect.n_per_state`"))


#: the mean-duration error a learned psi's bias is judged by (the fidelity check's default):
#: a reference whose error on the bias exceeds it cannot judge the bias
DURATION_TOLERANCE = 0.03

#: the margin on the diagnostic's cells a noisy reference is advised (its error falls as one
#: over the root of its cells: the advised ones bring it to the tolerance / sqrt(margin))
DIAGNOSTIC_MARGIN = 1.5


def diagnostic_cells_needed(cells: int, rel_se: float, tolerance: float) -> int:
    """The diagnostic cells that bring the relative error ``rel_se`` measured at ``cells``
    under ``tolerance``: it falls as one over the root of the cells, so ``cells`` x
    (``rel_se`` / ``tolerance``)^2 x :data:`DIAGNOSTIC_MARGIN`, rounded up to hundreds, and at
    least 100 more than ``cells``.

    Example:
        >>> diagnostic_cells_needed(1000, 0.046, 0.03)
        3600
    """
    n = int(math.ceil(cells * DIAGNOSTIC_MARGIN * (rel_se / tolerance) ** 2 / 100.0) * 100)
    return max(n, cells + 100)


def larger_diagnostic(cells: int | None, rel_se: float, tolerance: float) -> Remedy:
    """A diagnostic population large enough to judge psi's bias
    (:func:`diagnostic_cells_needed`); without ``cells``, no value.

    Example:
        >>> larger_diagnostic(1000, 0.046, 0.03).overrides
        ('gp.diagnostic.n_cells=3600',)
    """
    if not cells or not rel_se > 0 or not tolerance > 0:
        return Remedy("larger_diagnostic", "a larger diagnostic population "
                                           "(`gp.diagnostic.n_cells`, `gp.diagnostic.t_end`)")  # fmt: skip
    n = diagnostic_cells_needed(cells, rel_se, tolerance)
    return Remedy("larger_diagnostic", f"a larger diagnostic population, `gp.diagnostic.n_cells="
                  f"{n}` (now {cells}: its error falls as one over the root of its cells)",
                  (f"gp.diagnostic.n_cells={n}",))  # fmt: skip


def later_diagnostic_start(span: tuple[float, float] | None) -> Remedy:
    """The diagnostic population's record started half its run later: its first half switched
    at another rate than its second, so its cells were still drifting in that first half;
    ``gp.diagnostic.equilibration_time`` plus half of ``gp.diagnostic.t_end`` (``span``: the
    two, in s), in whole seconds, leaves that half out of the record. Without ``span``, no
    value.

    Example:
        >>> later_diagnostic_start((10.0, 100.0)).overrides
        ('gp.diagnostic.equilibration_time=60',)
    """
    if span is None or not span[1] > 0:
        return Remedy("later_diagnostic_start", "a longer `gp.diagnostic.equilibration_time`")
    equilibration, t_end = span
    start = math.ceil(equilibration + t_end / 2)
    return Remedy("later_diagnostic_start",
                  f"the diagnostic's record started later, `gp.diagnostic.equilibration_time="
                  f"{start}` (now {equilibration:g} s; its first {t_end / 2:g} s drifted from "
                  f"its last)", (f"gp.diagnostic.equilibration_time={start}",))  # fmt: skip


def longer_burn_in(burn_in: float | None, span: tuple[float, float] | None) -> Remedy:
    """A burn-in that ends where the diagnostic's drift did: its cells switched at another
    rate in the first half of their record than in the second, so they were still drifting
    ``model.burn_in`` + ``gp.diagnostic.equilibration_time`` + half of ``gp.diagnostic.t_end``
    (``burn_in`` and ``span``, in s) after their fixed start counts; a burn-in that long, in
    whole seconds, settles the collection's cells too (they start after the burn-in alone).
    Printed as ``++model.burn_in=...`` (a yaml model's key); without ``burn_in`` (a model
    whose start does not simulate one) or ``span``, no value.

    Example:
        >>> longer_burn_in(50.0, (10.0, 100.0)).overrides
        ('++model.burn_in=110',)
    """
    if burn_in is None or not burn_in > 0 or span is None or not span[1] > 0:
        return Remedy("longer_burn_in", "a longer burn-in (`model.burn_in`, where the model "
                      "has one; `python3 scripts/inspect_model.py` measures the settling "
                      "time)")  # fmt: skip
    equilibration, t_end = span
    needed = math.ceil(burn_in + equilibration + t_end / 2)
    return Remedy("longer_burn_in", f"a longer burn-in, `++model.burn_in={needed}` (now "
                  f"{burn_in:g} s: the diagnostic's cells still drifted {equilibration + t_end / 2:g} "
                  f"s after it; the collection's cells start after it too)",
                  (f"++model.burn_in={needed}",))  # fmt: skip


def coarser_classes(
    classes: CountClasses, sparse: str, shared: bool = False
) -> tuple[CountClasses, str] | None:
    """``classes`` with the bin of the class ``sparse`` merged into its neighbour in its lump
    (the edge between them removed), and the neighbour's name; None where ``sparse`` is not
    one of them or its lump has one bin. An end bin (a count's tail) merges inwards; a middle
    one with the neighbour nearer the lump's middle. Bins both lumps share (a flip keeps the
    bin, and ``shared``: relaxation needs them) lose the edge in both lumps; where no edge
    would be left, None (the classes would be the lumps: the two-state chain)."""
    if sparse not in classes.names:
        return None
    index = classes.names.index(sparse)
    phi = classes.lumps[index]
    j = index - (0 if phi == 0 else len(classes.edges[0]) + 1)
    edges = classes.edges[phi]
    if not edges:
        return None
    bins = len(edges) + 1
    # the removed edge: below the bin (merge with the lower neighbour) or above it
    upper = j == 0 or (j < bins - 1 and j < (bins - 1) / 2)
    cut = edges[j] if upper else edges[j - 1]
    together = classes.edges[0] == classes.edges[1]
    if shared and not together:
        return None
    new = tuple(tuple(e for e in classes.edges[p] if e != cut)
                if p == phi or together else classes.edges[p] for p in (0, 1))  # fmt: skip
    if not new[0] and not new[1]:
        return None
    merged = CountClasses(classes.variable, (new[0], new[1]), classes.lump_names)
    neighbour = classes.names[index + (1 if upper else -1)]
    return merged, neighbour


def classes_override(classes: CountClasses) -> str:
    """``classes`` as a command-line override Hydra parses (``++model.classes={species: D,
    edges: {off: [1], on: [3]}}``; one list where both lumps share the edges)."""

    def listed(edges: Sequence[float]) -> str:
        return "[" + ", ".join(f"{e:g}" for e in edges) + "]"

    variable = classes.variable
    count = (f"species: {variable}" if variable.isidentifier()
             else f"expression: '{variable}'")  # fmt: skip
    if classes.edges[0] == classes.edges[1]:
        edges = listed(classes.edges[0])
    else:
        # Hydra's grammar takes bare keys (a quoted one is no key; a name it reads otherwise,
        # e.g. true, the check refuses)
        edges = "{" + ", ".join(f"{n}: {listed(e)}" for n, e in
                                zip(classes.lump_names, classes.edges, strict=True)) + "}"  # fmt: skip
    return f"++model.classes={{{count}, edges: {edges}}}"


def coarser_remedy(classes: CountClasses | None, sparse: str | None, shared: bool) -> Remedy:
    """The remedy "coarser classes": where the model's classes are bins of a count and the
    sparse class is known, the edges with it merged into its neighbour
    (:func:`coarser_classes`), as the override that sets them; else the setting to change."""
    coarser = None if classes is None or sparse is None else \
        coarser_classes(classes, sparse, shared)  # fmt: skip
    if coarser is None:
        return Remedy("coarser_classes", "coarser classes (`model.classes`: fewer, wider bins)")
    merged, neighbour = coarser
    override = classes_override(merged)
    return Remedy("coarser_classes", f"coarser classes: `{sparse}` merged with its neighbour "
                  f"`{neighbour}`, `{override}`", (override,))  # fmt: skip


def clock_remedies(max_age: float | None, n_per_state: int | None, classes: Remedy) -> list[Remedy]:
    """The next steps for a chain with a switch clock (``gp=clock``) whose runs differ from the
    full model while its psi is unbiased where the population lives: what was not tried, not
    the clock again. A longer clock first (ages beyond ``gp.max_age`` are clamped to it, so
    memory that outlasts the cap is lost), then more transitions (the clock's psi is over one
    input more, the age, and each age bin sees a share of the rows: on the toggle switch the
    clock needed more data than the two-state chain, docs/fidelity.md); classes only where the
    memory is a slow count, not a cycle's phase (on Tyson's oscillator classes over its
    threshold's count did worse than the two-state chain, docs/sbml.md)."""
    if max_age is not None:
        longer = Remedy("longer_clock", f"the switch clock is on already; first a longer "
                        f"clock, `gp.max_age={2 * max_age:g}` (twice the `gp.max_age="
                        f"{max_age:g}` that ran): an age beyond the cap is clamped to it, so "
                        f"memory that outlasts it is lost (`python3 scripts/inspect_model.py` "
                        f"gives the age where the hazard flattens and, for an oscillating "
                        f"lump, the period).", (f"gp.max_age={2 * max_age:g}",))  # fmt: skip
    else:
        longer = Remedy("longer_clock", "the switch clock is on already; first a longer "
                        "clock, a larger `gp.max_age`: an age beyond the cap is clamped to it.")  # fmt: skip
    more = more_rows(n_per_state, "Then more transitions ({more}): the clock's psi is over "
                      "the age as well, and each age sees a share of the rows.")  # fmt: skip
    only = Remedy(classes.kind, f"{classes.text[0].upper()}{classes.text[1:]} only where the "
                  f"memory is a slow count rather than a cycle's phase (the inspector says "
                  f"which): bins of a count do not hold where a cycle is, and on an oscillator "
                  f"they did worse than the two-state chain (docs/sbml.md).",
                  classes.overrides)  # fmt: skip
    return [longer, more, only]


def clock_step(max_age: float | None, n_per_state: int | None, classes: str) -> str:
    """:func:`clock_remedies` as one text (``classes``: how the model gets classes)."""
    remedies = clock_remedies(max_age, n_per_state, Remedy("classes", f"classes ({classes})"))
    return " ".join(r.text for r in remedies)


@dataclass(frozen=True)
class MeasuredChoice:
    """What the verdict reads of the measured choice that made the run's chain (``gp=auto``:
    the record's ``choice.json`` and the ``gp.choice`` settings it was made with).

    Attributes:
        chosen: the chosen candidate's name (``two-state``, ``clock max_age=2``, ``classes``,
            ``phases``).
        scores: the record's table, one row per candidate (``kind``, ``complexity``,
            ``log_likelihood_per_window``, ``diff_from_best``, ``diff_se``,
            ``tied_with_best``, ``holds_durations``).
        kinds: ``gp.choice.kinds``: the candidate families asked for.
        max_ages: ``gp.choice.max_ages`` (s): the clock's caps tried.
        n_cells: ``gp.choice.n_cells``: the held-out full-model cells.
        tie_se: ``gp.choice.tie_se``: how many SE make a tie.
        classes: whether the model declares classes (K lumps can be a candidate).
        duration_tolerance: ``gp.choice.duration_tolerance``: the means' relative difference
            a candidate held to be chosen first (None: a record that does not say).
        thinned: whether its collection records one window in several (``record_every`` > 1)
            without keeping every switch and class move (``collect.keep_switches``): K lumps
            over a network's chosen classes are then advised with every class move kept.
    """

    chosen: str
    scores: tuple[Mapping[str, Any], ...]
    kinds: tuple[str, ...]
    max_ages: tuple[float, ...]
    n_cells: int
    tie_se: float
    classes: bool
    duration_tolerance: float | None = None
    thinned: bool = False

    def none_held(self) -> tuple[str, float] | None:
        """Where the choice's screen held no candidate (every row's ``holds_durations``
        false, under a known tolerance): the chosen candidate's farthest lump and its
        relative difference of the means; else None."""
        if self.duration_tolerance is None or not self.scores:
            return None
        if any(r.get("holds_durations", True) for r in self.scores):
            return None  # one held, or a record that does not say
        row = next((r for r in self.scores if str(r["kind"]) == self.chosen), None)
        suffix = "_mean_rel_diff"
        return farthest_lump({k[: -len(suffix)]: float(v) for k, v in (row or {}).items()
                              if k.endswith(suffix) and v is not None})  # fmt: skip


#: the candidate families that hold memory phi alone forgets (two-state holds none), as
#: gp.choice.kinds names them
MEMORY_FAMILIES = ("clock", "classes", "phases")
#: the family that needs classes the model declares (K lumps)
CLASSES_FAMILY = MEMORY_FAMILIES[1]


#: the measured choice's K-lumps candidate whose bins relax (where the model's classes are bins
#: both lumps share), fitted by gp=classes' recipe, and the overrides that train it outright
RELAXING_CANDIDATE = "classes relaxation"
RELAXING_OVERRIDES = ("gp=classes", "gp.class_moves=relaxation")


def nameable(name: str, row: Mapping[str, Any] | None = None) -> bool:
    """Whether candidate ``name`` can be trained outright from its record: a log clock only
    with its row's recorded overrides (its knee and bins are not in its name)."""
    return bool(row is not None and row.get("overrides")) or not name.startswith(LOG_CLOCK)


def candidate_overrides(name: str, row: Mapping[str, Any] | None = None) -> tuple[str, ...]:
    """The overrides that train candidate ``name`` outright, without the choice: those its
    row of the choice's table records (``overrides``: every gp key it was made with, a log
    clock's knee and bins among them), else, for a record without them, ``gp=svgp``
    (two-state), ``gp=clock gp.max_age=X``, ``gp=classes gp.class_moves=relaxation``
    (:data:`RELAXING_CANDIDATE`), or ``gp=<name>`` (its recipe).

    Raises:
        ValueError: an older record's candidate whose name alone cannot say how to train it
            (a clock on a log axis).
    """
    if row is not None and row.get("overrides"):
        return tuple(str(row["overrides"]).split())
    if not nameable(name, row):
        raise ValueError(f"candidate {name!r}: its knee and bins are in its row's overrides, "
                         f"which this record lacks")  # fmt: skip
    cap = candidate_cap(name)
    if cap is not None:
        return ("gp=clock", f"gp.max_age={cap:g}")
    if name == RELAXING_CANDIDATE:
        return RELAXING_OVERRIDES
    return ("gp=svgp",) if name == "two-state" else (f"gp={name}",)


def _listed(values: Sequence[Any]) -> str:
    return "[" + ",".join(f"{v:g}" if isinstance(v, float) else str(v) for v in values) + "]"


def _holds_more_memory(row: Mapping[str, Any], chosen: Mapping[str, Any]) -> bool:
    """Whether candidate ``row`` holds more memory than the ``chosen`` one: a clock with a
    longer cap, else a more complex kind."""
    cap, chosen_cap = candidate_cap(str(row["kind"])), candidate_cap(str(chosen["kind"]))
    if cap is not None and chosen_cap is not None:
        return cap > chosen_cap
    return int(row["complexity"]) > int(chosen["complexity"])


def _standing(row: Mapping[str, Any]) -> str:
    """A candidate's standing in the table, in words."""
    gap, se = float(row["diff_from_best"]), float(row.get("diff_se") or math.nan)
    if gap == 0:
        where = "had the highest held-out log-likelihood"
    elif math.isfinite(se) and se > 0:
        where = f"was {-gap / se:.1f} SE below the best held-out log-likelihood"
    else:
        where = f"was {-gap:.1e} per window below the best held-out log-likelihood"
    return where + ("" if row.get("holds_durations") else " and did not hold its durations")


def choice_remedies(choice: MeasuredChoice, n_per_state: int | None, network: bool) -> list[Remedy]:
    """The next steps where the runs miss memory that the kind the measured choice chose
    (``gp=auto``) does not hold: work through the choice, not around it (a kind named outright
    throws the measurement away). In order: wider candidates (a longer cap where the clock was
    chosen at the largest of ``gp.choice.max_ages``; the memory families ``gp.choice.kinds``
    left out; K lumps over ``++model.classes=auto`` for a network that declares no classes);
    more held-out cells where the choice was a tie within its SE (four times: the SE halves);
    more transitions; last, as an explicit alternative outside the choice, the best candidate
    that holds more memory than the chosen (a longer clock or a more complex kind), named with
    its standing in the table.

    Args:
        choice: the measured choice's record and settings.
        n_per_state: the collection's transitions per origin (None: unknown).
        network: whether the model is a reaction network (``model.classes=auto`` applies).
    """
    rows = {str(r["kind"]): r for r in choice.scores}
    chosen = rows.get(choice.chosen)
    out: list[Remedy] = []
    cap = candidate_cap(choice.chosen)
    if cap is not None and cap >= max(choice.max_ages):
        ages = _listed([*choice.max_ages, 2 * cap])
        out.append(Remedy("wider_caps", f"The choice chose the switch clock at its largest cap, "
                          f"{cap:g} s, and an age beyond the cap is clamped to it: a longer cap "
                          f"among the candidates, `gp.choice.max_ages={ages}` (the choice "
                          f"measures it against the rest).", (f"gp.choice.max_ages={ages}",)))  # fmt: skip
    # K lumps are a candidate only where the model declares classes: a network gets them
    auto_classes = not choice.classes and network
    missing = [f for f in MEMORY_FAMILIES if f not in choice.kinds
               and (f != CLASSES_FAMILY or choice.classes or auto_classes)]  # fmt: skip
    overrides: list[str] = []
    if missing:
        kinds = [*choice.kinds, *missing]
        overrides.append(f"gp.choice.kinds=[{','.join(kinds)}]")
    kept = False
    if auto_classes and CLASSES_FAMILY in (*choice.kinds, *missing):
        overrides.append("++model.classes=auto")
        # a thinned table holds one in record_every of the chain's moves within a lump: the
        # immigration-death's fitted sojourns 4.6-5.5 % off the exact ones, 1.5-2.0 % kept
        # (its check 17 -> 22 of 24; CERENA's, where K lumps trail, 20 -> 17: docs/choice.md)
        kept = choice.thinned
        if kept:
            overrides.append("collect.keep_switches=true")
    if overrides:
        left = f"left {', '.join(missing)} out (`gp.choice.kinds`)" if missing else ""
        none = "had no K lumps (the model declares no classes)" if auto_classes else ""
        out.append(Remedy("wider_kinds", f"The choice {' and '.join(w for w in (left, none) if w)}: "
                          f"wider candidates, `{' '.join(overrides)}`"
                          + (" (`model.classes=auto` chooses bins of the count that holds the "
                             "memory" + ("; `collect.keep_switches=true` keeps every move "
                                         "between them, which a thinned table samples"
                                         if kept else "") + ")" if auto_classes else "")
                          + ".", tuple(overrides)))  # fmt: skip
    tied = [k for k, r in rows.items() if r.get("tied_with_best") and k != choice.chosen]
    if tied:
        n = 4 * choice.n_cells
        out.append(Remedy("more_cells", f"The choice was a tie within {choice.tie_se:g} SE "
                          f"between {choice.chosen} (chosen) and {', '.join(tied)}: four times "
                          f"the held-out cells, `gp.choice.n_cells={n}`, halve the SE and may "
                          f"tell them apart.", (f"gp.choice.n_cells={n}",)))  # fmt: skip
    out.append(more_rows(n_per_state, "More transitions ({more}): every candidate's fit "
                         "sharpens, and with it the choice."))  # fmt: skip
    if chosen is not None:
        more = [r for k, r in rows.items() if k != choice.chosen and _holds_more_memory(r, chosen)]
        more = [r for r in more if nameable(str(r["kind"]), r)]
        runner = max(more, key=lambda r: (bool(r.get("holds_durations")),
                                          float(r["log_likelihood_per_window"])), default=None)  # fmt: skip
        if runner is not None:
            name = str(runner["kind"])
            named = candidate_overrides(name, runner)
            out.append(Remedy("runner_up", f"Outside the choice (it throws the measurement "
                              f"away): the next candidate with more memory, {name}, "
                              f"{_standing(runner)}: `{' '.join(named)}` to try it outright.",
                              named))  # fmt: skip
    return out


__all__ = [
    "DIAGNOSTIC_MARGIN",
    "DURATION_TOLERANCE",
    "MEMORY_FAMILIES",
    "RELAXING_CANDIDATE",
    "RELAXING_OVERRIDES",
    "Advisor",
    "Check",
    "MeasuredChoice",
    "Remedy",
    "candidate_overrides",
    "choice_remedies",
    "classes_override",
    "clock_remedies",
    "clock_step",
    "coarser_classes",
    "coarser_remedy",
    "diagnostic_cells_needed",
    "larger_diagnostic",
    "later_diagnostic_start",
    "longer_burn_in",
    "more_rows",
]
