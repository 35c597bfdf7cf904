"""The benchmark runs end to end (a smoke run, no timing asserts), and the fast paths it times
(compiled step, fused decisions) compute what the reference paths compute."""

from __future__ import annotations

import json

import pytest
import torch

from surrogate.benchmarks.lookup import format_lookup_report
from surrogate.benchmarks.loop import format_report, main
from surrogate.fields import GaussianField
from surrogate.gp import PsiLookupTable
from surrogate.models.ecoli import EcoliModel
from surrogate.simulate import AbstractDecision, FullDecision, Simulator

MODEL = EcoliModel()
DT = 0.05
START = (2.0, 0.0)


@pytest.mark.parametrize(
    ("inputs", "overrides", "lookup_size"),
    [
        # the default abstraction (the signal dG, one input): the shipped quick size, 1-D
        (["dG"], [], [64]),
        # the paper's (m, L) abstraction: the same size on both axes
        (["m", "L"], ["gp.inputs=inputs", "quick_settings.lookup_size=32"], [32, 32]),
    ],
    ids=["signal", "inputs"],
)
def test_quick_bench_writes_all_sections(
    compose_cfg, tmp_path, inputs: list[str], overrides: list[str], lookup_size: list[int]
) -> None:
    out = tmp_path / "bench.json"
    cfg = compose_cfg(
        "bench", ["quick=true", f"output={out}", "quick_settings.sizes=[50,200]", *overrides]
    )
    assert main(cfg) == out
    r = json.loads(out.read_text())
    for key in ("machine", "settings", "abstraction", "collect", "training", "throughput",
                "best_config", "motors", "breakdown", "paper", "memory", "total_s"):  # fmt: skip
        assert key in r, key
    assert {"cpu", "cores", "torch_threads", "device", "load_average"} <= set(r["machine"])
    # the torch step, then the per-cell kernel (the classifier has none: torch there too)
    assert [(row["backend"], row["n_cells"]) for row in r["throughput"]] == [
        ("torch", 50),
        ("torch", 200),
        ("numba", 50),
        ("numba", 200),
    ]
    for row in r["throughput"]:
        for model in ("full", "lookup", "classifier"):
            assert row[model]["cell_steps_per_s"] > 0
        kernel = "torch" if row["backend"] == "torch" else "numba"
        assert row["ratio_lookup"] > 0
        # the classifier has no kernel: on torch beside the full model's kernel, no ratio
        assert (row["ratio_classifier"] is None) == (kernel == "numba")
        assert (row["full"]["backend"], row["lookup"]["backend"]) == (kernel, kernel)
        assert row["classifier"]["backend"] == "torch"
    assert {(run["model"], run["backend"]) for run in r["paper"]["runs"]} == {
        (m, b) for m in ("full", "lookup") for b in ("torch", "numba")
    }
    assert [row["n_motors"] for row in r["motors"]] == [4, 10]
    assert r["collect"]["seconds"] > 0 and r["training"]["seconds"] > 0
    assert r["training"]["n_per_classifier"] == 300
    assert r["training"]["inputs"] == inputs
    assert set(r["training"]["fit_seconds"]) == {"psi_0", "psi_1"}
    a = r["abstraction"]
    assert a["inputs"] == inputs and set(a["domain"]) == set(inputs)
    assert a["lookup_size"] == lookup_size
    # the table and the cached classifier reproduce the classifier they were built from
    assert 0 <= a["lookup_max_deviation"] < 0.05 and 0 <= a["cached_max_deviation"] < 1e-4
    assert all(run["peak_rss_mb"] > 0 for run in r["memory"]["runs"])
    assert "trained on the fly" in a["source"]
    assert "throughput" in format_report(r)
    assert "kernel_compile" not in r  # the quick bench skips the fresh-process compilation


@pytest.mark.parametrize("model", ["ecoli", "ecoli_phospho"])
def test_lookup_only_bench_times_the_abstraction_alone(compose_cfg, tmp_path, model) -> None:
    """lookup_only=true: a table from a function of the signal (no training, no full model),
    each backend's rows saying which loop ran; E. coli also with the switch clock (its
    table has a node per step up to gp.max_age) and the K-lumps chain, side by side."""
    out = tmp_path / "bench.json"
    histories = ["none", "age", "classes"] if model == "ecoli" else ["none"]
    cfg = compose_cfg("bench", [
        "quick=true", "lookup_only=true", f"output={out}", f"model={model}",
        "quick_settings.sizes=[30]", "quick_settings.threads=[1]",
        f"histories=[{','.join(histories)}]",
        *(["model.burn_in=0"] if model == "ecoli_phospho" else []),
    ])  # fmt: skip
    assert main(cfg) == out
    r = json.loads(out.read_text())
    signal = {"ecoli": "dG", "ecoli_phospho": "activity"}[model]
    inputs = {"none": [signal], "age": [signal, "phi_age"], "classes": [signal]}
    sizes = {"none": [64], "age": [64, 101], "classes": [64]}  # 5 s of clock: a node per step
    assert r["model"] == model
    assert r["abstraction"]["inputs"] == {h: inputs[h] for h in histories}
    assert r["abstraction"]["lookup_size"] == {h: sizes[h] for h in histories}
    assert [(row["backend"], row["n_cells"], row["history"]) for row in r["throughput"]] == [
        (b, 30, h) for b in ("torch", "numba") for h in histories
    ]
    for row in r["throughput"]:
        assert row["lookup"]["cell_steps_per_s"] > 0
        assert row["lookup"]["backend"] == row["backend"]  # clock and classes: on the kernel too
    assert "collect" not in r and "lookup throughput" in format_lookup_report(r)


def test_kernel_compile_is_timed_cold_then_cached(tmp_path) -> None:
    """Two fresh processes share an empty numba cache: the first compiles the kernel, the
    second loads it (much faster)."""
    from surrogate.benchmarks.loop import kernel_compile_times

    times = kernel_compile_times({"_target_": "surrogate.models.ecoli.EcoliModel"}, tmp_path)
    assert times["target"] == "surrogate.models.ecoli.kernel:precompile"
    assert 0 < times["cached_s"] < times["cold_s"]
    assert any(tmp_path.rglob("*.nbi"))  # the first process filled the given cache


@pytest.mark.parametrize("quick", [False, True])
def test_shipped_bench_lookup_size_fits_the_default_inputs(compose_cfg, quick: bool) -> None:
    from surrogate.benchmarks.machine import bench_settings
    from surrogate.config import to_dict
    from surrogate.stages.settings import TrainSettings

    cfg = compose_cfg("bench", [f"quick={str(quick).lower()}"])
    settings = bench_settings(cfg)
    inputs = TrainSettings.from_config(to_dict(cfg)).inputs
    from surrogate.config import grid_size

    size = grid_size(settings["lookup_size"], "lookup_size", len(inputs))
    assert size is None or len(size) == len(inputs), (size, inputs)


def _table() -> PsiLookupTable:
    mm, ll = torch.meshgrid(torch.linspace(0, 6, 64), torch.linspace(0, 0.1, 64), indexing="ij")
    z = 3 * (mm - 2.2 - 10 * ll)
    values = torch.stack([0.5 * torch.sigmoid(z), torch.sigmoid(z)])
    return PsiLookupTable(values, [(0, 6), (0, 0.1)], ("m", "L"))


def _abstract() -> AbstractDecision:
    table = _table()
    return AbstractDecision(table, MODEL.internal, MODEL.featurizer(table.input_names))


def test_compile_failure_falls_back_to_eager(monkeypatch) -> None:
    def broken(fn, *args, **kwargs):
        def call(*a, **k):
            raise RuntimeError("no compiler here")

        return call

    monkeypatch.setattr(torch, "compile", broken)
    torch.manual_seed(0)
    sim = Simulator(MODEL, _abstract(), GaussianField(), DT, compile=True)
    state = sim.initial_state(100, START)
    with pytest.warns(RuntimeWarning, match="no compiler here"):
        sim.step(state)
    sim.step(state)  # eager from now on, no further warning
    assert "no compiler here" in sim.compile_error
    assert state.step == 2


@pytest.mark.slow
@pytest.mark.parametrize("model", ["full", "lookup"])
def test_compiled_step_computes_what_the_eager_step_computes(model: str) -> None:
    """Same inputs and random numbers through the eager and the torch.compile'd kernel."""
    torch.manual_seed(1)
    decision = FullDecision(MODEL.internal) if model == "full" else _abstract()
    eager = Simulator(MODEL, decision, GaussianField(), DT)
    compiled = Simulator(MODEL, decision, GaussianField(), DT, compile=True)
    state = eager.initial_state(2000, START)
    for _ in range(5):  # some run/tumble history
        eager.step(state)
    u, u64, z, extra = eager.draw_randoms(state.n_cells)
    args = (
        state.body, state.phi.view(torch.uint8), state.segment_steps,
        state.segment_complete.view(torch.uint8), decision.fused_state(), (u, u64, z, extra),
        0.25,
    )  # fmt: skip
    a = eager._run("_fused_step", *args)
    b = compiled._run("_fused_step", *args)
    if compiled.compile_error:
        pytest.skip(f"torch.compile unavailable here: {compiled.compile_error}")
    body_a, body_b = a[0], b[0]
    assert body_a.keys() == body_b.keys() and len(body_a) > 0
    pairs = [(f"body.{k}", body_a[k], body_b[k]) for k in body_a]
    names = ("phi", "segment_steps", "complete", "ended", "inputs")
    pairs += list(zip(names, a[1:6], b[1:6], strict=True))
    for name, x, y in pairs:
        if x.dtype.is_floating_point:
            torch.testing.assert_close(x, y, rtol=1e-5, atol=1e-5, msg=name)
        else:  # a flag may flip only where a uniform lies within round-off of its threshold
            assert (x != y).sum().item() <= 1, name
    assert len(a[6]) == len(b[6]) == (1 if model == "full" else 0)
    for x, y in zip(a[6], b[6], strict=True):  # decision state (motors)
        assert (x != y).sum().item() <= 1
