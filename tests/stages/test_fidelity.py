"""The fidelity stage's checks and report on synthetic runs (no training or simulation): the
second full run is the noise floor, not a candidate, and the exact psi is described as what it
is (the psi of cells adapted to their current input)."""

from __future__ import annotations

import numpy as np
import pytest

from surrogate.errors import ConfigError
from surrogate.stages import fidelity
from surrogate.stages.fidelity import RunResult

SMALL = [
    "collect.n_per_state=200",
    "collect.n_cells=50",
    "gp.n_inducing=10",
    "fidelity.train_seeds=[0]",
    "fidelity.fields=[gaussian]",
    "fidelity.n_cells=200",
    "fidelity.t_end=2.0",
    "gp=svgp",
]  # fmt: skip  (two-state: one exact chain, psi's)


def _run(rng: np.random.Generator, times: tuple[float, ...], shift: float) -> RunResult:
    return RunResult(
        observables={t: rng.normal(2.0 + shift, 0.5, 200) for t in times},
        mean_durations={"tumble": 0.1 * (1 + shift), "run": 1.0 * (1 + shift)},
        segments={"tumble": 500, "run": 500},
    )


@pytest.fixture
def checked(compose_cfg):
    settings = fidelity.validate(compose_cfg("fidelity", SMALL))
    (candidate,) = settings.candidates
    rng = np.random.default_rng(0)
    results = {
        "full|gaussian": _run(rng, settings.times, 0.0),
        "full_repeat|gaussian": _run(rng, settings.times, 0.0),
        "exact|gaussian": _run(rng, settings.times, 0.0),
        f"{candidate.label}|gaussian": _run(rng, settings.times, 0.5),  # far off: fails
    }
    table = fidelity.check(settings, results)
    return settings, results, table


def test_the_second_full_run_is_the_floor_not_a_candidate(checked) -> None:
    """Compared with itself as the floor, the second full run's checks could not fail: it is
    no row of the table, only every row's noise floor."""
    settings, results, table = checked
    (candidate,) = settings.candidates
    assert set(table["candidate"]) == {"exact", candidate.label}
    full, repeat = results["full|gaussian"], results["full_repeat|gaussian"]
    from scipy import stats

    for t in settings.times:
        rows = table[table["quantity"] == f"distance_t{t:g}"]
        floor = stats.ks_2samp(repeat.observables[t], full.observables[t]).statistic
        assert np.allclose(rows["noise_floor"], floor)
    learned = table[table["candidate"] == candidate.label]
    assert not learned["passed"].any()  # a shifted candidate fails every check
    summary = fidelity.summarise(table, settings)
    assert summary["checks"] == len(learned) and summary["passed"] == 0
    assert set(summary["by_candidate"]) == {"exact", candidate.label}


def test_the_report_calls_the_exact_psi_the_adapted_cells_psi(checked) -> None:
    settings, _, table = checked
    summary = fidelity.summarise(table, settings)
    text = "\n".join(body for _, body in fidelity.report_sections(table, summary, settings))
    assert "full_repeat" not in text
    assert "adapted to their current input" in text and "best" not in text
    # the chance failures: alpha x the learned candidates' KS checks (the references' excluded)
    learned = table[~table["candidate"].isin(fidelity.REFERENCES)]
    n_ks = int(learned["quantity"].str.startswith("distance_t").sum())
    assert f"up to {0.05 * n_ks:.1f} of these {n_ks} KS checks by chance" in text
    # each mean's error beside the two full runs' own difference (the floor), as each KS's
    assert "+50.0 % (+0.0 %) ✗" in text
    fig = fidelity.plot_ks(table, settings)
    labels = fig.axes[0].get_legend_handles_labels()[1]
    assert labels[0] == "noise floor" and "full_repeat" not in labels
    # the previous check of the model (surrogate/stages/check_history.py), where one exists
    assert "The previous check" not in text
    summary[fidelity.PREVIOUS] = {"directory": "model=m-a", "passed": 1, "checks": 4,
                                  "followed": [["gp.x=1"]], "now": 0, "fewer": True}  # fmt: skip
    text = "\n".join(body for _, body in fidelity.report_sections(table, summary, settings))
    assert "The previous check of this model at this size (`model=m-a`) passed 1 of 4" in text


def test_a_mean_just_past_the_tolerance_is_not_printed_as_the_tolerance() -> None:
    """A -3.04 % miss of a 3 % check printed "-3.0 % ✗"; one decimal more where one decimal
    would print the tolerance, one decimal elsewhere."""
    assert fidelity._percent(-0.0304, 0.03) == "-3.04"
    assert fidelity._percent(0.0296, 0.03) == "+2.96"
    assert fidelity._percent(-0.0314, 0.03) == "-3.1"
    assert fidelity._percent(0.5, 0.03) == "+50.0"


def test_the_report_says_a_mean_is_held_to_the_tolerance_whatever_its_floor(checked) -> None:
    """The mean check does not widen with its floor (the KS checks do): the report says so."""
    settings, _, table = checked
    summary = fidelity.summarise(table, settings)
    text = "\n".join(body for _, body in fidelity.report_sections(table, summary, settings))
    tol = 100 * float(settings.options["duration_tolerance"])
    assert f"a mean is held to {tol:g} % whatever its floor" in text
    assert set(table.loc[table["quantity"].str.startswith("mean_"), "threshold"]) == {tol / 100}


def test_a_clocked_recipe_is_checked_beside_the_exact_clock_which_is_a_reference(
    compose_cfg,
) -> None:
    """gp.history=age: the exact psi with a clock joins the table as a reference (like `exact`,
    not counted in the learned abstractions' checks), and the drift figure draws every run."""
    settings = fidelity.validate(compose_cfg("fidelity", [*SMALL, "gp=clock"]))
    (candidate,) = settings.candidates
    assert candidate.train.inputs == ("dG", "phi_age") and settings.exact_clocks
    rng = np.random.default_rng(0)
    labels = ["full", "full_repeat", "exact", fidelity.EXACT_CLOCK, candidate.label]
    results = {f"{k}|gaussian": _run(rng, settings.times, 0.0) for k in labels}
    table = fidelity.check(settings, results)
    summary = fidelity.summarise(table, settings)
    learned = table[table["candidate"] == candidate.label]
    assert set(table["candidate"]) == {"exact", fidelity.EXACT_CLOCK, candidate.label}
    assert summary["checks"] == len(learned)
    means = {f"{k}|gaussian": {f"{t:g}": [2.0, 0.01] for t in settings.times} for k in labels}
    fig = fidelity.plot_drift(means, settings)
    (ax,) = fig.axes
    assert len(ax.lines) == len(labels)  # the full model (the zero line), its repeat, 3 candidates


def test_paired_starts_are_a_setting_with_its_own_identity(compose_cfg) -> None:
    """fidelity.starts: independent keeps the identity of checks made before the key; paired
    is another check; a bad value and paired with stored references are refused by name."""
    plain = fidelity.validate(compose_cfg("fidelity", SMALL))
    named = fidelity.validate(compose_cfg("fidelity", [*SMALL, "fidelity.starts=independent"]))
    paired = fidelity.validate(compose_cfg("fidelity", [*SMALL, "fidelity.starts=paired"]))
    assert "starts" not in plain.identity()["fidelity"]
    assert named.directory == plain.directory != paired.directory
    with pytest.raises(ConfigError, match=r"fidelity.starts must be one of \['independent'"):
        fidelity.validate(compose_cfg("fidelity", [*SMALL, "fidelity.starts=shared"]))
    with pytest.raises(ConfigError, match=r"fidelity.starts=paired needs .*fidelity.reference=run"):
        fidelity.validate(compose_cfg("fidelity", [*SMALL, "fidelity.starts=paired",
                                                   "fidelity.reference=stored"]))  # fmt: skip


def test_runs_outside_their_collection_get_a_wider_one_checked(compose_cfg, checked) -> None:
    """A learned run above ``outside_warning`` outside its trained inputs: the report names
    the same command with collect's jumps twice as far (E. coli's ``model.perturbation``),
    checked by this stage's settings; none where every run stayed inside, or where the check
    refuses it (here `fidelity.reference=stored` with none stored: logged, not printed)."""
    from surrogate.config import to_dict

    settings, _, table = checked
    config = to_dict(compose_cfg("fidelity", SMALL))
    radius = float(settings.setup.model.perturbation_options["radius"])
    away = {"share_outside": 0.5, "inputs": {}}
    inside = {"share_outside": 0.0, "inputs": {}}
    wider = fidelity.wider_collection(settings, {"a|exponential": away, "a|gaussian": inside},
                                      config)  # fmt: skip
    assert wider == [f"++model.perturbation.radius={2 * radius:g}"]
    assert fidelity.wider_collection(settings, {"a|gaussian": inside}, config) is None
    summary = {**fidelity.summarise(table, settings), "wider_collection": wider,
               "outside_training": {"a|exponential": away}}  # fmt: skip
    text = "\n".join(body for _, body in fidelity.report_sections(table, summary, settings))
    assert f"the same command with `{wider[0]}` (checked)" in text
    stored = {**config, "fidelity": {**config["fidelity"], "reference": "stored"}}
    assert fidelity.wider_collection(settings, {"a|exponential": away}, stored) is None


def test_failed_checks_on_a_lagging_collection_get_its_blackout_checked(
    compose_cfg, checked, monkeypatch
) -> None:
    """A check failed and the candidate's collection lagged its jumps (the blackout collect
    advised, read from its manifest): the report names the same command with that blackout,
    checked by this stage's settings; none where every check passed, no collection lagged, or
    the check refuses it (a negative blackout here: logged, not printed)."""
    from surrogate.config import to_dict
    from surrogate.stages import reproduce

    settings, _, table = checked
    config = to_dict(compose_cfg("fidelity", SMALL))
    summary = fidelity.summarise(table, settings)
    assert summary["passed"] < summary["checks"]
    advice = ["collect.blackout_time=20", "collect.perturb_rate=0.025"]
    monkeypatch.setattr(reproduce, "collection_blackout", lambda tr, **_: tuple(advice))
    assert fidelity.settled_collection(settings, summary, config) == advice
    passed = {**summary, "passed": summary["checks"]}
    assert fidelity.settled_collection(settings, passed, config) is None
    text = "\n".join(body for _, body in fidelity.report_sections(
        table, {**summary, "settled_collection": advice}, settings))  # fmt: skip
    assert f"the same command with `{' '.join(advice)}` (checked)" in text
    assert "psi learns that lag" in text
    # fits that left the lagging rows out (gp.jump_rows): the blackout records more of them
    text = "\n".join(body for _, body in fidelity.report_sections(
        table, {**summary, "settled_collection": advice, "settled_kept": 0.16}, settings))  # fmt: skip
    assert "reading 16% of the rows" in text and "as many as the collection asks" in text
    assert "psi learns that lag" not in text
    monkeypatch.setattr(
        reproduce, "collection_blackout", lambda tr, **_: ("collect.blackout_time=-1",)
    )
    assert fidelity.settled_collection(settings, summary, config) is None
    monkeypatch.setattr(reproduce, "collection_blackout", lambda tr, **_: ())
    assert fidelity.settled_collection(settings, summary, config) is None


def test_a_training_seeds_chains_are_its_own_wherever_it_is_listed(compose_cfg) -> None:
    """Abstraction chains are keyed by training seed (and input choice), not by position: seed
    1 draws sim_seed + 3 x offset + 1 alone, first or second, and the report names the seeds."""
    base = [s for s in SMALL if not s.startswith("fidelity.train_seeds")]
    streams = {}
    for seeds in ("[1]", "[0,1]", "[1,0]", "[3,1]"):
        settings = fidelity.validate(
            compose_cfg("fidelity", [*base, f"fidelity.train_seeds={seeds}"])
        )
        streams[seeds] = {c.train_seed: c.stream for c in settings.candidates}
        assert fidelity._chain_seeds(settings).count("seed 1: 8001") == 1
    assert {s[1] for s in streams.values()} == {1}
    # the streams' identity only where the old rule (the i-th listed drew + i) differs
    identity = fidelity.validate(compose_cfg("fidelity", [*base, "fidelity.train_seeds=[0,1]"]))
    assert "chain_streams" not in identity.identity()
    moved = fidelity.validate(compose_cfg("fidelity", [*base, "fidelity.train_seeds=[1]"]))
    assert moved.identity()["chain_streams"] == [1]
    assert streams["[3,1]"][3] == 3
    two = fidelity.validate(compose_cfg("fidelity", [*base, "fidelity.train_seeds=[0]",
                                                     "fidelity.inputs=[signal,signal]"]))  # fmt: skip
    assert [c.stream for c in two.candidates] == [0, fidelity.INPUTS_SEED_STRIDE]


def test_chain_repeats_give_the_means_spread_and_their_own_identity(compose_cfg) -> None:
    """fidelity.chain_repeats=3: the check reads the first run, the table adds the means'
    sd from run to run and their average error, the report says so; 1 keeps the identity of
    checks made before the key; a bad count is refused by name."""
    plain = fidelity.validate(compose_cfg("fidelity", SMALL))
    assert "chain_repeats" not in plain.identity()["fidelity"]
    three = fidelity.validate(compose_cfg("fidelity", [*SMALL, "fidelity.chain_repeats=3"]))
    assert three.directory != plain.directory
    for bad in ("0", "1.5", "true"):
        with pytest.raises(ConfigError, match=r"fidelity.chain_repeats must be an integer >= 1"):
            fidelity.validate(compose_cfg("fidelity", [*SMALL, f"fidelity.chain_repeats={bad}"]))
    (candidate,) = three.candidates
    rng = np.random.default_rng(0)
    results = {k: _run(rng, three.times, 0.0) for k in ("full|gaussian", "full_repeat|gaussian",
                                                         "exact|gaussian")}  # fmt: skip
    shifts = (0.01, 0.03, 0.05)  # the first run's run mean +1 %, the three's average +3 %
    results[f"{candidate.label}|gaussian"] = _run(rng, three.times, shifts[0])
    for r, shift in enumerate(shifts[1:], start=1):
        results[f"{candidate.label}|gaussian|{fidelity.REPEAT}{r}"] = _run(rng, three.times, shift)
    table = fidelity.check(three, results)
    row = table[(table["candidate"] == candidate.label) & (table["quantity"] == "mean_run")].iloc[0]
    assert row["value"] == pytest.approx(0.01) and row["chain_mean_rel"] == pytest.approx(0.03)
    means = np.array([1.01, 1.03, 1.05])
    assert row["chain_rel_sd"] == pytest.approx(means.std(ddof=1) / means.mean())
    exact = table[(table["candidate"] == "exact") & (table["quantity"] == "mean_run")].iloc[0]
    assert np.isnan(exact["chain_rel_sd"])  # only the abstractions are repeated
    # each KS row: the share of the chain's runs within that row's limit
    from scipy import stats

    runs = [results[f"{candidate.label}|gaussian"],
            *(results[f"{candidate.label}|gaussian|{fidelity.REPEAT}{r}"] for r in (1, 2))]  # fmt: skip
    for t in three.times:
        ks_row = table[(table["candidate"] == candidate.label)
                       & (table["quantity"] == f"distance_t{t:g}")].iloc[0]  # fmt: skip
        full = results["full|gaussian"].observables[t]
        passing = [stats.ks_2samp(r.observables[t], full).statistic <= ks_row["threshold"]
                   for r in runs]  # fmt: skip
        assert ks_row["chain_pass_share"] == pytest.approx(np.mean(passing))
    summary = fidelity.summarise(table, three)
    text = "".join(body for _, body in fidelity.report_sections(table, summary, three))
    assert "fidelity.chain_repeats=3" in text and "(runs +3.0 % +- 1.9 % sd)" in text
    assert "(runs pass " in text


def test_failed_checks_name_the_check_drawn_again(compose_cfg, checked, monkeypatch) -> None:
    """A check failed: the report names the same command at sim_seed + 10,000 (every run drawn
    again on the same fits), checked by this stage's settings; none where every check passed
    or the settings refuse it."""
    from surrogate.config import to_dict

    settings, _, table = checked
    config = to_dict(compose_cfg("fidelity", SMALL))
    summary = fidelity.summarise(table, settings)
    again = fidelity.draw_again(settings, summary, config)
    assert again == [f"fidelity.sim_seed={5000 + fidelity.DRAW_AGAIN_STRIDE}"]
    assert fidelity._refusal(config, again) is None  # the advice runs
    assert fidelity.draw_again(settings, {**summary, "passed": summary["checks"]}, config) is None
    text = "\n".join(body for _, body in fidelity.report_sections(
        table, {**summary, "draw_again": again}, settings))  # fmt: skip
    assert "the same command with `fidelity.sim_seed=15000` (checked) draws" in text
    # refused by the stage's settings (e.g. stored references of the old seed): not printed
    monkeypatch.setattr(fidelity, "_refusal", lambda *_: "no stored reference at seed 15000")
    assert fidelity.draw_again(settings, summary, config) is None


def test_failed_checks_under_a_measured_choice_name_its_remedies(
    compose_cfg, checked, monkeypatch
) -> None:
    """A check failed and the chain was chosen by measurement: the report names the choice's
    own remedy, checked by this stage's settings: the candidates it lacked (K lumps for a
    model that declares classes, `gp.choice.kinds`), else four times the held-out cells where
    it was a tie (a chosen spread off changes neither: its screen is no remedy since session
    38); none where every check passed, no chain was measured, or the settings refuse it
    (gp=svgp has no gp.choice)."""
    from dataclasses import replace

    from surrogate.config import to_dict
    from surrogate.diagnosis.remedies import MeasuredChoice
    from surrogate.stages import reproduce

    settings, _, table = checked
    auto = to_dict(compose_cfg("fidelity", [*(o for o in SMALL if o != "gp=svgp"), "gp=auto"]))
    summary = fidelity.summarise(table, settings)
    assert summary["passed"] < summary["checks"]

    def row(kind: str, complexity: int, tied: bool) -> dict:
        return {"kind": kind, "complexity": complexity, "log_likelihood_per_window": -0.1,
                "diff_from_best": 0.0, "diff_se": 1e-4, "tied_with_best": tied,
                "holds_durations": True}  # fmt: skip

    def choice(kinds: tuple[str, ...]) -> MeasuredChoice:
        return MeasuredChoice(chosen="clock max_age=5", kinds=kinds, max_ages=(1.0, 2.0, 5.0),
                              scores=(row("two-state", 0, False), row("clock max_age=5", 1, True),
                                      row("phases", 3, True)),
                              n_cells=1000, tie_se=1.0, classes=True)  # fmt: skip

    monkeypatch.setattr(reproduce, "measured_choice", lambda tr: choice(("two-state", "clock")))
    wider = fidelity.wider_choice(settings, summary, auto)
    assert wider == ["gp.choice.kinds=[two-state,clock,classes,phases]"]
    assert fidelity._refusal(auto, wider) is None  # the advice runs
    text = "\n".join(body for _, body in fidelity.report_sections(
        table, {**summary, "wider_choice": wider}, settings))  # fmt: skip
    assert f"the same command with `{wider[0]}` (checked) widens or sharpens" in text
    every = ("two-state", "clock", "classes", "phases")
    monkeypatch.setattr(reproduce, "measured_choice", lambda tr: choice(every))
    assert fidelity.wider_choice(settings, summary, auto) == ["gp.choice.n_cells=4000"]
    # the chosen clock's occupancy spread off (CERENA's seed 0: +9.1 %) where the phases
    # hold theirs: the same remedies as without
    spread = {
        "clock max_age=5": (0.091, 0.010),
        "phases": (0.028, 0.010),
        "two-state": (-0.49, 0.008),
    }
    screened = replace(choice(every), scores=tuple(
        {**r, "spread_rel_diff": spread[r["kind"]][0], "spread_rel_se": spread[r["kind"]][1]}
        for r in choice(every).scores))  # fmt: skip
    monkeypatch.setattr(reproduce, "measured_choice", lambda tr: screened)
    assert fidelity.wider_choice(settings, summary, auto) == ["gp.choice.n_cells=4000"]
    narrow = replace(screened, kinds=("two-state", "clock"))
    monkeypatch.setattr(reproduce, "measured_choice", lambda tr: narrow)
    assert fidelity.wider_choice(settings, summary, auto) == wider
    # followed before from settings like these for fewer passes: the next remedy instead
    tried = {" ".join(wider)}
    assert fidelity.wider_choice(settings, summary, auto, tried) == ["gp.choice.n_cells=4000"]
    assert fidelity.wider_choice(settings, {**summary, "passed": summary["checks"]}, auto) is None
    named = to_dict(compose_cfg("fidelity", SMALL))  # gp=svgp: no gp.choice to widen
    assert fidelity.wider_choice(settings, summary, named) is None
    monkeypatch.setattr(reproduce, "measured_choice", lambda tr: None)
    assert fidelity.wider_choice(settings, summary, auto) is None


def test_each_field_draws_its_own_stream_as_stored_references_do(compose_cfg) -> None:
    """fidelity.streams=per_field (the default): every run of the second field draws 10,000,000
    past the first's seed (the full model, its floor, the exact chain, each abstraction), the
    stored references by the same rule; shared keeps one seed for every field; every run's
    seed is distinct; an unknown value is refused by name."""
    from surrogate.stages.reference import FIELD_SEED_STRIDE, ReferenceSettings

    two = [s for s in SMALL if not s.startswith("fidelity.fields")]
    two += ["fidelity.fields=[gaussian,linear]", "reference.record_interval=1.0"]
    per_field = fidelity.validate(compose_cfg("fidelity", two))
    o = per_field.options
    (candidate,) = per_field.candidates
    for run_seed in (5000, 6000, 7000, fidelity.chain_seed(o, candidate)):
        assert fidelity.field_stream(o, run_seed, "gaussian") == run_seed
        assert fidelity.field_stream(o, run_seed, "linear") == run_seed + FIELD_SEED_STRIDE
    refs = ReferenceSettings.from_config(compose_cfg("fidelity", two))
    assert {(r.field_name, r.which): r.seed for r in refs.runs} == {
        ("gaussian", "full"): 5000, ("gaussian", "full_repeat"): 6000,
        ("linear", "full"): 5000 + FIELD_SEED_STRIDE,
        ("linear", "full_repeat"): 6000 + FIELD_SEED_STRIDE,
    }  # fmt: skip
    assert "fidelity.streams" not in refs.command
    shared_cfg = compose_cfg("fidelity", [*two, "fidelity.streams=shared"])
    shared = fidelity.validate(shared_cfg)
    assert fidelity.field_stream(shared.options, 5000, "linear") == 5000
    assert shared.directory != per_field.directory  # another draw, another check
    assert "fidelity.streams=shared" in ReferenceSettings.from_config(shared_cfg).command
    with pytest.raises(ConfigError, match=r"fidelity.streams must be one of"):
        fidelity.validate(compose_cfg("fidelity", [*two, "fidelity.streams=paired"]))
    # a repeat stride that reaches the next field's streams is refused before any work
    with pytest.raises(ConfigError, match=r"at most 100 chain_repeats"):
        fidelity.validate(compose_cfg("fidelity", [*two, "fidelity.chain_repeats=101"]))
    fidelity.validate(compose_cfg("fidelity", [*two, "fidelity.chain_repeats=100"]))
