"""The shared time loop: movement, tumbling, durations, methylation, chemotaxis, with every
decision layer (full model, a known psi, the exact lumped psi)."""

from __future__ import annotations

import math

import numpy as np
import pandas as pd
import pytest
import torch
from scipy import stats

from surrogate.fields import ConstantField, GaussianField
from surrogate.models.ecoli import EcoliModel, adapted_methylation
from surrogate.simulate import (
    AbstractDecision,
    ExactDecision,
    FullDecision,
    Simulator,
    simulate_population,
)

MODEL = EcoliModel()
DT = 0.05


def constant_psi(p_from_0: float, p_from_1: float):
    """A run probability that depends on the origin state only: p(phi' = 1 | phi)."""

    def psi(phi: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
        return torch.where(phi.reshape(-1) > 0, p_from_1, p_from_0).to(torch.float32)

    return psi


def abstract(model: EcoliModel, p_from_0: float, p_from_1: float) -> AbstractDecision:
    return AbstractDecision(constant_psi(p_from_0, p_from_1), model.internal)


def test_always_run_moves_straight_at_speed() -> None:
    torch.manual_seed(0)
    sim = Simulator(MODEL, abstract(MODEL, 1.0, 1.0), GaussianField(), dt=DT)
    state = sim.initial_state(256, (2.0, 0.0))
    heading0 = state.body["heading"].clone()
    for _ in range(200):  # 10 s
        sim.step(state)
    # every cell ran 10 s at 20 um/s along its initial heading: exactly 0.2 mm in a straight line
    expected = torch.tensor([2.0, 0.0]) + 0.2 * torch.stack(
        [torch.cos(heading0), torch.sin(heading0)], -1
    )
    assert torch.allclose(state.body["position"], expected, atol=1e-5)
    assert torch.equal(state.body["heading"], heading0)


def test_always_tumble_stays_put_and_turns_by_gamma_angles() -> None:
    torch.manual_seed(1)
    sim = Simulator(MODEL, abstract(MODEL, 0.0, 0.0), GaussianField(), dt=DT)
    state = sim.initial_state(20_000, (2.0, 0.0))
    start, h0 = state.body["position"].clone(), state.body["heading"].clone()
    sim.step(state)
    assert torch.equal(state.body["position"], start)
    turn = torch.remainder(state.body["heading"] - h0 + math.pi, 2 * math.pi) - math.pi
    deg = torch.rad2deg(turn.abs()).double().numpy()
    # |turn| is the Gamma(4, 18.32 deg) angle folded onto [0, 180]: P(|turn| <= x) =
    # G(x) + 1 - G(360 - x) (angles above 360 deg have probability ~1e-9). KS at alpha = 0.01.
    gamma = stats.gamma(4, scale=18.32)
    ks = stats.kstest(deg, lambda x: gamma.cdf(x) + gamma.sf(360 - x))
    assert ks.statistic < 1.63 / math.sqrt(len(deg))
    # random sign: binomial test on the fraction of left turns
    assert stats.binomtest(int((turn > 0).sum()), len(deg)).pvalue > 1e-3


def test_per_tumble_mode_turns_once_per_tumble() -> None:
    torch.manual_seed(2)
    model = EcoliModel(tumble_mode="per_tumble")
    sim = Simulator(model, abstract(model, 0.0, 0.0), GaussianField(), dt=DT)
    state = sim.initial_state(100, (2.0, 0.0))
    state.phi[:] = True
    h0 = state.body["heading"].clone()
    sim.step(state)  # RUN -> TUMBLE: exactly one turn, by a non-zero angle for every cell
    h1 = state.body["heading"].clone()
    assert bool((h1 != h0).all())
    for _ in range(5):  # still tumbling: no further turns
        sim.step(state)
    assert torch.equal(state.body["heading"], h1)


def test_run_and_tumble_durations_are_counted_in_windows(tmp_path) -> None:
    # phi alternates deterministically: RUN for 3 windows, TUMBLE for 2 (a known pattern)
    pattern = [True, True, True, False, False] * 12

    class Scripted:
        name = "scripted"
        fusable = False
        internal = MODEL.internal

        def __init__(self) -> None:
            self.k = 0

        def initialize(self, x):
            return torch.zeros(x.shape[0], dtype=torch.bool)

        def step(self, phi, x, dt):
            out = torch.full_like(phi, pattern[self.k])
            self.k += 1
            return out

    sim = Simulator(MODEL, Scripted(), ConstantField(), dt=DT)
    simulate_population(sim, 4, 3.0, tmp_path, record_interval=0.5, progress=False)
    d = pd.read_parquet(tmp_path / "durations.parquet")
    # the first (left-censored) tumble is dropped; then runs of 3 windows and tumbles of 2
    assert set(d[d.kind == "run"].duration.round(6)) == {0.15}
    assert set(d[d.kind == "tumble"].duration.round(6)) == {0.1}
    assert len(d) == 4 * (12 + 11)
    obs = pd.read_parquet(tmp_path / "observables.parquet")
    assert sorted(obs.t.unique()) == pytest.approx([0.5 * k for k in range(7)])


@pytest.mark.parametrize("swap", [False, True])
def test_origin_dependent_psi_gives_geometric_durations(tmp_path, swap: bool) -> None:
    """psi(phi) known: runs last Geometric(1 - p(1|1)) windows, tumbles Geometric(p(1|0)).

    Asking psi for the other origin state (psi of 1 - phi) would give runs of mean
    dt / (1 - 0.3) = 0.071 s instead of 0.5 s: the check cannot pass with a swapped origin.
    """
    p0, p1 = 0.3, 0.9
    decision = abstract(MODEL, p0, p1)
    if swap:  # the mistake this test exists to catch: the layer asks psi of 1 - phi
        inner = decision._psi
        decision._psi = lambda phi, z: inner(1 - phi, z)
    torch.manual_seed(6)
    sim = Simulator(MODEL, decision, ConstantField(), dt=DT)
    simulate_population(sim, 500, 40.0, tmp_path, progress=False)
    d = pd.read_parquet(tmp_path / "durations.parquet")
    ok = True
    for kind, s in (("run", 1 - p1), ("tumble", p0)):
        x = d[d.kind == kind].duration.to_numpy()
        mean, sd = DT / s, DT * math.sqrt(1 - s) / s  # geometric in windows of dt
        z = (x.mean() - mean) / (sd / math.sqrt(len(x)))
        ok = ok and abs(z) < 4.0 and len(x) > 5_000
    assert ok != swap


def test_methylation_follows_the_ou_law_in_the_simulation() -> None:
    """Through the simulator's own step: at constant L the methylation's stationary law is
    N(m0(L), sigma_m^2). Scaling the OU noise by 0 or sqrt(2), or its drift, fails this."""
    torch.manual_seed(7)
    field = ConstantField(0.02)
    sim = Simulator(MODEL, abstract(MODEL, 0.3, 0.9), field, dt=DT)
    state = sim.initial_state(4000, (0.0, 0.0))
    p = MODEL.params
    for _ in range(round(3 * p.tau / DT)):  # decorrelate from the start (3 tau)
        sim.step(state)
    m = state.body["m"].double().numpy()
    m0 = float(adapted_methylation(torch.tensor(0.02, dtype=torch.float64), p))
    n = len(m)
    # mean within 5 s.e.; variance within the chi-square 1e-4 two-sided quantiles
    assert abs(m.mean() - m0) < 5 * p.sigma_m / math.sqrt(n)
    chi2 = (n - 1) * m.var(ddof=1) / p.sigma_m**2
    assert stats.chi2(n - 1).ppf(5e-5) < chi2 < stats.chi2(n - 1).ppf(1 - 5e-5)


def _final_distances(field, n_cells: int, t_end: float, seed: int) -> torch.Tensor:
    torch.manual_seed(seed)
    sim = Simulator(MODEL, FullDecision(MODEL.internal), field, dt=DT)
    state = sim.initial_state(n_cells, (2.0, 0.0), equilibration_time=5.0)
    with torch.no_grad():
        for _ in range(round(t_end / DT)):
            sim.step(state)
    return field.distance_from_peak(state.body["position"])


def test_chemotaxis_towards_the_peak_in_gaussian_field() -> None:
    n = 400
    in_field = _final_distances(GaussianField(), n, 150.0, seed=3)
    control = _final_distances(ConstantField(0.0), n, 150.0, seed=4)
    # one-sided Welch test that cells in L1 end closer to the peak than in a zero field; with
    # 400 cells per arm the s.e. of the difference is ~0.02 mm, so we also require a margin of
    # 0.05 mm (chemotactic drift over 150 s is expected to be a few tenths of a mm)
    diff = control.mean() - in_field.mean()
    t = stats.ttest_ind(control.numpy(), in_field.numpy(), equal_var=False, alternative="greater")
    assert t.pvalue < 1e-3
    assert diff.item() > 0.05


def test_run_tumble_durations_in_zero_field_near_sanity_figures(tmp_path) -> None:
    # ecoli-parameters.md sanity figures (4 motors, Yp* 2.7, L = 0, OU on, dt 0.05): run ~0.48 s,
    # tumble ~0.23 s. They are simulated estimates of unstated precision, so we allow +-20 %;
    # sampling s.e. here is < 1 %.
    torch.manual_seed(5)
    sim = Simulator(MODEL, FullDecision(MODEL.internal), ConstantField(0.0), dt=DT)
    simulate_population(sim, 1000, 60.0, tmp_path, equilibration_time=5.0, progress=False)
    d = pd.read_parquet(tmp_path / "durations.parquet")
    run, tumble = d[d.kind == "run"].duration, d[d.kind == "tumble"].duration
    assert len(run) > 10_000 and len(tumble) > 10_000
    assert run.mean() == pytest.approx(0.48, rel=0.2)
    assert tumble.mean() == pytest.approx(0.23, rel=0.2)


@pytest.mark.parametrize("level", [0.0, 0.05])
def test_exact_psi_chain_follows_the_full_model_at_fixed_inputs(tmp_path, level: float) -> None:
    """The two-state chain driven by the exact lumped psi reproduces the full model's mean run
    and tumble durations at fixed inputs (methylation noise off, so (m, L) stay at the adapted
    point): both within 4.5 combined standard errors, from ~20k segments per model."""
    model = EcoliModel(cv=1e-9)
    means = {}
    for name, decision in (("full", FullDecision(model.internal)),
                           ("exact", ExactDecision(model.internal, DT))):  # fmt: skip
        torch.manual_seed(8)
        sim = Simulator(model, decision, ConstantField(level), dt=DT)
        out = tmp_path / name
        simulate_population(sim, 400, 40.0, out, start=(0.0, 0.0), progress=False)
        d = pd.read_parquet(out / "durations.parquet")
        means[name] = {k: d[d.kind == k].duration.to_numpy() for k in ("run", "tumble")}
    for kind in ("run", "tumble"):
        a, b = means["full"][kind], means["exact"][kind]
        se = math.sqrt(a.var() / len(a) + b.var() / len(b))
        assert len(a) > 5_000 and len(b) > 5_000
        assert abs(a.mean() - b.mean()) < 4.5 * se, (kind, a.mean(), b.mean(), se)


def test_simulator_leaves_the_callers_psi_checks_alone() -> None:
    from surrogate.gp import PsiLookupTable

    table = PsiLookupTable(torch.full((2, 4), 0.5), [(0.0, 1.0)], ("dG",))
    decision = AbstractDecision(table, MODEL.internal, MODEL.featurizer(["dG"]))
    Simulator(MODEL, decision, GaussianField(), dt=DT)
    assert table.check_finite is True
    with pytest.raises(Exception, match="NaN"):
        table(torch.tensor([0]), torch.tensor([[float("nan")]]))


def test_warm_up_does_not_touch_the_random_stream() -> None:
    """Compiling (warm-up) must not draw random numbers: the step after it is the same as
    without it (the warm-up's kernel is eager here, so only the stream can differ)."""
    finals = []
    for warm in (False, True):
        torch.manual_seed(9)
        sim = Simulator(MODEL, FullDecision(MODEL.internal), GaussianField(), dt=DT)
        state = sim.initial_state(50, (2.0, 0.0))
        if warm:
            sim._kernels["_fused_step"] = sim._fused_step  # an "uncompiled compile"
            sim.warm_up(state)
        for _ in range(20):
            sim.step(state)
        finals.append(state.body["position"].clone())
    assert torch.equal(finals[0], finals[1])


def test_bad_field_values_are_named_with_their_time() -> None:
    from surrogate.errors import NumericalError
    from surrogate.fields import Field

    class Negative(Field):
        def __call__(self, position, t):
            return torch.full(position.shape[:-1], -0.01)

    sim = Simulator(MODEL, FullDecision(MODEL.internal), Negative(), dt=DT)
    state = sim.initial_state(10, (2.0, 0.0))
    with pytest.raises(NumericalError, match=r"negative concentrations.*at t=0 s"):
        sim.check_state(state)


def test_methylation_noise_reaches_the_stationary_spread_from_adapted_start() -> None:
    """The initial methylation is drawn from the OU's stationary law (mean m0(L), s.d.
    sigma_m), so the spread is right from the start."""
    torch.manual_seed(10)
    sim = Simulator(MODEL, FullDecision(MODEL.internal), ConstantField(0.0), dt=DT)
    m = sim.initial_state(20_000, (0.0, 0.0)).body["m"].double().numpy()
    p = MODEL.params
    assert np.std(m) == pytest.approx(p.sigma_m, rel=0.03)
