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
   still drifting from their start: the burn-in is too short.
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
   (``gp=clock``). Where the clock ran already, what was not tried (:func:`clock_step`): a
   longer clock (twice ``gp.max_age``), more transitions, and classes only where the memory is
   a slow count rather than a cycle's phase; never the setting in use.

None applying: every comparison is within the noise floor or the critical value at this
population size; trust it there and check at scale (``scripts/fidelity.py``).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

from surrogate.kinds import ChainKind
from surrogate.simulate.support import describe_sparse_where, sparse_share

#: |first half - second half| of the diagnostic's switching, in standard errors, above which
#: its population was still settling
SETTLING_Z = 4.0
#: a bias is significant above this many standard errors
BIAS_Z = 2.0


@dataclass
class Verdict:
    """The reading of a run's measurements.

    Attributes:
        trust: no cause applies: within the noise floor at this size.
        causes: each cause that applies: ``(name, what was measured, the next step)``.
        caveats: what to watch where it is trusted, as causes are written.
    """

    trust: bool
    causes: list[tuple[str, str, str]] = field(default_factory=list)
    caveats: list[tuple[str, str, str]] = field(default_factory=list)

    def markdown(self) -> str:
        """The verdict as report text."""
        if self.trust:
            return ("**Trust it at this size**: every comparison is within the full model's "
                    "noise floor or the KS critical value, the learned psi is unbiased where the "
                    "population lives within its error, and no run left the training data. "
                    "Small differences hide at small populations: confirm at scale with "
                    "`python3 scripts/fidelity.py` (thousands of cells, several training "
                    "seeds)." + "".join(f"\n\nCaveat, **{name}**: {measured} Where a check at "
                                        f"scale fails: {step}"
                                        for name, measured, step in self.caveats))  # fmt: skip
        lines = ["**Do not trust it yet.** In order (the first is the likeliest cause of the "
                 "others):", ""]  # fmt: skip
        for i, (name, measured, step) in enumerate(self.causes, 1):
            lines.append(f"{i}. **{name}**: {measured} Next: {step}")
        return "\n".join(lines)


def verdict(
    *,
    diagnostic: Mapping[str, Any] | None,
    lump_names: Sequence[str],
    failures: Mapping[str, Sequence[str]],
    outside: Mapping[str, Mapping[str, Any] | None],
    outside_warning: float,
    tolerance: float,
    kind: ChainKind,
    network: bool,
    n_per_state: int | None,
    class_shares: Mapping[str, Any] | None = None,
    max_age: float | None = None,
) -> Verdict:
    """Read the measurements (see the module docstring).

    Args:
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
    """
    causes: list[tuple[str, str, str]] = []
    away = {f: r for f, r in outside.items() if r and r["share_outside"] > outside_warning}
    if away:
        parts = []
        for f, r in away.items():
            inputs = [f"{n} seen [{v['seen'][0]:.3g}, {v['seen'][1]:.3g}] vs trained "
                      f"[{v['trained'][0]:.3g}, {v['trained'][1]:.3g}]"
                      for n, v in r["inputs"].items() if v["share_below"] or v["share_above"]]  # fmt: skip
            parts.append(
                f"{f}: {100 * r['share_outside']:.1f} % of cell-steps ({'; '.join(inputs)})"
            )
        causes.append((
            "Outside the training data",
            "the abstraction ran outside the inputs it was trained on in " + "; ".join(parts)
            + ", where its lookup clamps to the range's edge.",
            "collect transitions where these cells go: `collect.* field=<that field>`, or a "
            "wider collection (`model.body.perturbation.radius`, a field with that range).",
        ))  # fmt: skip
    failing = {f: list(q) for f, q in failures.items() if q}
    thin = _sparse_rows(outside, outside_warning)
    caveats: list[tuple[str, str, str]] = []
    if thin is not None:  # a cause where a comparison fails, else a caveat beside the trust
        (causes if failing else caveats).append(thin)
    d = diagnostic or {}
    scores = {p: d.get(f"phi{p}") for p in (0, 1)}
    settling = [(p, s["settling_z"]) for p, s in scores.items()
                if s and abs(s.get("settling_z") or 0.0) > SETTLING_Z]  # fmt: skip
    if settling:
        what = ", ".join(f"leaving {lump_names[p]}: {z:+.1f} standard errors"
                         for p, z in settling)  # fmt: skip
        causes.append((
            "Not settled",
            f"the full model's diagnostic population switched at different rates in the first "
            f"and second half of its run ({what}): its cells were still drifting from where they "
            f"started, so its transitions (and the collection's) are not those of settled cells.",
            "a longer burn-in (`model.burn_in`, where the model has one; `python3 "
            "scripts/inspect_model.py` measures the settling time), or a longer "
            "`equilibration_time`.",
        ))  # fmt: skip
    biased, noisy = [], []
    for p, s in scores.items():
        if not s or s.get("rel_bias") is None:
            continue
        se = s.get("rel_bias_se")
        bias = s["rel_bias"]
        if se is not None and se > tolerance:
            noisy.append(f"leaving {lump_names[p]}: {100 * bias:+.1f} % +- {100 * se:.1f} %")
        elif abs(bias) > tolerance and (se is None or abs(bias) > BIAS_Z * se):
            pred = s.get("predicted_duration_error") or (1 / (1 + bias) - 1)
            err = f"+- {100 * se:.1f} %" if se is not None else "(exact reference)"
            biased.append(f"leaving {lump_names[p]}: {100 * bias:+.1f} % {err}, which predicts "
                          f"{100 * pred:+.1f} % in the mean {lump_names[p]} duration")  # fmt: skip
    if biased:
        more = f"`collect.n_per_state={4 * n_per_state}`" if n_per_state else \
            "a larger `collect.n_per_state`"  # fmt: skip
        causes.append((
            "Biased switching probabilities",
            "where the population lives the learned psi is off: " + "; ".join(biased) + ".",
            f"more transitions ({more}: the bias of a GP fit falls with its data), and "
            "check `gp.epochs`/`gp.n_inducing` converged (the training history figure).",
        ))  # fmt: skip
    if noisy:
        causes.append((
            "A reference too noisy to judge",
            "the diagnostic's full-model reference cannot tell the learned psi's bias from "
            "none: " + "; ".join(noisy) + ".",
            "a larger diagnostic population (`gp.diagnostic.n_cells`, `gp.diagnostic.t_end`).",
        ))  # fmt: skip
    shares = class_shares or {}
    drift = kind.classes and bool(shares.get("drift"))
    if drift:
        more = f"`collect.n_per_state={4 * n_per_state}`" if n_per_state else \
            "a larger `collect.n_per_state`"  # fmt: skip
        step = (f"more transitions per class ({more}) or other classes (`model.classes`)"
                if kind.relaxation else
                "`gp.class_moves=relaxation` where the classes are bins of a slow count (the "
                "learned moves between bins, rare per window and mostly a count jittering "
                f"across an edge, mix them faster than the count moves), else {more}")  # fmt: skip
        causes.append((
            "Class shares drift",
            f"run as the diagnostic's full-model population was, the chain's classes after "
            f"{shares['t']:g} s are {100 * shares['total_variation']:.1f} % (total variation) "
            f"from the full model's, chi-square p = {shares['p_value']:.2g}: its moves between "
            "classes are off, whatever each class's switching.",
            step + ".",
        ))  # fmt: skip
    if failing and not biased and not away and thin is None and not drift:
        what = "; ".join(f"{f}: {', '.join(q)}" for f, q in failing.items())
        classes = ("`gp=classes` with `model.classes=auto` (or declared bins of the count "
                   "that holds the memory)" if network else
                   "`gp=classes` where the model declares classes")  # fmt: skip
        if kind.classes:
            step = ("more classes or other bins (`model.classes`), or more transitions per "
                    "class (`collect.n_per_state`).")  # fmt: skip
        elif kind.clock:
            step = clock_step(max_age, n_per_state, classes)
        else:
            step = f"classes finer than phi, {classes}, or the switch clock `gp=clock`."
        causes.append((
            "Memory the chain over phi does not hold",
            f"the runs differ from the full model beyond its noise floor ({what}) while the "
            "learned switching probabilities match the full model's where the population "
            "lives: what phi alone forgets (the network's hidden state) shapes the runs.",
            step,
        ))  # fmt: skip
    if causes:  # not trusted anyway: thin rows are one more thing to mend
        causes, caveats = causes + caveats, []
    return Verdict(trust=not causes, causes=causes, caveats=caveats)


def _sparse_rows(
    outside: Mapping[str, Mapping[str, Any] | None], outside_warning: float
) -> tuple[str, str, str] | None:
    """The cause "Sparse training data" (``(name, what was measured, the next step)``) where
    any field's run spent more than ``outside_warning`` of its cell-steps inside the trained
    range in sparsely trained bins (its report's ``share_sparse``); None where none did."""
    thin = {f: r for f, r in outside.items()
            if r and (sparse_share(r) or 0.0) > outside_warning}  # fmt: skip
    if not thin:
        return None
    parts = [f"{f}: {100 * float(r['share_sparse']):.1f} % of cell-steps, most at "
             f"{describe_sparse_where(r)} "
             f"({100 * float(r.get('sparse_where_share', 0.0)):.1f} %)"
             for f, r in thin.items()]  # fmt: skip
    if any(r.get("classes") for r in thin.values()):  # a K-lumps chain: checked per class
        return (
            "Sparse training data",
            "inside its trained range the K-lumps chain ran where its training rows of the "
            "cells' own class are sparse (fewer per class than a leaving rate within 20 % "
            "needs) in " + "; ".join(parts)
            + ": its law from that class there is the fit's guess between few of its rows.",
            "more rows (`collect.n_per_state`: a rare class's rows grow in proportion) or "
            "coarser classes (`model.classes`: fewer, wider bins), or training rows there: a "
            "training field or a perturbation design (`model.body.perturbation`) that reaches "
            "those inputs.",
        )  # fmt: skip
    return (
        "Sparse training data",
        "inside its trained range the abstraction ran where its training rows are sparse "
        "(fewer per state than a switching rate within 20 % needs) in " + "; ".join(parts)
        + ": its psi there is the fit's guess between few rows.",
        "training rows there: a training field or a perturbation design "
        "(`model.body.perturbation`) that reaches those inputs; more rows "
        "(`collect.n_per_state`) fill them only in proportion.",
    )  # fmt: skip


def clock_step(max_age: float | None, n_per_state: int | None, classes: str) -> str:
    """The next step for a chain with a switch clock (``gp=clock``) whose runs differ from the
    full model while its psi is unbiased where the population lives: what was not tried, not
    the clock again. A longer clock first (ages beyond ``gp.max_age`` are clamped to it, so
    memory that outlasts the cap is lost), then more transitions (the clock's psi is over one
    input more, the age, and each age bin sees a share of the rows: on the toggle switch the
    clock needed more data than the two-state chain, docs/fidelity.md); classes only where the
    memory is a slow count, not a cycle's phase (on Tyson's oscillator classes over its
    threshold's count did worse than the two-state chain, docs/sbml.md)."""
    longer = (f"`gp.max_age={2 * max_age:g}` (twice the `gp.max_age={max_age:g}` that ran)"
              if max_age is not None else "a larger `gp.max_age`")  # fmt: skip
    more = f"`collect.n_per_state={4 * n_per_state}`" if n_per_state else \
        "a larger `collect.n_per_state`"  # fmt: skip
    return (
        f"the switch clock is on already; first a longer clock, {longer}: an age beyond the "
        f"cap is clamped to it, so memory that outlasts it is lost (`python3 "
        f"scripts/inspect_model.py` gives the age where the hazard flattens and, for an "
        f"oscillating lump, the period); then more transitions ({more}): the clock's psi is "
        f"over the age as well, and each age sees a share of the rows. Classes ({classes}) "
        f"only where the memory is a slow count rather than a cycle's phase (the inspector "
        f"says which): bins of a count do not hold where a cycle is, and on an oscillator "
        f"they did worse than the two-state chain (docs/sbml.md)."
    )


__all__ = ["BIAS_Z", "SETTLING_Z", "Verdict", "clock_step", "verdict"]
