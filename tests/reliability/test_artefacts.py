"""Missing, foreign and corrupt artefacts are refused with the file and the remedy named."""

from __future__ import annotations

import json
from pathlib import Path

import pandas as pd
import pytest
import torch

from surrogate.errors import ArtefactError, MissingArtefactError
from surrogate.evaluate.statistics import load_run
from surrogate.gp import load_psi
from surrogate.io import (
    MANIFEST,
    check_settings,
    load_tensors,
    read_csv,
    read_json,
    read_manifest,
    read_parquet,
    write_json,
    write_parquet,
)
from surrogate.stages import collect, train
from surrogate.stages import evaluate as evaluate_stage
from surrogate.stages import simulate as simulate_stage
from surrogate.stages.artefacts import CLASS_CHAIN
from surrogate.stages.collect import TRANSITIONS

# ---------------------------------------------------------------------------------------------
# missing inputs name the command that makes them
from .conftest import collect_dir, fit_dir, train_dir


def test_train_without_collect_names_the_collect_command(tiny) -> None:
    cfg = tiny("train", ["seed=7"])
    with pytest.raises(MissingArtefactError) as info:
        train.run(cfg)
    text = str(info.value)
    assert "no collected transitions" in text and str(collect_dir(cfg)) in text
    assert (
        "python scripts/collect.py model=ecoli field=gaussian dt=0.05 seed=7 "
        "collect.n_per_state=200 collect.n_cells=50 collect.equilibration_time=1.0`" in text
    )
    assert not train_dir(cfg).exists()  # nothing was started


def test_simulate_abstract_without_train_names_the_train_command(tiny) -> None:
    cfg = tiny("simulate", ["decision=abstract"])
    with pytest.raises(MissingArtefactError) as info:
        simulate_stage.run(cfg)
    text = str(info.value)
    assert "no trained abstraction" in text
    # the whole command: every setting that differs from the shipped defaults, and the fit's
    # thread count as resolved (this process's: the command reproduces the same fit)
    assert (
        "Run `python scripts/train.py model=ecoli field=gaussian dt=0.05 seed=0 "
        "collect.n_per_state=200 collect.n_cells=50 collect.equilibration_time=1.0 "
        "gp=classes gp.n_inducing=10 gp.epochs=2 gp.batch_size=100 gp.grid_size=[10] "
        f"gp.threads={torch.get_num_threads()} gp.diagnostic.n_cells=50 gp.diagnostic.t_end=5.0` "
        "first (after `python scripts/collect.py model=ecoli field=gaussian dt=0.05 seed=0" in text
    )


def test_evaluate_without_simulations_names_the_simulate_command(tiny) -> None:
    with pytest.raises(MissingArtefactError) as info:
        evaluate_stage.run(tiny("evaluate"))
    text = str(info.value)
    assert "missing simulation" in text
    assert (
        "python scripts/simulate.py decision=full model=ecoli field=gaussian dt=0.05 seed=0 "
        "n_cells=20 t_end=2.0 equilibration_time=1.0`" in text
    )
    assert "evaluate.run_missing=true" in text


# ---------------------------------------------------------------------------------------------
# an artefact made with other settings is refused, the difference named


def _tamper_settings(directory: Path, section: str, key: str, value) -> None:
    manifest = json.loads((directory / MANIFEST).read_text())
    manifest["settings"][section][key] = value
    write_json(directory / MANIFEST, manifest)


def test_check_settings_names_every_difference() -> None:
    expected = {"dt": 0.05, "collect": {"perturb_rate": 0.2}, "seed": 0}
    found = {"dt": 0.05, "collect": {"perturb_rate": 0.5}, "seed": 1}
    with pytest.raises(ArtefactError) as info:
        check_settings(expected, found, "data/collect/x", "python scripts/collect.py")
    text = str(info.value)
    assert "collect: artefact has {'perturb_rate': 0.5}" in text
    assert "seed: artefact has 1, this run wants 0" in text
    assert "dt" not in text.split("settings (")[1].split(")")[0]  # only what differs
    assert "python scripts/collect.py" in text
    check_settings(expected, dict(expected), "x", "y")  # equal settings pass


def test_train_refuses_transitions_made_with_other_settings(tiny, copy_data) -> None:
    cfg = tiny("train")
    _tamper_settings(collect_dir(cfg), "collect", "perturb_rate", 0.5)
    with pytest.raises(
        ArtefactError, match=r"made with different settings \(collect: artefact has"
    ):
        train.load_transitions(train.validate(cfg))
    with pytest.raises(ArtefactError, match="'perturb_rate': 0.5"):
        train.run(cfg, force=True)
    # rerunning collect would only reuse the foreign artefact, so it says to remove it
    with pytest.raises(ArtefactError, match=r"rm -r .*collect.* && python scripts/collect.py"):
        collect.run(cfg)


def test_simulate_refuses_an_abstraction_made_with_other_settings(tiny, copy_data) -> None:
    cfg = tiny("simulate", ["decision=abstract"])
    _tamper_settings(fit_dir(tiny("train")), "gp", "n_inducing", 99)
    with pytest.raises(ArtefactError, match=r"gp: artefact has .*'n_inducing': 99"):
        simulate_stage.run(cfg)


# ---------------------------------------------------------------------------------------------
# truncated or corrupt files are refused, never half-read


def _truncate(path: Path, keep: float) -> None:
    data = path.read_bytes()
    path.write_bytes(data[: int(len(data) * keep)])


@pytest.mark.parametrize("keep", [0.0, 0.5, 0.99])
@pytest.mark.parametrize("name", [TRANSITIONS, MANIFEST])
def test_train_refuses_a_truncated_collect_artefact(
    tiny, copy_data, name: str, keep: float
) -> None:
    cfg = tiny("train")
    path = collect_dir(cfg) / name
    _truncate(path, keep)
    with pytest.raises(ArtefactError) as info:
        train.load_transitions(train.validate(cfg))
    assert str(path) in str(info.value) and "corrupt or truncated" in str(info.value)


@pytest.mark.parametrize("keep", [0.0, 0.5, 0.99])
@pytest.mark.parametrize("where", ["fit", "train"])
def test_a_truncated_psi_file_is_refused(tiny, copy_data, keep: float, where: str) -> None:
    """The fit's psi.pt (what a two-state simulation loads) and the train directory's copy; the
    default chain for E. coli (K lumps) loads its class table, below."""
    directory = {"fit": fit_dir, "train": train_dir}[where](tiny("train"))
    _truncate(directory / train.PSI, keep)
    for load in (
        lambda: load_psi(directory / train.PSI),
        lambda: train.load_abstraction(directory),
    ):
        with pytest.raises(ArtefactError) as info:
            load()
        assert str(directory / train.PSI) in str(info.value)


@pytest.mark.parametrize("keep", [0.0, 0.5])
def test_a_truncated_class_chain_is_refused(tiny, copy_data, keep: float) -> None:
    """The K-lumps chain's table (the default for E. coli): what its simulations load."""
    path = fit_dir(tiny("train")) / CLASS_CHAIN
    _truncate(path, keep)
    with pytest.raises(ArtefactError, match=CLASS_CHAIN):
        simulate_stage.run(tiny("simulate", ["decision=abstract"]))


def test_a_truncated_train_manifest_is_refused(tiny, copy_data) -> None:
    cfg = tiny("train")
    path = fit_dir(cfg) / MANIFEST
    _truncate(path, 0.5)
    with pytest.raises(ArtefactError, match=f"{path}.*not valid JSON"):
        train.resolve_abstraction(train.validate(cfg))
    with pytest.raises(ArtefactError, match=f"{path}.*not valid JSON"):
        simulate_stage.run(tiny("simulate", ["decision=abstract"]))
    path = train_dir(cfg) / MANIFEST
    _truncate(path, 0.5)
    with pytest.raises(ArtefactError, match=f"{path}.*not valid JSON"):
        train.run(cfg)  # the stage does not reuse (or overwrite) a corrupt artefact silently


def test_a_manifest_that_is_not_a_manifest_is_refused(tiny, copy_data) -> None:
    cfg = tiny("train")
    (collect_dir(cfg) / MANIFEST).write_text("[1, 2, 3]\n")
    with pytest.raises(ArtefactError, match="is not a stage manifest"):
        read_manifest(collect_dir(cfg))
    with pytest.raises(ArtefactError, match="is not a stage manifest"):
        train.load_transitions(train.validate(cfg))


def test_transitions_that_disagree_with_their_manifest_are_refused(tiny, copy_data) -> None:
    cfg = tiny("train")
    path = collect_dir(cfg) / TRANSITIONS
    table = pd.read_parquet(path)
    write_parquet(path, table.iloc[:-10])
    with pytest.raises(ArtefactError, match=f"{path} has 390 rows but its manifest says 400"):
        train.load_transitions(train.validate(cfg))
    write_parquet(path, table.drop(columns=["phi_next"]))
    with pytest.raises(ArtefactError, match=r"lacks column\(s\) \['phi_next'\]"):
        train.load_transitions(train.validate(cfg))


@pytest.mark.parametrize("name", ["observables.parquet", "durations.parquet", "manifest.json"])
def test_evaluate_refuses_a_truncated_simulation(tiny, name: str) -> None:
    directory = simulate_stage.run(tiny("simulate"))
    load_run(directory)  # complete: loads
    _truncate(directory / name, 0.5)
    with pytest.raises(ArtefactError) as info:
        load_run(directory)
    assert str(directory / name) in str(info.value)


@pytest.mark.parametrize(
    ("reader", "content"),
    [
        (read_json, b'{"stage": "collect", "seed": 0'),
        (read_json, b"\xff\xfe\x00garbage"),
        (read_parquet, b"PAR1 not really parquet"),
        (read_parquet, b""),
        (load_tensors, b"PK\x03\x04 truncated zip"),
        (load_tensors, b""),
        (read_csv, b""),
    ],
)
def test_readers_refuse_corrupt_files_by_name(tmp_path: Path, reader, content: bytes) -> None:
    path = tmp_path / "artefact.bin"
    path.write_bytes(content)
    with pytest.raises(ArtefactError) as info:
        reader(path)
    assert str(path) in str(info.value)
    assert not isinstance(info.value, MissingArtefactError)


@pytest.mark.parametrize("reader", [read_json, read_parquet, load_tensors, read_csv])
def test_readers_name_the_command_for_a_missing_file(tmp_path: Path, reader) -> None:
    with pytest.raises(MissingArtefactError, match="Run `python scripts/x.py` first"):
        reader(tmp_path / "nope", made_by="python scripts/x.py")
