"""A collection's identity holds what its rows depend on: where a network's classes are bins of
a count, the rows store the count and train applies the bins, so changing only the bins reuses
the collection (it once re-collected the same seeded transitions, ~2.5 min each time), while
another count, or rows that do depend on the classes, are collected anew."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import yaml

from surrogate.simulate.classes import CLASS, CLASS_COUNT, CLASS_COUNT_NEXT, CLASS_NEXT
from surrogate.stages import collect
from surrogate.stages import train as train_stage
from surrogate.stages.settings import CollectSettings, TrainSettings
from tests.sbml.builder import Reaction, Species, build

#: a tiny collection of the network below (static cells: only the network is simulated)
TINY = ["collect.n_per_state=60", "collect.n_cells=20", "collect.record_every=2",
        "collect.equilibration_time=1.0", "collect.probe_seconds=0"]  # fmt: skip


def _spec(folder: Path, classes: dict | None) -> Path:
    """A count X born at the input's rate and lost at 0.5/s drives a switch S (phi = S1 >= 1);
    ``classes`` as the yaml gives them."""
    folder.mkdir(exist_ok=True)
    text = build(
        "input_driven",
        [Species("X", amount=4), Species("S0", amount=1), Species("S1", amount=0)],
        {"b": 2.0, "d": 0.5, "c": 0.2, "e": 1.0},
        [Reaction("birth", "b", {}, {"X": 1}),
         Reaction("death", "d * X", {"X": 1}, {}),
         Reaction("on", "c * X * S0", {"S0": 1}, {"S1": 1}),
         Reaction("off", "e * S1", {"S1": 1}, {"S0": 1})],
    )  # fmt: skip
    (folder / "driven.xml").write_text(text)
    spec = {"network": "driven.xml", "inputs": {"b": "100 * L"}, "lump": "S1 >= 1",
            "body": {"kind": "static"}, "burn_in": 5.0,
            **({"classes": classes} if classes is not None else {})}  # fmt: skip
    path = folder / "model.yaml"
    path.write_text(yaml.safe_dump(spec))
    return path


def _train_cfg(compose_cfg, spec: Path, *extra: str):
    return compose_cfg("train", ["model=sbml", f"model.spec={spec}", "gp=classes", *TINY,
                                 *extra])  # fmt: skip


def test_only_the_bins_changed_keeps_the_collections_identity(compose_cfg, tmp_path) -> None:
    """The same yaml edited: other bins of X keep the rows' directory (the fit's changes);
    another count is other rows."""
    folder = tmp_path / "m"

    def settings(classes: dict, *extra: str) -> tuple[Path, Path]:
        s = TrainSettings.from_config(_train_cfg(compose_cfg, _spec(folder, classes), *extra))
        assert isinstance(s.source, CollectSettings) and s.source.bins_at_train
        return s.source.directory, s.fit_directory

    coarse = settings({"species": "X", "edges": [5]})
    fine = settings({"species": "X", "edges": [3, 8]})
    assert coarse[0] == fine[0]  # the same rows
    assert coarse[1] != fine[1]  # fitted on other classes
    # the bins given on the command line leave the rows' identity too
    given = settings({"species": "X", "edges": [5]}, "+model.classes={species: X, edges: [3, 8]}")
    assert given[0] == coarse[0] and given[1] != coarse[1]
    # another count is other rows: collected anew
    assert settings({"expression": "X + S1", "edges": [5]})[0] != coarse[0]


def test_rows_that_depend_on_the_classes_keep_them_in_their_identity(compose_cfg, tmp_path) -> None:
    """No classes: the identity as it was (the model's own); E. coli's rows carry its classes'
    expected law, so the classes stay in its identity as they were."""
    plain = CollectSettings.from_config(_train_cfg(compose_cfg, _spec(tmp_path / "p", None)))
    assert not plain.bins_at_train and plain.bins_identity() == {}
    assert {k: plain.identity()[k] for k in ("model", "model_sources")} == {
        k: plain.setup.identity()[k] for k in ("model", "model_sources")
    }
    ecoli = CollectSettings.from_config(compose_cfg("train", ["gp=classes"]))
    assert not ecoli.bins_at_train
    assert ecoli.identity() == {**ecoli.setup.identity(), "collect": ecoli.identity()["collect"],
                                "device": "cpu"}  # fmt: skip


def test_train_applies_its_bins_to_a_collection_made_with_others(compose_cfg, tmp_path) -> None:
    """Collected with one bin edge, read with two: the rows are reused (not collected again)
    and their classes are the reader's, from the stored counts."""
    first = _train_cfg(compose_cfg, _spec(tmp_path / "m", {"species": "X", "edges": [5]}))
    directory = collect.run(first)
    manifest = json.loads((directory / "manifest.json").read_text())
    second = _train_cfg(compose_cfg, _spec(tmp_path / "m", {"species": "X", "edges": [3, 8]}))
    assert collect.run(second) == directory
    assert json.loads((directory / "manifest.json").read_text()) == manifest  # not re-collected
    table, _ = train_stage.load_transitions(TrainSettings.from_config(second))
    for value, phi, column in ((CLASS_COUNT, "phi", CLASS), (CLASS_COUNT_NEXT, "phi_next",
                                                              CLASS_NEXT)):  # fmt: skip
        x, p = table[value].to_numpy(), table[phi].to_numpy()
        want = np.digitize(x, [3, 8]) + 3 * p  # three bins per lump, lump 1's after lump 0's
        assert (table[column].to_numpy() == want).all()
    stored = np.digitize(table[CLASS_COUNT].to_numpy(), [5]) + 2 * table["phi"].to_numpy()
    assert table[CLASS].nunique() > 2 and not (table[CLASS].to_numpy() == stored).all()
