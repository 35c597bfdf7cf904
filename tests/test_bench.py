"""The benchmark runs end to end (a smoke run, no timing asserts), and the fast paths it times
(compiled step, fused decisions) compute what the reference paths compute."""

from __future__ import annotations

import json

import pytest
import torch

from surrogate.bench import format_report, main
from surrogate.fields import GaussianField
from surrogate.gp import PsiLookupTable
from surrogate.models.ecoli import EcoliParameters
from surrogate.simulate import AbstractDecision, FullDecision, Simulator

P = EcoliParameters()


def test_quick_bench_writes_all_sections(compose_cfg, tmp_path) -> None:
    out = tmp_path / "bench.json"
    cfg = compose_cfg("bench", ["quick=true", f"output={out}", "quick_settings.sizes=[50,200]"])
    assert main(cfg) == out
    r = json.loads(out.read_text())
    for key in ("machine", "settings", "abstraction", "collect", "training", "throughput",
                "best_config", "motors", "breakdown", "paper", "memory", "total_s"):  # fmt: skip
        assert key in r, key
    assert {"cpu", "cores", "torch_threads", "device", "load_average"} <= set(r["machine"])
    assert [row["n_cells"] for row in r["throughput"]] == [50, 200]
    for row in r["throughput"]:
        for model in ("full", "lookup", "classifier"):
            assert row[model]["cell_steps_per_s"] > 0
        assert row["ratio_lookup"] > 0 and row["ratio_classifier"] > 0
    assert [row["n_motors"] for row in r["motors"]] == [4, 10]
    assert {run["model"] for run in r["paper"]["runs"]} == {"full", "lookup"}
    assert r["collect"]["seconds"] > 0 and r["training"]["seconds"] > 0
    assert r["training"]["n_per_classifier"] == 300
    assert all(run["peak_rss_mb"] > 0 for run in r["memory"]["runs"])
    assert "trained on the fly" in r["abstraction"]["source"]
    assert "throughput" in format_report(r)


def _table() -> PsiLookupTable:
    mm, ll = torch.meshgrid(torch.linspace(0, 6, 64), torch.linspace(0, 0.1, 64), indexing="ij")
    z = 3 * (mm - 2.2 - 10 * ll)
    return PsiLookupTable(torch.stack([0.5 * torch.sigmoid(z), torch.sigmoid(z)]), (0, 6), (0, 0.1))


def test_compile_failure_falls_back_to_eager(monkeypatch) -> None:
    def broken(fn, *args, **kwargs):
        def call(*a, **k):
            raise RuntimeError("no compiler here")

        return call

    monkeypatch.setattr(torch, "compile", broken)
    torch.manual_seed(0)
    sim = Simulator(AbstractDecision(_table(), P), GaussianField(), P, 0.05, compile=True)
    state = sim.initial_state(100)
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
    decision = FullDecision(P) if model == "full" else AbstractDecision(_table(), P)
    eager = Simulator(decision, GaussianField(), P, 0.05)
    compiled = Simulator(decision, GaussianField(), P, 0.05, compile=True)
    state = eager.initial_state(2000)
    for _ in range(5):  # some run/tumble history
        eager.step(state)
    u, u64, z, angle = eager.draw_randoms(state.n_cells)
    args = (
        state.position, state.heading, state.methylation, state.run.view(torch.uint8),
        state.segment_steps, state.segment_complete.view(torch.uint8),
        decision.fused_state(), u, u64, z, angle, 0.25,
    )  # fmt: skip
    a = eager._run("_fused_step", *args)
    b = compiled._run("_fused_step", *args)
    if compiled.compile_error:
        pytest.skip(f"torch.compile unavailable here: {compiled.compile_error}")
    names = ("position", "heading", "m", "run", "segment_steps", "complete", "ended", "ligand")
    for name, x, y in zip(names, a[:8], b[:8], strict=True):
        if x.dtype.is_floating_point:
            torch.testing.assert_close(x, y, rtol=1e-5, atol=1e-5, msg=name)
        else:  # a flag may flip only where a uniform lies within round-off of its threshold
            assert (x != y).sum().item() <= 1, name
    for x, y in zip(a[8], b[8], strict=True):  # decision state (motors)
        assert (x != y).sum().item() <= 1
