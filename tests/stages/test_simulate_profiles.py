"""The simulate stage in a grid field: profiles, kymograph and band facts beside the run's other
artefacts (none in a given field); evaluate draws two such runs side by side."""

from __future__ import annotations

from surrogate.evaluate.statistics import load_run
from surrogate.io import read_manifest
from surrogate.simulate.profiles import PROFILES, read_profiles
from surrogate.stages import simulate as simulate_stage
from surrogate.stages.artefacts import KYMOGRAPH_FIGURE
from surrogate.stages.evaluate import write_kymograph

RUN = ["decision=full", "n_cells=30", "t_end=2.0", "record_interval=0.5",
       "equilibration_time=0.5", "backend=torch"]  # fmt: skip


def test_a_coupled_run_writes_profiles_a_kymograph_and_band_facts(compose_cfg, tmp_path) -> None:
    coupled = [simulate_stage.run(compose_cfg("simulate", [*RUN, "field=channel_consumed",
                                                           f"seed={s}"])) for s in (0, 1)]  # fmt: skip
    out = coupled[0]
    profiles = read_profiles(out)
    assert profiles.read == "serine" and profiles.counts.shape == (5, 512)
    assert (profiles.counts.sum(1) + profiles.below + profiles.above == 30).all()
    assert (out / KYMOGRAPH_FIGURE).stat().st_size > 0
    manifest = read_manifest(out)
    assert manifest["profiles"]["n_records"] == 5 and manifest["profiles"]["file"] == PROFILES
    assert set(manifest["band"]) >= {"front", "peak", "column_width"}
    given = simulate_stage.run(compose_cfg("simulate", [*RUN, "field=gaussian"]))
    assert not (given / PROFILES).exists() and not (given / KYMOGRAPH_FIGURE).exists()
    assert "profiles" not in read_manifest(given)
    # evaluate: both runs in a grid field side by side; a run in a given field, no figure
    runs = tuple(load_run(d) for d in coupled)
    figure = write_kymograph(tmp_path, runs, ("full", "full, seed 1"))
    assert figure is not None and figure.read_bytes()[:4] == b"\x89PNG"
    assert write_kymograph(tmp_path / "no", (runs[0], load_run(given)), ("a", "b")) is None
