"""The report's reading of a run: trust it, or which cause applies and which setting to try."""

from __future__ import annotations

from typing import Any

import pytest

from surrogate.diagnosis.advice import VerdictInputs, verdict
from surrogate.diagnosis.remedies import Advisor, MeasuredChoice, Remedy, candidate_overrides
from surrogate.kinds import chain_kind
from surrogate.kinds.scoring import candidate_cap


def _score(bias: float, se: float | None = 0.01, settling: float = 0.0) -> dict[str, Any]:
    return {"rel_bias": bias, "rel_bias_se": se, "settling_z": settling,
            "predicted_duration_error": 1 / (1 + bias) - 1}  # fmt: skip


def _outside(share: float) -> dict[str, Any]:
    return {"share_outside": share, "sampled_cell_steps": 1000,
            "inputs": {"L": {"share_below": 0.0, "share_above": share, "seen": [0.0, 0.5],
                             "trained": [0.0, 0.1]}}}  # fmt: skip


def _args(lumps: str = "phi", history: str = "none", class_moves: str = "learned") -> dict:
    """A run of the chain the config's strings name, within noise and unbiased."""
    return {
        "diagnostic": {"reference": "empirical", "phi0": _score(0.0), "phi1": _score(0.005)},
        "lump_names": ("off", "on"), "failures": {"gaussian": []},
        "outside": {"gaussian": _outside(0.0)}, "outside_warning": 0.01, "tolerance": 0.03,
        "kind": chain_kind(lumps, history, class_moves), "network": True, "n_per_state": 10_000,
    }  # fmt: skip


def _read(lumps: str = "phi", history: str = "none", class_moves: str = "learned",
          **changes: Any):  # fmt: skip
    """The verdict of a run of the chain the config's strings name (gp.lumps, gp.history,
    gp.class_moves), with ``changes`` to the measurements."""
    args = _args(lumps, history, class_moves)
    if isinstance(changes.get("diagnostic"), dict):  # the scores given replace the default's
        changes["diagnostic"] = {**args["diagnostic"], **changes["diagnostic"]}
    return verdict(VerdictInputs(**{**args, **changes}))


def test_within_noise_and_unbiased_is_trusted() -> None:
    v = _read()
    assert v.trust and not v.causes
    assert "Trust it at this size" in v.markdown() and "fidelity.py" in v.markdown()


def test_a_bias_within_its_error_or_the_tolerance_is_no_cause() -> None:
    assert _read(diagnostic={"phi0": _score(0.05, se=0.03)}).trust  # within two errors
    assert _read(diagnostic={"phi0": _score(0.02, se=0.001)}).trust  # within the tolerance


def test_each_cause_names_its_measurement_and_next_step() -> None:
    away = _read(outside={"gaussian": _outside(0.2)})
    assert [c[0] for c in away.causes] == ["Outside the training data"]
    assert "20.0 % of cell-steps" in away.causes[0][1] and "L seen [0, 0.5]" in away.causes[0][1]
    assert [r.kind for _, r in away.remedies] == ["training_field"]  # the model names no radius
    wider = ("++model.body.perturbation.radius=6",)
    further = _read(outside={"gaussian": _outside(0.2)}, wider_collection=wider)
    assert [r.overrides for _, r in further.remedies] == [wider, ()]
    assert "`++model.body.perturbation.radius=6`" in further.causes[0][2]
    refused = verdict(VerdictInputs(**{**_args(), "outside": {"gaussian": _outside(0.2)},
                                       "wider_collection": wider}),
                      check=lambda overrides, what: "no such key")  # fmt: skip
    assert [r.kind for _, r in refused.remedies] == ["training_field"]
    assert "not advised: ++model.body.perturbation.radius=6 (no such key)" in refused.causes[0][2]
    drifting = _read(diagnostic={"phi0": _score(0.0, settling=-6.0)})
    assert drifting.causes[0][0] == "Not settled" and "model.burn_in" in drifting.causes[0][2]
    assert [r.overrides for _, r in drifting.remedies] == [(), ()]  # no span: no value
    later = _read(diagnostic={"phi0": _score(0.0, settling=-6.0)}, diagnostic_span=(10.0, 100.0))
    assert [r.overrides for _, r in later.remedies] == [
        ("gp.diagnostic.equilibration_time=60",), ()]  # fmt: skip
    assert "`gp.diagnostic.equilibration_time=60` (now 10 s; its first 50 s" in later.causes[0][2]
    # a simulated burn-in: one that ends where the drift did (it printed no value before)
    burned = _read(diagnostic={"phi0": _score(0.0, settling=-6.0)}, diagnostic_span=(10.0, 100.0),
                   burn_in=50.0)  # fmt: skip
    assert [r.overrides for _, r in burned.remedies][1] == ("++model.burn_in=110",)
    assert "`++model.burn_in=110` (now 50 s: the diagnostic's cells still drifted 60 s" \
        in burned.causes[0][2]  # fmt: skip
    biased = _read(diagnostic={"phi0": _score(0.15, se=0.02)})
    (cause,) = biased.causes
    assert cause[0] == "Biased switching probabilities"
    assert "+15.0 % +- 2.0 %" in cause[1] and "-13.0 % in the mean off duration" in cause[1]
    assert "collect.n_per_state=40000" in cause[2]
    noisy = _read(diagnostic={"phi0": _score(0.15, se=0.1)})
    assert noisy.causes[0][0] == "A reference too noisy to judge"
    assert "gp.diagnostic.n_cells" in noisy.causes[0][2]
    # with the diagnostic's size known, a value: its error over the root of its cells, under
    # the tolerance with a margin (10 % at 1,000 cells: 1000 x 1.5 x (0.1 / 0.03)^2)
    sized = _read(diagnostic={"phi0": _score(0.15, se=0.1)}, diagnostic_cells=1000)
    assert [r.overrides for _, r in sized.remedies] == [("gp.diagnostic.n_cells=16700",)]
    assert "`gp.diagnostic.n_cells=16700` (now 1000" in sized.causes[0][2]


def test_failing_runs_with_an_unbiased_psi_point_to_memory() -> None:
    memory = _read(failures={"gaussian": ["on_fraction_t100", "off"]})
    (cause,) = memory.causes
    assert cause[0] == "Memory the chain over phi does not hold"
    assert "gaussian: on_fraction_t100, off" in cause[1]
    assert "model.classes=auto" in cause[2] and "gp=clock" in cause[2]
    python_model = _read(failures={"gaussian": ["off"]}, network=False)
    assert "model.classes=auto" not in python_model.causes[0][2]
    classes = _read(failures={"gaussian": ["off"]}, lumps="classes")
    assert "model.classes" in classes.causes[0][2] and "gp=clock" not in classes.causes[0][2]
    # a biased psi explains failing runs by itself: memory is not claimed then
    both = _read(failures={"gaussian": ["off"]}, diagnostic={"phi0": _score(0.2, se=0.02)})
    assert [c[0] for c in both.causes] == ["Biased switching probabilities"]
    assert "Do not trust it yet" in both.markdown()


def test_drifting_class_shares_point_to_relaxation_then_to_more_data() -> None:
    """A K-lumps chain whose class shares drift: the cause names the total variation and the
    test's p, and the next step is bins that relax (learned moves) or more transitions per
    class (relaxation already on); the memory cause is not added on top, and a two-state chain
    ignores class shares."""
    shares = {"t": 100.0, "total_variation": 0.12, "p_value": 1e-9, "drift": True}
    failing = {"gaussian": ["mean_low"]}
    v = _read(lumps="classes", class_shares=shares, failures=failing)
    names = [c[0] for c in v.causes]
    assert names == ["Class shares drift"]
    assert "12.0 %" in v.causes[0][1] and "p = 1e-09" in v.causes[0][1]
    assert "gp.class_moves=relaxation" in v.causes[0][2]
    relaxed = _read(lumps="classes", class_shares=shares, class_moves="relaxation")
    assert "collect.n_per_state=40000" in relaxed.causes[0][2]
    assert "relaxation" not in relaxed.causes[0][2].split("(")[0]
    assert _read(lumps="phi", class_shares=shares).trust
    assert _read(lumps="classes", class_shares={**shares, "drift": False}).trust


def test_a_failing_clock_is_told_what_was_not_tried() -> None:
    """A chain with the switch clock on (an oscillator's advice) whose runs fail with an
    unbiased psi: the next step is a longer clock (twice the cap that ran) and more
    transitions, classes only with the reason they may not help; never the clock itself."""
    clock = _read(failures={"gaussian": ["off"]}, history="age", max_age=3.5)
    (cause,) = clock.causes
    step = cause[2]
    assert "gp.max_age=7" in step and "gp.max_age=3.5" in step
    assert "collect.n_per_state=40000" in step
    assert "`gp=clock`" not in step and "try classes" not in step
    assert step.index("gp.max_age=7") < step.index("gp=classes")  # classes last, with a reason
    assert "cycle's phase" in step
    # without a clock, the clock is still offered
    assert "`gp=clock`" in _read(failures={"gaussian": ["off"]}).causes[0][2]


def _row(kind: str, complexity: int, gap: float, se: float = 2e-5, tied: bool = False,
         holds: bool = True) -> dict[str, Any]:  # fmt: skip
    """A row of a measured choice's table (the log-likelihood the gap from a best at -0.345)."""
    return {"kind": kind, "complexity": complexity, "log_likelihood_per_window": -0.345 + gap,
            "diff_from_best": gap, "diff_se": se, "tied_with_best": tied,
            "holds_durations": holds}  # fmt: skip


def _choice(chosen: str, rows: list[dict[str, Any]], **changes: Any) -> MeasuredChoice:
    base = {"kinds": ("two-state", "clock", "classes", "phases"), "max_ages": (1.0, 2.0, 5.0),
            "n_cells": 1000, "tie_se": 1.0, "classes": False}  # fmt: skip
    return MeasuredChoice(chosen, tuple(rows), **{**base, **changes})


def test_memory_under_a_measured_choice_widens_the_choice_not_a_kind() -> None:
    """gp=auto chose the clock at its largest cap: the memory remedy widens the caps and the
    families left out, names no kind but the runner-up with more memory (with its standing),
    and never doubles gp.max_age (which, under gp=auto, set every clock candidate's cap alike)."""
    rows = [_row("two-state", 0, -4e-4), _row("clock max_age=1", 1, -1e-4),
            _row("clock max_age=5", 1, 0.0), _row("phases", 3, -8e-5, holds=False)]  # fmt: skip
    choice = _choice("clock max_age=5", rows, kinds=("two-state", "clock", "phases"))
    v = _read(failures={"gaussian": ["off"]}, history="age", max_age=5.0, choice=choice)
    (cause,) = v.causes
    kinds = [r.kind for _, r in v.remedies]
    assert kinds == ["wider_caps", "wider_kinds", "more_rows", "runner_up"]
    overrides = {r.kind: r.overrides for _, r in v.remedies}
    assert overrides["wider_caps"] == ("gp.choice.max_ages=[1,2,5,10]",)
    assert overrides["wider_kinds"] == ("gp.choice.kinds=[two-state,clock,phases,classes]",
                                        "++model.classes=auto")  # fmt: skip
    # a thinned collection: K lumps over a network's chosen classes with every move kept
    thinned = _read(failures={"gaussian": ["off"]}, history="age", max_age=5.0,
                    choice=_choice("clock max_age=5", rows, kinds=("two-state", "clock", "phases"),
                                   thinned=True))  # fmt: skip
    wider = next(r for _, r in thinned.remedies if r.kind == "wider_kinds")
    assert wider.overrides[1:] == ("++model.classes=auto", "collect.keep_switches=true")
    assert "`collect.keep_switches=true` keeps every move" in wider.text
    assert overrides["runner_up"] == ("gp=phases",)
    assert "phases, was 4.0 SE below the best" in cause[2] and "did not hold" in cause[2]
    assert "gp.max_age=10" not in cause[2] and "`gp=clock`" not in cause[2]
    # the named chain (no choice): today's remedy, the cap doubled
    named = _read(failures={"gaussian": ["off"]}, history="age", max_age=5.0)
    assert named.remedies[0][1].kind == "longer_clock"


def test_a_tie_asks_for_more_held_out_cells_and_no_wider_cap_below_the_largest() -> None:
    """Two-state chosen as the simplest of a tie: four times the held-out cells; no longer cap
    (the clock did not win at its largest), every family already a candidate, and a model
    that declares classes (K lumps were a candidate) is not told model.classes=auto; the
    runner-up is the best with more memory that holds its durations, whatever its likelihood."""
    rows = [_row("two-state", 0, -1e-5, tied=True), _row("clock max_age=1", 1, 0.0, tied=True),
            _row("classes", 2, 5e-5, holds=False), _row("clock max_age=5", 1, -2e-4)]  # fmt: skip
    choice = _choice("two-state", rows, classes=True)
    v = _read(failures={"gaussian": ["off"]}, choice=choice)
    overrides = {r.kind: r.overrides for _, r in v.remedies}
    assert list(overrides) == ["more_cells", "more_rows", "runner_up"]
    assert overrides["more_cells"] == ("gp.choice.n_cells=4000",)
    assert overrides["runner_up"] == ("gp=clock", "gp.max_age=1")
    step = v.causes[0][2]
    assert "tie within 1 SE between two-state (chosen) and clock max_age=1" in step
    assert "clock max_age=1, had the highest held-out log-likelihood:" in step
    # a model that is no network and declares no classes: K lumps cannot join
    plain = _read(failures={"gaussian": ["off"]}, network=False,
                  choice=_choice("two-state", rows[:1], kinds=("two-state",)))  # fmt: skip
    widened = plain.remedies[0][1].overrides
    assert widened == ("gp.choice.kinds=[two-state,clock,phases]",)


def test_a_choice_where_none_held_is_a_caveat_beside_the_trust() -> None:
    """Runs within noise from a chain the choice took as the closest where no candidate held
    its durations: trusted, with a caveat naming the chosen's farthest lump and the choice's
    remedies (each checked as any remedy); a choice where one held, or a record without the
    tolerance, adds none; failing runs fold it into the causes, and the memory cause, which
    gives the same remedies, leaves it out."""

    def row(kind: str, complexity: int, gap: float, few: float, many: float) -> dict[str, Any]:
        return {**_row(kind, complexity, gap, holds=False),
                "few_mean_rel_diff": few, "many_mean_rel_diff": many}  # fmt: skip

    rows = [row("two-state", 0, -2e-2, 0.004, 0.067), row("clock max_age=5", 1, -8e-4, -0.034,
            0.003), row("classes", 2, 0.0, 0.011, 0.068)]  # fmt: skip
    choice = _choice("clock max_age=5", rows, classes=True, duration_tolerance=0.03)
    assert choice.none_held() == ("few", -0.034)
    v = _read(history="age", max_age=5.0, choice=choice)
    assert v.trust and [c[0] for c in v.caveats] == ["No candidate held its durations"]
    name, measured, step = v.caveats[0]
    assert "within 3%" in measured
    assert "clock max_age=5, chosen as the closest, was -3.4 % on few" in measured
    assert "gp.choice.max_ages=[1,2,5,10]" in step and "collect.n_per_state=40000" in step
    assert {r.kind for c, r in v.remedies if c == name} >= {"wider_caps", "more_rows"}
    assert "Caveat, **No candidate held its durations**" in v.markdown()
    refused = verdict(VerdictInputs(**{**_args("phi", "age"), "max_age": 5.0, "choice": choice}),
                      check=lambda overrides, what: "refused here")  # fmt: skip
    assert "not advised: gp.choice.max_ages=[1,2,5,10] (refused here)" in refused.caveats[0][2]
    held = [{**rows[0], "holds_durations": True}, *rows[1:]]
    assert _read(choice=_choice("two-state", held, duration_tolerance=0.03)).caveats == []
    assert _read(choice=_choice("clock max_age=5", rows)).caveats == []  # tolerance unknown
    biased = _read(choice=choice, diagnostic={"phi0": _score(0.2, se=0.02)})
    assert [c[0] for c in biased.causes] == ["Biased switching probabilities",
                                             "No candidate held its durations"]  # fmt: skip
    # more rows, advised under the bias, is printed once: the caveat's step points to it
    assert "collect.n_per_state=40000" in biased.causes[0][2]
    assert "[also `collect.n_per_state=40000`, advised above under \"Biased switching " \
        "probabilities\"]" in biased.causes[1][2]  # fmt: skip
    assert [c for c, r in biased.remedies if r.kind == "more_rows"] == [
        "Biased switching probabilities"]  # fmt: skip
    memory = _read(failures={"gaussian": ["off"]}, history="age", max_age=5.0, choice=choice)
    assert [c[0] for c in memory.causes] == ["Memory the chain over phi does not hold"]


def test_a_lagging_collection_is_a_caveat_beside_the_trust() -> None:
    """Runs within noise and psi unbiased, but collect measured its rows lagging their jumps:
    trusted, with a caveat naming the blackout collect advised (checked as any remedy); where
    psi is biased the blackout is that cause's first remedy instead, printed once; no caveat
    where nothing lagged. The chosen psi may read the clock while the candidates that read
    none learned the lag (CERENA's gene-expression network, docs/choice.md)."""
    blackout = ("collect.blackout_time=20", "collect.perturb_rate=0.025")
    v = _read(history="age", max_age=2.0, blackout=blackout)
    assert v.trust and [c[0] for c in v.caveats] == ["Rows that lag their jumps"]
    assert f"`{' '.join(blackout)}`" in v.caveats[0][2]
    assert [r.overrides for _, r in v.remedies] == [blackout]
    assert "Caveat, **Rows that lag their jumps**" in v.markdown()
    assert v.caveats[0][1].endswith("a psi that reads no clock learns that lag.")  # named
    rows = [_row("two-state", 0, -2e-2), _row("clock max_age=2", 1, 0.0)]
    chosen = _read(history="age", max_age=2.0, blackout=blackout,
                   choice=_choice("clock max_age=2", rows, duration_tolerance=0.03))  # fmt: skip
    assert chosen.caveats[0][1].endswith("the chain was chosen among candidates that do.")
    refused = verdict(VerdictInputs(**{**_args("phi", "age"), "max_age": 2.0,
                                       "blackout": blackout}),
                      check=lambda overrides, what: "refused here")  # fmt: skip
    assert refused.trust and "not advised: " + " ".join(blackout) in refused.caveats[0][2]
    biased = _read(blackout=blackout, diagnostic={"phi0": _score(0.2, se=0.02)})
    assert [c[0] for c in biased.causes] == ["Biased switching probabilities"]
    assert biased.remedies[0][1].overrides == blackout
    assert _read(history="age", max_age=2.0).caveats == []


def test_the_runner_up_is_named_by_its_rows_overrides_a_log_clock_only_so() -> None:
    """A candidate's name cannot say a log clock's knee and bins: the runner-up is named by
    the overrides its row records (what the choice trained it with); from a record without
    them a log clock is not offered (`gp=clock log max_age=20` cannot run), and its cap still
    reads as memory (twice the clock at 10 s's)."""
    log_clock = "gp=clock gp.max_age=20 gp.clock_knee=0.25 gp.clock_bins=63"
    rows = [_row("two-state", 0, -4e-4), _row("clock max_age=10", 1, 0.0),
            {**_row("clock log max_age=20", 1, -1e-4), "overrides": log_clock}]  # fmt: skip
    choice = _choice("clock max_age=10", rows, max_ages=(1.0, 2.0, 5.0, 10.0))
    v = _read(failures={"gaussian": ["off"]}, history="age", max_age=10.0, choice=choice)
    overrides = {r.kind: r.overrides for _, r in v.remedies}
    assert overrides["runner_up"] == tuple(log_clock.split())
    bare = [*rows[:2], _row("clock log max_age=20", 1, -1e-4)]
    v = _read(failures={"gaussian": ["off"]}, history="age", max_age=10.0,
              choice=_choice("clock max_age=10", bare, max_ages=(1.0, 2.0, 5.0, 10.0)))  # fmt: skip
    assert "runner_up" not in [r.kind for _, r in v.remedies]
    assert candidate_cap("clock log max_age=20") == 20.0 and candidate_cap("classes") is None
    with pytest.raises(ValueError, match="knee and bins"):
        candidate_overrides("clock log max_age=20")


def test_a_remedy_advised_under_an_earlier_cause_is_printed_once() -> None:
    """The same remedy under a second cause points to the first instead of being printed
    again; a step left with nothing new says so, not that nothing runs; a refused one is still
    named as refused."""
    advisor = Advisor(check=lambda overrides, what: "refused" if "gp=x" in overrides else None,
                      tried=None)  # fmt: skip
    rows = Remedy(
        "more_rows", "more rows (`collect.n_per_state=400`)", ("collect.n_per_state=400",)
    )
    first = advisor.step("Bias", [rows])
    assert first == "more rows (`collect.n_per_state=400`)"
    second = advisor.step("Memory", [rows])
    assert second == ('the remedies advised above [also `collect.n_per_state=400`, advised above '
                      'under "Bias"]')  # fmt: skip
    third = advisor.step("Other", [rows, Remedy("x", "x", ("gp=x",))])
    assert third.startswith("the remedies advised above") and "not advised: gp=x (refused)" in third
    assert [c for c, _ in advisor.remedies] == ["Bias"]
    assert advisor.step("Bias", [rows]) == first  # the same cause again: printed as before
