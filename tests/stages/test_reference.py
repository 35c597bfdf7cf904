"""Stored full-model references: shards merge into the run they define, a stopped run resumes
from its finished shards, the fidelity check reads them (and simulates no full run), and a
reference made for another model identity is refused by the settings that differ."""

from __future__ import annotations

import numpy as np
import pytest

from surrogate.errors import ArtefactError, ConfigError, MissingArtefactError
from surrogate.simulate.batch import Replicate
from surrogate.simulate.decision import FullDecision
from surrogate.stages import fidelity, reference, runs
from surrogate.stages.shards import shard_seed, shard_sizes

RUN = ["fidelity.fields=[gaussian]", "fidelity.n_cells=12", "fidelity.t_end=1.0",
       "reference.shard_cells=5", "reference.record_interval=0.5", "reference.workers=1"]  # fmt: skip
SMALL = ["collect.n_per_state=200", "collect.n_cells=50", "gp.n_inducing=10", "gp.epochs=20",
         "gp.diagnostic.n_cells=20", "gp.diagnostic.t_end=2.0", "fidelity.train_seeds=[0]",
         "fidelity.exact_psi=false"]  # fmt: skip


@pytest.fixture
def stored(compose_cfg, tmp_path):
    """The references of a small config, made once (3 shards per run, 2 runs)."""
    overrides = [*RUN, f"reference.dir={tmp_path / 'references'}"]
    settings = reference.validate(compose_cfg("fidelity", overrides))
    reference.make(settings)
    return overrides, settings


def _record_simulated_shards(monkeypatch) -> list[tuple[str, int]]:
    """The (run, shard) pairs simulated from now on, appended as each shard is simulated."""
    made: list[tuple[str, int]] = []
    simulate_shard = reference._simulate_shard

    def spy(r, shard, out, s):
        made.append((r.which, shard))
        simulate_shard(r, shard, out, s)

    monkeypatch.setattr(reference, "_simulate_shard", spy)
    return made


def test_shards_merge_into_the_run_they_define(stored) -> None:
    """The stored run is its shards, each the standalone run of its own seed, concatenated in
    shard order; the means come from exact totals; every record time is kept."""
    _, settings = stored
    r = settings.run_for("gaussian", "full")
    assert r.shard_count == 3 and shard_sizes(12, 3) == [4, 4, 4]
    got = reference.load(r, settings.command, r.record_times)
    model = r.setup.model
    parts = []
    for i, n in enumerate(shard_sizes(r.n_cells, r.shard_count)):
        seed = shard_seed(r.seed, r.shard_count, i)
        rep = Replicate(FullDecision(model.internal), r.setup.field, n, seed, r.start)
        plan = runs.RunPlan(r.setup.dt, r.record_times, r.t_end, r.equilibration_time)
        parts.append(runs.simulate_runs(model, [rep], ["s"], plan=plan, progress=False)["s"])
    want = runs.RunResult.merge(parts, r.setup.dt)
    assert list(got.observables) == list(r.record_times) == [0.5, 1.0]
    for t in r.record_times:
        np.testing.assert_array_equal(got.observables[t], want.observables[t])
    assert got.segments == want.segments and got.total_steps == want.total_steps
    for lump, mean in want.mean_durations.items():
        assert got.mean_durations[lump] == pytest.approx(mean, rel=1e-12)
        assert got.segments[lump] == int(got.histograms[lump].sum())
        # the exact totals agree with the histogram where no segment reached its last bin
        k = np.arange(len(got.histograms[lump]))
        assert int((k * got.histograms[lump]).sum()) == got.total_steps[lump]
    # the noise-floor run has its own seed: another sample
    repeat = reference.load(settings.run_for("gaussian", "full_repeat"), settings.command, [1.0])
    assert not np.array_equal(repeat.observables[1.0], got.observables[1.0])


def test_a_stopped_run_resumes_from_its_finished_shards(compose_cfg, tmp_path, monkeypatch) -> None:
    settings = reference.validate(
        compose_cfg("fidelity", [*RUN, f"reference.dir={tmp_path / 'references'}"])
    )
    reference._make_shard(settings, 0, 1, force=False)  # one shard made before a "stop"
    made = _record_simulated_shards(monkeypatch)
    reference.make(settings)
    assert sorted(made) == [("full", 0), ("full", 2), ("full_repeat", 0), ("full_repeat", 1),
                            ("full_repeat", 2)]  # fmt: skip
    made.clear()
    reference.make(settings)  # everything stored: nothing simulated again
    assert made == []


def test_fidelity_reads_the_stored_runs_and_simulates_no_full_run(
    stored, compose_cfg, monkeypatch
) -> None:
    overrides, settings = stored
    simulated = []
    simulate_runs = runs.simulate_runs

    def spy(model, replicates, labels, **kw):
        simulated.extend(labels)
        return simulate_runs(model, replicates, labels, **kw)

    monkeypatch.setattr(fidelity, "simulate_runs", spy)
    cfg = compose_cfg("fidelity", [*overrides, *SMALL, "fidelity.reference=stored",
                                   "fidelity.times=[0.5,1.0]"])  # fmt: skip
    out = fidelity.run(cfg)
    assert simulated and not any(label.startswith("full") for label in simulated)
    import pandas as pd

    table = pd.read_csv(out / "fidelity.csv")
    full = reference.load(settings.run_for("gaussian", "full"), settings.command, [1.0])
    repeat = reference.load(settings.run_for("gaussian", "full_repeat"), settings.command, [1.0])
    from scipy import stats

    floor = stats.ks_2samp(repeat.observables[1.0], full.observables[1.0]).statistic
    row = table[table["quantity"] == "distance_t1"]
    assert np.allclose(row["noise_floor"], floor)


def test_a_reference_of_another_model_identity_is_refused_by_name(stored, compose_cfg) -> None:
    """Before any training: the message names the setting that differs and the command."""
    overrides, _ = stored
    cfg = compose_cfg("fidelity", [*overrides, *SMALL, "fidelity.reference=stored",
                                   "model.tau=20.0"])  # fmt: skip
    with pytest.raises(MissingArtefactError) as err:
        fidelity.validate(cfg)
    text = str(err.value)
    assert "model.tau: stored 15.0, wanted 20.0" in text
    assert "python scripts/reference.py model=ecoli model.tau=20" in text


def test_check_times_the_reference_does_not_keep_are_refused(stored, compose_cfg) -> None:
    overrides, _ = stored
    cfg = compose_cfg("fidelity", [*overrides, *SMALL, "fidelity.reference=stored",
                                   "fidelity.times=[0.75]"])  # fmt: skip
    with pytest.raises(ArtefactError, match=r"multiples of 0.5 s, not at \[0.75\]"):
        fidelity.validate(cfg)


@pytest.mark.parametrize(
    ("override", "message"),
    [
        ("reference.workers=0", "reference.workers must be a positive integer"),
        ("reference.shard_cells=0", "reference.shard_cells"),
        ("reference.record_interval=0.3", "must be a multiple of reference.record_interval"),
        ("reference.dir=''", "reference.dir must name"),
        ("fidelity.reference=maybe", "fidelity.reference must be one of"),
    ],
)
def test_bad_reference_settings_are_refused(compose_cfg, override, message) -> None:
    cfg = compose_cfg("fidelity", [*RUN, *SMALL, override])
    with pytest.raises(ConfigError, match=message):
        (fidelity if override.startswith("fidelity.") else reference).validate(cfg)


@pytest.mark.slow
def test_worker_processes_make_the_same_bytes(compose_cfg, tmp_path) -> None:
    """Two worker processes of one thread each make what one in-process worker makes."""
    results = []
    for workers in (1, 2):
        settings = reference.validate(compose_cfg("fidelity", [
            *RUN, f"reference.workers={workers}", f"reference.dir={tmp_path / str(workers)}",
            f"data_dir={tmp_path / f'data{workers}'}"]))  # fmt: skip
        reference.make(settings)
        r = settings.run_for("gaussian", "full")
        results.append(reference.load(r, settings.command, r.record_times))
    one, two = results
    for t in one.observables:
        np.testing.assert_array_equal(one.observables[t], two.observables[t])
    assert one.segments == two.segments and one.total_steps == two.total_steps


def test_a_larger_run_copies_the_shards_a_smaller_one_made(
    stored, compose_cfg, monkeypatch
) -> None:
    """Shard i of a run is the same cells whatever the run's size (child i of the seed), so a
    run of 16 cells (4 shards of 4) simulates only its new shard and copies the 12-cell run's
    three: the merged run's first 12 cells are the stored run's, byte for byte."""
    overrides, small = stored
    made = _record_simulated_shards(monkeypatch)
    larger = reference.validate(compose_cfg("fidelity", [*overrides, "fidelity.n_cells=16"]))
    reference.make(larger)
    assert sorted(made) == [("full", 3), ("full_repeat", 3)]
    r, r12 = larger.run_for("gaussian", "full"), small.run_for("gaussian", "full")
    got = reference.load(r, larger.command, r.record_times)
    old = reference.load(r12, small.command, r12.record_times)
    for t in r.record_times:
        np.testing.assert_array_equal(got.observables[t][:12], old.observables[t])
        assert len(got.observables[t]) == 16
    # another shard size is other cells: nothing to copy
    made.clear()
    other = reference.validate(compose_cfg("fidelity", [*overrides, "reference.shard_cells=4"]))
    reference.make(other)
    assert len(made) == 6
