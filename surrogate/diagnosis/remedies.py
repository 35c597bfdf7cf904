"""The remedies the verdict (:mod:`surrogate.diagnosis.advice`) prints: each a setting to change,
checked before it is printed and never advised again where a previous run applied it without a
gain; coarser classes as concrete edges; what the switch clock tries next."""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass

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
        ``then``; a note names each one left out and why."""
        kept, notes = [], []
        for r in remedies:
            why = self.tried.get(r.kind)
            if why is None and r.overrides and self.check is not None:
                why = self.check(r.overrides, r.text)
            if why is None:
                kept.append(r)
                self.remedies.append((cause, r))
            else:
                self.dropped.append((cause, r, why))
                notes.append(f"not advised: {' '.join(r.overrides) or r.kind} ({why})")
        text = sep.join(r.text for r in kept) + then if kept else \
            "nothing this reading can advise runs or is untried"  # fmt: skip
        return text + "".join(f" [{n}]" for n in notes)


def more_rows(n_per_state: int | None, text: str = "more transitions ({more})") -> Remedy:
    """More collected rows: four times ``collect.n_per_state`` where it is known."""
    if n_per_state:
        more = f"`collect.n_per_state={4 * n_per_state}`"
        return Remedy("more_rows", text.format(more=more),
                      (f"collect.n_per_state={4 * n_per_state}",))  # fmt: skip
    return Remedy("more_rows", text.format(more="a larger `collect.n_per_state`"))


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


__all__ = [
    "Advisor",
    "Check",
    "Remedy",
    "classes_override",
    "clock_remedies",
    "clock_step",
    "coarser_classes",
    "coarser_remedy",
    "more_rows",
]
