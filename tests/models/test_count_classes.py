"""Classes finer than phi for any network (bins of a count): declared, chosen, validated, and
used: a network whose switching depends on a hidden count fails with the two-state chain and
passes with the classes, at the KS critical value of the duration samples."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import yaml

from surrogate.errors import ConfigError
from surrogate.evaluate.statistics import ExactSample, compare_distributions
from surrogate.models.count_classes import (
    CountBinning,
    CountClasses,
    CountClassifier,
    _choose,
    _edges,
    _formula,
    _homogeneous_edges,
    _readable,
    _sample,
    choose_count_classes,
    parse_classes,
    slow_combinations,
    spread_inputs,
)
from surrogate.models.sbml_agent import SbmlAgentModel
from surrogate.simulate import FullDecision
from surrogate.simulate.batch import Replicate
from surrogate.stages.runs import RunPlan, simulate_runs
from surrogate.stages.simulate import exact_class_decision, exact_decision
from tests.sbml.builder import Reaction, Species, build

#: c(alpha) of the asymptotic two-sample KS critical value at alpha = 0.001
KS_C_ALPHA_001 = 1.949


def _hidden_gene(tmp_path, **spec) -> SbmlAgentModel:
    """Three slow gene copies (G0 <-> G1 at 0.05/s each) and a fast switch S turned on at
    k G1 and off at 1/s; phi = S1 >= 1. While no copy is active the switch cannot turn on: the
    off periods are a mixture over the hidden count G1 that phi does not show."""
    text = build(
        "hidden_gene",
        [Species("G0", amount=3), Species("G1", amount=0), Species("S0", amount=1),
         Species("S1", amount=0)],
        {"a": 0.05, "k": 2.0, "c": 1.0},
        [Reaction("act", "a * G0", {"G0": 1}, {"G1": 1}),
         Reaction("deact", "a * G1", {"G1": 1}, {"G0": 1}),
         Reaction("on", "k * G1 * S0", {"S0": 1}, {"S1": 1}),
         Reaction("off", "c * S1", {"S1": 1}, {"S0": 1})],
    )  # fmt: skip
    (tmp_path / "hidden.xml").write_text(text)
    base = {"network": "hidden.xml", "inputs": {"k": "40 * L"}, "lump": "S1 >= 1",
            "signal_bounds": {"k": [0.0, 4.0]}, "body": {"kind": "static"}, "burn_in": 0.0}  # fmt: skip
    path = tmp_path / "model.yaml"
    path.write_text(yaml.safe_dump({**base, **spec}))
    return SbmlAgentModel(str(path))


def test_classes_name_and_bin_counts_within_each_lump() -> None:
    classes = CountClasses("P", ((2.0, 5.0), (10.0,)), ("low", "high"))
    assert classes.names == ("low|P<2", "low|2<=P<5", "low|P>=5", "high|P<10", "high|P>=10")
    assert classes.lumps == (0, 0, 0, 1, 1)
    classify = CountClassifier(classes, ["P"], "model.classes")
    counts = torch.tensor([[0], [2], [4], [5], [9], [9], [10]])
    phi = torch.tensor([0, 0, 0, 0, 0, 1, 1])
    assert classify(counts, phi).tolist() == [0, 1, 1, 2, 2, 3, 4]
    expression = CountClassifier(CountClasses("P + 2 * Q", ((3.0,), (3.0,))), ["P", "Q"], "c")
    assert expression(torch.tensor([[1, 0], [1, 1]]), torch.tensor([0, 1])).tolist() == [0, 3]


@pytest.mark.parametrize(
    ("value", "message"),
    [
        ("some", "must be auto or a mapping"),
        ({"edges": [1]}, "needs exactly one of species"),
        ({"species": "X", "expression": "X", "edges": [1]}, "needs exactly one of species"),
        ({"species": "Y", "edges": [1]}, "is not a species of the network"),
        ({"species": "X", "edges": [3, 2]}, "must increase strictly"),
        ({"species": "X", "edges": [1, math.inf]}, "must be finite numbers"),
        ({"species": "X", "edges": []}, "the classes would be the lumps themselves"),
        ({"species": "X", "edges": {"off": [1]}}, "needs exactly the lumps"),
        ({"species": "X", "edges": "1, 2"}, "must be a list of numbers"),
        (
            {"species": "X", "edges": [1], "bins": 3},
            r"unknown model.classes setting\(s\) \['bins'\]",
        ),
        ({"species": "X"}, r"model.classes needs the setting\(s\) \['edges'\]"),
        ({"expression": "X +", "edges": [1]}, "model.classes"),
    ],
)
def test_bad_classes_are_refused_by_name(value, message) -> None:
    with pytest.raises(ConfigError, match=message):
        parse_classes(value, ["X"], ("off", "on"))


def test_the_yaml_declares_classes_and_the_exact_class_law(tmp_path) -> None:
    model = _hidden_gene(tmp_path, classes={"species": "G1", "edges": [1, 2, 3]})
    internal = model.internal
    assert (
        internal.class_names[:2] == ("off|G1<1", "off|1<=G1<2") and len(internal.class_names) == 8
    )
    step = internal.exact_class_step(torch.tensor([[2.0]], dtype=torch.float64), 0.05)
    assert step.shape == (1, 8, 8)
    assert torch.allclose(step.sum(-1), torch.ones(1, 8, dtype=torch.float64))
    # the classes are part of the model's identity
    other = _hidden_gene(tmp_path, classes={"species": "G1", "edges": [1]})
    assert model.sources()["classes"] != other.sources()["classes"]


def test_auto_chooses_the_hidden_count(tmp_path) -> None:
    """The chooser's held-out gain is largest for the hidden gene count G1 (the switch
    species add nothing beyond phi, which they are) and significant."""
    model = _hidden_gene(tmp_path)
    classes, report = choose_count_classes(model.internal, torch.tensor([2.0]), 0.05,
                                           cells=200, windows=400, cache_dir=tmp_path)  # fmt: skip
    assert classes.variable in ("G1", "G0")  # one determines the other
    assert report["significant"]
    gains = {c["species"]: c["gain_nats_per_window"] for c in report["candidates"]}
    assert gains[classes.variable] > 10 * max(abs(gains["S0"]), abs(gains["S1"]), 1e-6)
    # cached: the same choice again, read back
    again, _ = choose_count_classes(model.internal, torch.tensor([2.0]), 0.05, cells=200,
                                    windows=400, cache_dir=tmp_path)  # fmt: skip
    assert again.to_config() == classes.to_config()


def test_a_hidden_count_fails_two_states_and_passes_with_classes(tmp_path) -> None:
    """Static cells at one input: the full network, the exact two-state chain and the exact
    K-lumps chain over bins of G1. Off-period durations (tens of thousands each): the two-state
    chain's geometric law is far from the full model's mixture (KS above the 0.1 % critical
    value), the class chain's is within it."""
    model = _hidden_gene(tmp_path, classes={"species": "G1", "edges": [1, 2, 3]})
    dt, n = 0.05, 1000
    torch.manual_seed(0)
    two_state, _ = exact_decision(model, dt, "lookup", None, torch.device("cpu"))
    classes = exact_class_decision(model, dt, torch.device("cpu"))
    from surrogate.fields import GaussianField

    field = GaussianField()
    reps = [Replicate(FullDecision(model.internal), field, n, 1, (2.0, 0.0)),
            Replicate(two_state, field, n, 2, (2.0, 0.0)),
            Replicate(classes, field, n, 3, (2.0, 0.0))]  # fmt: skip
    runs = simulate_runs(model, reps, ["full", "two", "classes"],
                         plan=RunPlan(dt, [100.0], 100.0, 0.0), progress=False)  # fmt: skip

    def off(label: str) -> ExactSample:
        counts = runs[label].histograms["off"]
        k = np.nonzero(counts)[0]
        return ExactSample(k.astype(np.float64), counts[k])

    full = off("full")
    for label, passes in (("two", False), ("classes", True)):
        res = compare_distributions(full, off(label))
        critical = KS_C_ALPHA_001 * math.sqrt((res["n_a"] + res["n_b"]) / (res["n_a"] * res["n_b"]))
        assert (res["ks"] <= critical) == passes, (label, res["ks"], critical)


def _input_driven(tmp_path, **spec) -> SbmlAgentModel:
    """A count X born at the input's rate b and lost at 0.5/s (stationary mean 2 b) drives a
    switch S (on at 0.2 X, off at 1/s); phi = S1 >= 1. The file's b is 2 (X ~ 4); the fields
    may give b up to 20 (X ~ 40)."""
    text = build(
        "input_driven",
        [Species("X", amount=4), Species("S0", amount=1), Species("S1", amount=0)],
        {"b": 2.0, "d": 0.5, "c": 0.2, "e": 1.0},
        [Reaction("birth", "b", {}, {"X": 1}),
         Reaction("death", "d * X", {"X": 1}, {}),
         Reaction("on", "c * X * S0", {"S0": 1}, {"S1": 1}),
         Reaction("off", "e * S1", {"S1": 1}, {"S0": 1})],
    )  # fmt: skip
    (tmp_path / "driven.xml").write_text(text)
    base = {"network": "driven.xml", "inputs": {"b": "100 * L"}, "lump": "S1 >= 1",
            "body": {"kind": "static"}, "burn_in": 20.0}  # fmt: skip
    path = tmp_path / "model.yaml"
    path.write_text(yaml.safe_dump({**base, **spec}))
    return SbmlAgentModel(str(path))


def test_spread_inputs_cover_each_range_evenly() -> None:
    grid = spread_inputs([1.0, 5.0, 7.0], {0: (0.0, 1.0), 2: (10.0, 20.0)}, 4)
    assert grid[:, 0].tolist() == [0.125, 0.375, 0.625, 0.875]
    assert grid[:, 1].tolist() == [5.0] * 4  # not ranged: its default
    assert sorted(grid[:, 2].tolist()) == [11.25, 13.75, 16.25, 18.75]  # shuffled, same values


def test_auto_over_a_range_bins_the_counts_the_range_gives(monkeypatch, tmp_path) -> None:
    """At the file's input alone X stays near 4, so its bins end where the fields' cells only
    begin; spread over b in [2, 20] the bins reach X's values across the range (stationary
    X ~ Poisson(2 b): up to ~40), with ``bins`` per lump."""
    monkeypatch.setenv("SURROGATE_CACHE_DIR", str(tmp_path / "cache"))
    at_file = _input_driven(tmp_path, classes="auto")
    spread = _input_driven(tmp_path, classes={"auto": {"over": {"b": [2.0, 20.0]}, "bins": 4}})
    one, many = at_file.internal.count_classes, spread.internal.count_classes
    assert one.variable == many.variable == "X"
    assert max(max(e) for e in one.edges) < 10
    assert max(max(e) for e in many.edges) > 20
    assert all(len(e) <= 3 for e in many.edges) and max(len(e) for e in many.edges) == 3
    assert many.edges[0] == many.edges[1]  # shared: a flip of phi keeps X's bin
    sample = spread.class_report["sample"]
    assert sample["inputs_min"][0] == pytest.approx(2.0, abs=0.1)
    assert sample["inputs_max"][0] == pytest.approx(20.0, abs=0.1)
    assert spread.class_report["significant"]


@pytest.mark.parametrize(
    ("value", "message"),
    [
        ({"auto": 3}, r"model.classes.auto must be a mapping"),
        ({"auto": {}, "edges": [1]}, "auto takes its options inside it"),
        ({"auto": {"width": 2}}, r"unknown model.classes.auto setting\(s\) \['width'\]"),
        ({"auto": {"bins": 1}}, "bins must be an integer from 2 to 20"),
        ({"auto": {"bins": 2.5}}, "bins must be an integer from 2 to 20"),
        ({"auto": {"over": {"zz": [0, 1]}}}, "not an input parameter"),
        ({"auto": {"over": {"b": [20, 2]}}}, r"must be \[lo, hi\] with 0 <= lo < hi"),
        ({"auto": {"over": {"b": [-1, 2]}}}, r"must be \[lo, hi\] with 0 <= lo < hi"),
        ({"auto": {"over": {"b": [1, math.inf]}}}, r"must be \[lo, hi\]"),
        ({"auto": {"over": [1, 2]}}, "must map input parameters"),
    ],
)
def test_bad_auto_classes_are_refused_before_any_simulation(tmp_path, value, message) -> None:
    with pytest.raises(ConfigError, match=message):
        _input_driven(tmp_path, classes=value)


def test_the_full_model_identity_leaves_out_the_abstraction_settings(tmp_path) -> None:
    """A stored full-model reference serves any classes and collection budget (they shape only
    the abstraction), not another lump or burn-in."""
    config = {"_target_": "surrogate.models.sbml_agent.SbmlAgentModel", "spec": "model.yaml"}
    plain = _input_driven(tmp_path).full_model_identity(config)
    with_classes = _input_driven(
        tmp_path, classes={"species": "X", "edges": [5]}, collect={"n_per_state": 10}
    ).full_model_identity({**config, "classes": {"species": "X", "edges": [5]}})
    assert with_classes == plain
    assert _input_driven(tmp_path, lump="S1 >= 2").full_model_identity(config) != plain
    assert _input_driven(tmp_path, burn_in=30.0).full_model_identity(config) != plain


def test_homogeneous_edges_cut_where_the_chance_of_leaving_changes() -> None:
    """A count uniform over 0..49 whose chance of leaving lump 0 is 0.1 below 15, 0.5 up to 45
    and 0.9 from 45: three bins placed where the chance of leaving varies least are [0, 15),
    [15, 45), [45, 50) (equal-mass quantile bins would cut at 16 and 33)."""
    rng = np.random.default_rng(0)
    values = rng.integers(0, 50, size=(2000, 100)).astype(np.float64)
    chance = np.where(values < 15, 0.1, np.where(values < 45, 0.5, 0.9))
    before = np.zeros(values.shape, dtype=np.int8)
    after = (rng.random(values.shape) < chance).astype(np.int8)
    assert _homogeneous_edges(values, before, after, 3, lumps=(0,)) == (15.0, 45.0)
    assert _edges(values.ravel(), 3) == (16.0, 33.0)
    # fewer distinct values than bins: every value its own bin
    assert _homogeneous_edges(values % 3, before, after, 8, lumps=(0,)) == (1.0, 2.0)
    # shared by two lumps: a bin must hold windows of both, so the lump-1 windows (values 20-29
    # only) bound the bins to the values both lumps reach
    before = np.where(values < 20, 0, np.where(values < 30, rng.integers(0, 2, values.shape), 0))
    shared = _homogeneous_edges(values, before.astype(np.int8), after, 3)
    assert all(20.0 <= e <= 30.0 for e in shared)


def _dimer(tmp_path) -> SbmlAgentModel:
    """P made at k = 5/s, degraded at 0.05/s per monomer, dimerising fast (2P <-> P2, hundreds
    of firings per second): the total protein P + 2 P2 is what the fast pair leaves alone."""
    text = build(
        "dimer",
        [Species("P", amount=20), Species("P2", amount=40)],
        {"k": 5.0, "kd": 2.0, "ku": 200.0},
        [Reaction("make", "k", {}, {"P": 1}),
         Reaction("decay", "0.05 * P", {"P": 1}, {}),
         Reaction("dim", "kd * P * (P - 1) / 2", {"P": 2}, {"P2": 1}),
         Reaction("dis", "ku * P2", {"P2": 1}, {"P": 2})],
    )  # fmt: skip
    (tmp_path / "dimer.xml").write_text(text)
    spec = {"network": "dimer.xml", "inputs": {"k": "50 * L"}, "lump": "P >= 10",
            "body": {"kind": "static"}, "burn_in": 0.0}  # fmt: skip
    path = tmp_path / "dimer.yaml"
    path.write_text(yaml.safe_dump(spec))
    return SbmlAgentModel(str(path))


def test_slow_combinations_are_what_the_fast_reactions_leave_unchanged(tmp_path) -> None:
    """The dimer network: the fast reactions are the dimerisation pair (their mean firings per
    window from the sample's propensities), and the one combination is P + 2 P2."""
    internal = _dimer(tmp_path).internal
    inputs = torch.tensor([5.0])
    counts, _ = _sample(internal, inputs, 0.05, cells=20, windows=50, seed=0)
    combos, fast = slow_combinations(internal, counts, inputs, 0.05)
    assert fast == ["dim", "dis"]
    assert [(f, v.tolist()) for f, v in combos] == [("P + 2 * P2", [1, 2])]
    # nothing is fast at a window 1,000 times shorter: no combination beyond the species
    assert slow_combinations(internal, counts, inputs, 5e-5) == ([], [])


def test_combinations_read_as_counts_with_positive_terms() -> None:
    species = ["Gene", "P2Gene", "Rna", "P", "P2"]
    # 2 Gene - P - 2 P2 with Gene + P2Gene conserved: the total protein, less a constant
    assert _readable([2, 0, 0, -1, -2], [[1, 1, 0, 0, 0]]) == [0, 2, 0, 1, 2]
    assert _formula([0, 2, 0, 1, 2], species) == "2 * P2Gene + P + 2 * P2"
    assert _formula([-1, 0, 0, 1, 0], species) == "-Gene + P"
    assert _readable([1, -1], []) == [1, -1]


def test_a_steady_count_is_preferred_to_a_jittery_one_of_equal_gain() -> None:
    """Two candidates that carry the same hidden count (equal held-out gains): the one the fast
    reactions change is passed over for the steady one; without fast reactions the first
    (a species) is kept."""
    rng = np.random.default_rng(0)
    n, w = 200, 400
    hidden = rng.integers(0, 4, n)
    leave = np.array([0.05, 0.2, 0.4, 0.6])[hidden]
    phi = np.zeros((w + 1, n), dtype=np.int8)
    for t in range(w):
        flip = rng.random(n) < leave
        phi[t + 1] = np.where(flip, 1 - phi[t], phi[t])
    counts = np.broadcast_to(hidden[None, :, None], (w + 1, n, 1)).astype(np.int64)
    combos = [("X + 0 * X", np.array([1]))]
    chosen, report = _choose(counts, phi, ["X"], ("off", "on"), CountBinning(3), combos, {"X"})
    assert chosen.variable == "X + 0 * X"
    assert [c["fast_changed"] for c in report["candidates"]] == [True, False]
    kept, _ = _choose(counts, phi, ["X"], ("off", "on"), CountBinning(3), combos, set())
    assert kept.variable == "X"


def test_a_count_that_decides_phi_gets_each_lumps_own_bins() -> None:
    """phi = X >= 25 on a random walk of X over 0..49 (a threshold on the count itself, as the
    inspector's `P2 >= 87` on the textbook's dimerisation): no bin of X holds both lumps, so
    shared bins are none (the chooser then returned phi alone, gain 0); each lump now gets its
    own bins, and the walk's distance to the threshold is what they hold: from X = 24 it
    leaves `off` half the time, from below never, and from 25 it leaves `on` half the time."""
    rng = np.random.default_rng(1)
    n, w = 200, 1000
    x = np.empty((w + 1, n), dtype=np.int64)
    x[0] = rng.integers(0, 50, n)
    for t in range(w):
        x[t + 1] = np.clip(x[t] + rng.choice([-1, 1], n), 0, 49)
    phi = (x >= 25).astype(np.int8)
    classes, report = _choose(x[:, :, None], phi, ["X"], ("off", "on"), CountBinning(4))
    assert 24.0 in classes.edges[0] and 26.0 in classes.edges[1]
    assert max(classes.edges[0]) <= 25 and min(classes.edges[1]) >= 25
    assert report["significant"] and report["candidates"][0]["gain_nats_per_window"] > 0
