"""Whether to trust an abstraction, and what to try next, from what a run measured.

A report's tables say where an abstraction differs from its full model; a user new to the method
needs the reading: is this within noise, and if not, which setting to change. :func:`verdict`
reads the measurements a reproduce run has (the evaluations against the full model and its noise
floor, the learned psi's diagnostic where the population lives, the inputs outside the trained
range) and names, in order, the first causes that apply:

1. **Outside the training data** (any run's share of cell-steps with an input outside the trained
   range above ``outside_warning``): the psi there is the range's edge, not learned: collect
   where the cells go. **Sparse training data** (inside the range, a share of cell-steps above
   the same threshold in bins of the fit's histogram where its training rows are sparse):
   the psi there is the fit's guess between few rows: training rows there. A cause only where
   a comparison fails; where every one passes it is a caveat beside the trust (a GP pools
   neighbouring bins, which the per-bin count does not credit: the band passed at 100,000 cells
   with a quarter of its cell-steps in such bins, docs/fields.md).
2. **Not settled** (the diagnostic population's switching frequency differs between the first
   and second half of its run by more than 4 standard errors): the full model's cells were
   still drifting from their start: the diagnostic's record starts half its run later
   (``gp.diagnostic.equilibration_time``), or the burn-in is too short.
3. **Biased psi** (|bias| above two standard errors and above the duration tolerance): the
   learned switching probability where cells live is off, and the mean durations with it (the
   predicted error beside the measured): more transitions. A reference too noisy to tell (its
   standard error above the tolerance): a larger diagnostic population.
4. **Class shares drift** (a K-lumps chain whose classes, run as the diagnostic's full-model
   population was, end in shares the chi-square test tells from the full model's): its moves
   between classes are off although each class may switch right: bins of a slow count moving
   by relaxation (``gp.class_moves=relaxation``), or more transitions per class.
5. **Memory** (the runs differ from the full model beyond the noise floor while the psi is
   unbiased within its error): the chain over phi forgets what the network remembers: classes
   finer than phi (``gp=classes``, with ``model.classes=auto`` for a network) or a switch clock
   (``gp=clock``). Where the clock ran already, what was not tried (:func:`~surrogate.diagnosis.remedies.clock_step`): a
   longer clock (twice ``gp.max_age``), more transitions, and classes only where the memory is
   a slow count rather than a cycle's phase; never the setting in use. Where the chain was
   chosen by measurement (``gp=auto``), through the choice, not around it
   (:func:`~surrogate.diagnosis.remedies.choice_remedies`): wider candidates (a longer cap in
   ``gp.choice.max_ages`` where the clock won at the largest; the memory families
   ``gp.choice.kinds`` left out), more held-out cells where the choice was a tie, more
   transitions, and the next candidate with more memory only as an explicit alternative.

None applying: every comparison is within the noise floor or the critical value at this
population size; trust it there and check at scale (``scripts/fidelity.py``). Where the chain
was chosen by measurement and no candidate held its durations on the choice's held-out cells
(``MeasuredChoice.none_held``: the closest was chosen), that is a caveat beside the trust, with
the choice's remedies (a cause where another cause applies; left to the memory cause, which
prints the same remedies, where that applies).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

from surrogate.diagnosis.remedies import (
    Advisor,
    Check,
    MeasuredChoice,
    Remedy,
    choice_remedies,
    clock_remedies,
    coarser_remedy,
    larger_diagnostic,
    later_diagnostic_start,
    longer_burn_in,
    more_rows,
)
from surrogate.kinds import ChainKind
from surrogate.models.count_classes import CountClasses
from surrogate.simulate.support import describe_sparse_where, sparse_share

#: |first half - second half| of the diagnostic's switching, in standard errors, above which
#: its population was still settling
SETTLING_Z = 4.0
#: a bias is significant above this many standard errors
BIAS_Z = 2.0
#: the cause read where the runs fail with psi unbiased
MEMORY_CAUSE = "Memory the chain over phi does not hold"
#: the cause whose remedies put a lagging collection's blackout first
BIASED_CAUSE = "Biased switching probabilities"


@dataclass
class Verdict:
    """The reading of a run's measurements.

    Attributes:
        trust: no cause applies: within the noise floor at this size.
        causes: each cause that applies: ``(name, what was measured, the next step)``.
        caveats: what to watch where it is trusted, as causes are written.
        remedies: ``(cause, remedy)`` for every remedy printed.
        dropped: ``(cause, remedy, why)`` for every remedy not printed: refused by the
            settings' checks, or tried by a previous run of the model without a gain.
    """

    trust: bool
    causes: list[tuple[str, str, str]] = field(default_factory=list)
    caveats: list[tuple[str, str, str]] = field(default_factory=list)
    remedies: list[tuple[str, Remedy]] = field(default_factory=list)
    dropped: list[tuple[str, Remedy, str]] = field(default_factory=list)

    def markdown(self, confirm: str = "python3 scripts/fidelity.py") -> str:
        """The verdict as report text; ``confirm`` is the check at scale it names where it
        trusts the run (the fidelity command of the run's model and collection)."""
        if self.trust:
            caveats = "".join(f"\n\nCaveat, **{name}**: {measured} Where a check at scale "
                              f"fails: {step}" for name, measured, step in self.caveats)  # fmt: skip
            return (
                "**Trust it at this size**: every comparison is within the full model's "
                "noise floor or the KS critical value, the learned psi is unbiased where the "
                "population lives within its error, and no run left the training data. "
                "Small differences hide at small populations: confirm at scale with "
                f"`{confirm}` (thousands of cells, several training seeds)." + caveats
            )
        lines = ["**Do not trust it yet.** In order (the first is the likeliest cause of the "
                 "others):", ""]  # fmt: skip
        for i, (name, measured, step) in enumerate(self.causes, 1):
            lines.append(f"{i}. **{name}**: {measured} Next: {step}")
        return "\n".join(lines)


def _missing(value: Any) -> bool:
    """Whether a measurement is missing or NaN: not measured, never evidence."""
    return value is None or (isinstance(value, float) and math.isnan(value))


def unmeasured(
    diagnostic: Mapping[str, Any] | None,
    lump_names: Sequence[str],
    outside: Mapping[str, Mapping[str, Any] | None],
) -> list[str]:
    """What the verdict needs and the run did not measure (missing or NaN): the learned psi's
    diagnostic leaving each lump (its bias; a NaN bias where the reference never left that
    lump) and each field's outside-training report."""
    out = []
    if not diagnostic:
        out.append("the learned psi's diagnostic (none in train_metrics.json)")
    else:
        for p in (0, 1):
            s = diagnostic.get(f"phi{p}")
            if not s:
                out.append(f"the diagnostic leaving {lump_names[p]} (absent)")
            elif _missing(s.get("rel_bias")):
                out.append(f"the psi's bias leaving {lump_names[p]} ({s.get('rel_bias')}: e.g. "
                           f"a reference that never left {lump_names[p]})")  # fmt: skip
            elif _missing(s.get("settling_z", 0.0)):
                out.append(f"the settling of the diagnostic leaving {lump_names[p]} (NaN)")
    for f, r in outside.items():
        if not r or _missing(r.get("share_outside")):
            out.append(f"field {f}'s inputs against the training data (no outside-training "
                       f"report)")  # fmt: skip
    return out


@dataclass(frozen=True)
class VerdictInputs:
    """What a reproduce run measured, as the verdict reads it.

    Attributes:
        diagnostic: the learned psi's diagnostic (``train_metrics.json["diagnostic"]``).
        lump_names: phi = 0 and 1's names.
        failures: per field, the quantities above the noise floor and critical value.
        outside: per field, the abstraction run's ``outside_training`` report.
        outside_warning: the share above which a run is outside its training data (or, by
            its ``share_sparse``, where it was sparse).
        tolerance: the mean-duration tolerance a bias is judged by (e.g. 0.03).
        kind: the chain that ran (:func:`~surrogate.kinds.chain_kind`): its classes, its
            switch clock and how its classes moved.
        network: whether the model is a reaction network (``model.classes=auto`` applies).
        n_per_state: the collection's transitions per origin (for the advice).
        class_shares: a K-lumps chain's class shares against the full model's
            (``train_metrics.json["class_shares"]``).
        max_age: the switch clock's cap (s) where the chain ran with one (``kind.clock``).
        count_classes: the model's classes where they are bins of a count: coarser classes
            are then advised as edges (:func:`~surrogate.diagnosis.remedies.coarser_classes`).
        choice: the measured choice that chose ``kind`` (``gp=auto``); None where the kind was
            named or the rule chose it. Its memory remedies then work through the choice.
        wider_collection: the overrides that send collect's perturbation further
            (:meth:`~surrogate.models.base.Model.wider_collection`), advised where the runs
            leave the trained inputs; empty where the model has none.
        blackout: the collection that keeps out rows still lagging a jump (collect's
            manifest, ``after_jump.advice``: :func:`~surrogate.diagnosis.jumps.blackout_advice`),
            advised first where psi is biased; empty where its rows did not lag.
        diagnostic_cells: the diagnostic population's cells (``gp.diagnostic.n_cells``): a
            reference too noisy to judge is advised the cells that bring its error under the
            tolerance (:func:`~surrogate.diagnosis.remedies.larger_diagnostic`); None: no value to advise.
        diagnostic_span: the diagnostic population's settling and recorded spans (s,
            ``gp.diagnostic.equilibration_time`` and ``t_end``): a population not settled is
            advised a later start of its record
            (:func:`~surrogate.diagnosis.remedies.later_diagnostic_start`); None: no value.
        burn_in: the model's burn-in (s, ``model.burn_in``) where its cells' start simulates
            one and the model is a yaml (its key is given as ``++model.burn_in``): a population
            not settled is advised one that ends where the drift did
            (:func:`~surrogate.diagnosis.remedies.longer_burn_in`); None: no value.
    """

    diagnostic: Mapping[str, Any] | None
    lump_names: Sequence[str]
    failures: Mapping[str, Sequence[str]]
    outside: Mapping[str, Mapping[str, Any] | None]
    outside_warning: float
    tolerance: float
    kind: ChainKind
    network: bool
    n_per_state: int | None
    class_shares: Mapping[str, Any] | None = None
    max_age: float | None = None
    count_classes: CountClasses | None = None
    choice: MeasuredChoice | None = None
    wider_collection: tuple[str, ...] = ()
    blackout: tuple[str, ...] = ()
    diagnostic_cells: int | None = None
    diagnostic_span: tuple[float, float] | None = None
    burn_in: float | None = None


def verdict(  # noqa: C901  # one branch per first cause, in the report's order
    run: VerdictInputs, check: Check | None = None, tried: Mapping[str, str] | None = None
) -> Verdict:
    """Read the measurements (see the module docstring).

    Args:
        run: what the run measured.
        check: checks a remedy's overrides before it is printed (``(overrides, text) ->
            refusal or None``); None: not checked.
        tried: remedy kinds not to advise again, each with what its last run measured
            (:func:`surrogate.stages.advice.tried_remedies`).

    A measurement the verdict needs that is missing or NaN (:func:`unmeasured`) is not
    evidence: the verdict is then not to trust, naming what was not measured.
    """
    diagnostic, lump_names, failures, outside = (run.diagnostic, run.lump_names, run.failures,
                                                 run.outside)  # fmt: skip
    outside_warning, tolerance, kind, network = (run.outside_warning, run.tolerance, run.kind,
                                                 run.network)  # fmt: skip
    n_per_state, class_shares, max_age, count_classes = (run.n_per_state, run.class_shares,
                                                         run.max_age, run.count_classes)  # fmt: skip
    advisor = Advisor(check, tried)
    causes: list[tuple[str, str, str]] = []
    missing = unmeasured(diagnostic, lump_names, outside)
    if missing:
        causes.append((
            "Not measured",
            "the verdict needs what this run did not measure: " + "; ".join(missing)
            + ". A missing or NaN measurement is no evidence that the psi is unbiased or that "
            "the inputs stayed inside the training data.",
            "rerun the stages that measure them (`gp.diagnostic` in train, the abstraction's "
            "runs in simulate) or read the tables alone.",
        ))  # fmt: skip
    away = {f: r for f, r in outside.items() if r and (r.get("share_outside") or 0.0)
            > outside_warning}  # fmt: skip
    if away:
        parts = []
        for f, r in away.items():
            inputs = [f"{n} seen [{v['seen'][0]:.3g}, {v['seen'][1]:.3g}] vs trained "
                      f"[{v['trained'][0]:.3g}, {v['trained'][1]:.3g}]"
                      for n, v in r["inputs"].items() if v["share_below"] or v["share_above"]]  # fmt: skip
            parts.append(
                f"{f}: {100 * r['share_outside']:.1f} % of cell-steps ({'; '.join(inputs)})"
            )
        name = "Outside the training data"
        wider = run.wider_collection
        remedies = [Remedy("training_field", "training where they go (a `field` whose inputs "
                           f"span those of {', '.join(sorted(away))})")]  # fmt: skip
        if wider:
            remedies.insert(0, Remedy("wider_collection", f"a collection that reaches them, "
                                      f"`{' '.join(wider)}` (collect's jumps twice as far "
                                      f"from the field's peak)", wider))  # fmt: skip
        causes.append((
            name,
            "the abstraction ran outside the inputs it was trained on in " + "; ".join(parts)
            + ", where its lookup clamps to the range's edge.",
            "collect transitions where these cells go: "
            + advisor.step(name, remedies, then="."),
        ))  # fmt: skip
    failing = {f: list(q) for f, q in failures.items() if q}
    thin = _sparse_rows(outside, outside_warning, n_per_state, advisor, count_classes,
                        kind.relaxation)  # fmt: skip
    caveats: list[tuple[str, str, str]] = []
    if thin is not None:  # a cause where a comparison fails, else a caveat beside the trust
        (causes if failing else caveats).append(thin)
    d = diagnostic or {}
    scores = {p: d.get(f"phi{p}") for p in (0, 1)}
    settling = [(p, s["settling_z"]) for p, s in scores.items()
                if s and not _missing(s.get("settling_z"))
                and abs(s["settling_z"]) > SETTLING_Z]  # fmt: skip
    if settling:
        what = ", ".join(f"leaving {lump_names[p]}: {z:+.1f} standard errors"
                         for p, z in settling)  # fmt: skip
        step = advisor.step("Not settled", [later_diagnostic_start(run.diagnostic_span),
                                             longer_burn_in(run.burn_in, run.diagnostic_span)],
                             then=".")  # fmt: skip
        causes.append((
            "Not settled",
            f"the full model's diagnostic population switched at different rates in the first "
            f"and second half of its run ({what}): its cells were still drifting from where they "
            f"started, so its transitions (and the collection's) are not those of settled cells.",
            step,
        ))  # fmt: skip
    biased, noisy, noisy_se = [], [], []
    for p, s in scores.items():
        if not s or _missing(s.get("rel_bias")):
            continue
        se = s.get("rel_bias_se")
        se = None if _missing(se) else se
        bias = s["rel_bias"]
        if se is not None and se > tolerance:
            noisy.append(f"leaving {lump_names[p]}: {100 * bias:+.1f} % +- {100 * se:.1f} %")
            noisy_se.append(float(se))
        elif abs(bias) > tolerance and (se is None or abs(bias) > BIAS_Z * se):
            pred = s.get("predicted_duration_error") or (1 / (1 + bias) - 1)
            err = f"+- {100 * se:.1f} %" if se is not None else "(exact reference)"
            biased.append(f"leaving {lump_names[p]}: {100 * bias:+.1f} % {err}, which predicts "
                          f"{100 * pred:+.1f} % in the mean {lump_names[p]} duration")  # fmt: skip
    if biased:
        name = BIASED_CAUSE
        causes.append((
            name,
            "where the population lives the learned psi is off: " + "; ".join(biased) + ".",
            advisor.step(name, [*_blackout(run.blackout),
                                more_rows(n_per_state, "more transitions ({more}: the bias "
                                          "of a GP fit falls with its data)")],
                         then=", and check `gp.epochs`/`gp.n_inducing` converged (the training "
                              "history figure)."),
        ))  # fmt: skip
    if noisy:
        name = "A reference too noisy to judge"
        causes.append((
            name,
            "the diagnostic's full-model reference cannot tell the learned psi's bias from "
            "none: " + "; ".join(noisy) + ".",
            advisor.step(name, [larger_diagnostic(run.diagnostic_cells, max(noisy_se), tolerance)],
                         then="."),
        ))  # fmt: skip
    shares = class_shares or {}
    drift = kind.classes and bool(shares.get("drift"))
    if drift:
        name = "Class shares drift"
        more = more_rows(n_per_state, "more transitions per class ({more})")
        if kind.relaxation:
            remedies = [more, Remedy("other_classes", "other classes (`model.classes`)")]
        else:
            # under gp=auto the group has no class_moves: relaxation is K lumps named outright
            relax = (("gp=classes", "gp.class_moves=relaxation") if run.choice is not None
                     else ("gp.class_moves=relaxation",))  # fmt: skip
            beside = " (outside the measured choice)" if run.choice is not None else ""
            remedies = [Remedy("relaxation", f"`{' '.join(relax)}`{beside} where the classes "
                               "are bins of a slow count (the learned moves between bins, rare "
                               "per window and mostly a count jittering across an edge, mix "
                               "them faster than the count moves)", relax),
                        more]  # fmt: skip
        causes.append((
            name,
            f"run as the diagnostic's full-model population was, the chain's classes after "
            f"{shares['t']:g} s are {100 * shares['total_variation']:.1f} % (total variation) "
            f"from the full model's, chi-square p = {shares['p_value']:.2g}: its moves between "
            "classes are off, whatever each class's switching.",
            advisor.step(name, remedies, then="."),
        ))  # fmt: skip
    if failing and not biased and not away and thin is None and not drift:
        name = MEMORY_CAUSE
        what = "; ".join(f"{f}: {', '.join(q)}" for f, q in failing.items())
        classes = (Remedy("classes", "classes finer than phi, `gp=classes` with "
                          "`++model.classes=auto` (or declared bins of the count that holds "
                          "the memory)", ("gp=classes", "++model.classes=auto"))
                   if network else
                   Remedy("classes", "classes finer than phi, `gp=classes` where the model "
                          "declares classes", ("gp=classes",)))  # fmt: skip
        if run.choice is not None:  # the measured choice: widen or sharpen it
            other = ([Remedy("other_classes", "More classes or other bins (`model.classes`): "
                             "the K-lumps candidate changes, and the choice measures it again.")]
                     if kind.classes else [])  # fmt: skip
            step = advisor.step(name, other + choice_remedies(run.choice, n_per_state, network),
                                sep=" ")  # fmt: skip
        elif kind.classes:
            step = advisor.step(name, [
                Remedy("other_classes", "more classes or other bins (`model.classes`)"),
                more_rows(n_per_state, "more transitions per class ({more})")], then=".")  # fmt: skip
        elif kind.clock:
            step = advisor.step(name, clock_remedies(max_age, n_per_state, classes), sep=" ")
        else:
            step = advisor.step(name, [classes, Remedy("clock", "the switch clock `gp=clock`",
                                                       ("gp=clock",))], then=".")  # fmt: skip
        causes.append((
            name,
            f"the runs differ from the full model beyond its noise floor ({what}) while the "
            "learned switching probabilities match the full model's where the population "
            "lives: what phi alone forgets (the network's hidden state) shapes the runs.",
            step,
        ))  # fmt: skip
    memory = any(c[0] == MEMORY_CAUSE for c in causes)
    choice = run.choice
    held_none = choice.none_held() if choice is not None else None
    if choice is not None and held_none is not None and not memory:  # memory: same remedies
        name = "No candidate held its durations"
        lump, miss = held_none
        caveats.append((
            name,
            f"on the measured choice's held-out full-model cells no candidate kept every "
            f"lump's mean duration within {choice.duration_tolerance:.0%} "
            f"(`gp.choice.duration_tolerance`); {choice.chosen}, chosen as the closest, "
            f"was {100 * miss:+.1f} % on {lump} there, so these runs agreeing at this size "
            "says less than it would of a chain that held them (docs/choice.md).",
            advisor.step(name, choice_remedies(choice, n_per_state, network), sep=" "),
        ))  # fmt: skip
    if run.blackout and not any(c[0] == BIASED_CAUSE for c in causes):
        # the chosen psi may read the clock (unbiased here) while the candidates that read
        # none learned the lag, and the choice was made among them (CERENA's gene-expression
        # network: 14 of 24 at scale on such a collection, 19 of 24 on the settled one)
        name = "Rows that lag their jumps"
        caveats.append((
            name,
            "collect warned that its rows soon after a jump switch at other rates than "
            "settled ones; a psi that reads no clock learns that lag"
            + ("; the chain was chosen among candidates that do." if choice is not None
               else "."),
            advisor.step(name, _blackout(run.blackout), then="."),
        ))  # fmt: skip
    if causes:  # not trusted anyway: thin rows are one more thing to mend
        causes, caveats = causes + caveats, []
    return Verdict(trust=not causes, causes=causes, caveats=caveats,
                   remedies=advisor.remedies, dropped=advisor.dropped)  # fmt: skip


def _blackout(advice: Sequence[str]) -> list[Remedy]:
    """The remedy of a collection whose rows lag a jump (none where they did not)."""
    if not advice:
        return []
    return [Remedy("blackout", f"rows recorded only once a jump has settled, `{' '.join(advice)}` "
                   f"(collect measured its rows soon after a jump switching at other rates than "
                   f"settled ones at the same inputs, and psi learns that lag; docs/choice.md)",
                   tuple(advice))]  # fmt: skip


def _sparse_rows(
    outside: Mapping[str, Mapping[str, Any] | None],
    outside_warning: float,
    n_per_state: int | None = None,
    advisor: Advisor | None = None,
    classes: CountClasses | None = None,
    shared: bool = False,
) -> tuple[str, str, str] | None:
    """The cause "Sparse training data" (``(name, what was measured, the next step)``) where
    any field's run spent more than ``outside_warning`` of its cell-steps inside the trained
    range in sparsely trained bins (its report's ``share_sparse``); None where none did.
    ``classes`` (bins of a count) and ``shared`` (the chain needs bins both lumps share): the
    coarser classes are advised as edges (:func:`~surrogate.diagnosis.remedies.coarser_classes`)."""
    advisor = advisor or Advisor(None, None)
    name = "Sparse training data"
    thin = {f: r for f, r in outside.items()
            if r and (sparse_share(r) or 0.0) > outside_warning}  # fmt: skip
    if not thin:
        return None
    parts = [f"{f}: {100 * float(r['share_sparse']):.1f} % of cell-steps, most at "
             f"{describe_sparse_where(r)} "
             f"({100 * float(r.get('sparse_where_share', 0.0)):.1f} %)"
             for f, r in thin.items()]  # fmt: skip
    design = Remedy("training_rows", "training rows there: a training field or a perturbation "
                    "design (`model.body.perturbation`) that reaches those inputs")  # fmt: skip
    if any(r.get("classes") for r in thin.values()):  # a K-lumps chain: checked per class
        return (
            name,
            "inside its trained range the K-lumps chain ran where its training rows of the "
            "cells' own class are sparse (fewer per class than a leaving rate within 20 % "
            "needs) in " + "; ".join(parts)
            + ": its law from that class there is the fit's guess between few of its rows.",
            advisor.step(name, [
                more_rows(n_per_state, "more rows ({more}: a rare class's rows grow in "
                           "proportion)"),
                coarser_remedy(classes, _first_sparse_class(thin), shared),
                design], then="."),
        )  # fmt: skip
    return (
        name,
        "inside its trained range the abstraction ran where its training rows are sparse "
        "(fewer per state than a switching rate within 20 % needs) in " + "; ".join(parts)
        + ": its psi there is the fit's guess between few rows.",
        advisor.step(name, [
            design, more_rows(n_per_state, "more rows ({more}), which fill them only in "
                               "proportion")], then="."),
    )  # fmt: skip


def _first_sparse_class(thin: Mapping[str, Mapping[str, Any]]) -> str | None:
    """The class of the most visited sparse region over the fields (their ``sparse_class``)."""
    named = [r for r in thin.values() if r.get("sparse_class") is not None]
    best = max(named, key=lambda r: float(r.get("sparse_where_share") or 0.0), default=None)
    return None if best is None else str(best["sparse_class"])


__all__ = [
    "BIAS_Z",
    "SETTLING_Z",
    "Verdict",
    "VerdictInputs",
    "unmeasured",
    "verdict",
]
