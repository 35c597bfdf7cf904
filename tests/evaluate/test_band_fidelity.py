"""Band fidelity: the KS distance from binned counts against scipy's on the same samples, the
critical value against Kolmogorov's law, and the rule on synthetic bands: identical profiles
pass with nothing to report, a band shifted by a few columns fails at sizes that resolve it,
the same band drawn again at another size passes."""

from __future__ import annotations

import math

import numpy as np
import pandas as pd
import pytest
from scipy import stats
from scipy.special import erf

from surrogate.evaluate.band_fidelity import (
    binned_cdf,
    binned_ks,
    compare_profiles,
    judge,
    plot_band_fidelity,
    position_bins,
    summarise_pair,
)
from surrogate.evaluate.ks import ks_c_alpha, ks_critical_value, noise_threshold
from surrogate.simulate.profiles import Profiles

H = 0.02  # mm, the columns' width (experiment=band's)
EDGES = np.linspace(-1.0, 3.0, 201)  # 200 columns of H
X = 0.5 * (EDGES[1:] + EDGES[:-1])
T = np.arange(0.0, 100.0 + 5.0, 10.0)  # 11 record times, s
SPEED = 0.01  # mm/s
WIDTH = 0.15  # mm, the band's s.d.


def bins_of(values: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """``(n_x + 2,)`` counts: below ``edges[0]``, per column ``[e_k, e_k+1)``, at or above the
    last edge (the layout of :func:`position_bins`)."""
    index = np.searchsorted(edges, values, side="right")  # 0: below, n_x + 1: at/above the end
    return np.bincount(index, minlength=edges.size + 1)


def band(n: int, shift: float, seed: int) -> Profiles:
    """A Gaussian band of ``n`` cells at ``shift + SPEED t`` drawn at every record time, with
    the serine depleted behind a front at the same place (an erf, deterministic)."""
    rng = np.random.default_rng(seed)
    centre = shift + SPEED * T
    bins = np.stack([bins_of(rng.normal(c, WIDTH, n), EDGES) for c in centre])
    c = 0.1 * 0.5 * (1.0 + erf((X[None, :] - centre[:, None]) / 0.2))
    c[0] = 0.1  # the first record is the initial profile, the front's reference
    return Profiles(t=T.copy(), edges=EDGES.copy(), counts=bins[:, 1:-1], below=bins[:, 0],
                    above=bins[:, -1], concentration={"serine": c}, read="serine",
                    n_cells=n)  # fmt: skip


def test_the_ks_from_bins_is_scipys_at_the_edges_and_a_lower_bound_of_the_unbinned() -> None:
    """On two samples of different sizes, with cells past either end: the KS from the counts
    equals ``ks_2samp`` on the values moved to their bin's lower edge (the ECDFs then step only
    at the edges), equals the largest gap of the exact ECDFs at the edges, and is at most the
    unbinned ``ks_2samp``."""
    rng = np.random.default_rng(3)
    a, b = rng.normal(0.9, 0.8, 700), rng.normal(1.1, 0.9, 1300)
    assert (a < EDGES[0]).any() and (b >= EDGES[-1]).any()  # the overflow bins are used
    bins_a, bins_b = bins_of(a, EDGES), bins_of(b, EDGES)
    ks = float(binned_ks(bins_a, bins_b))

    def snapped(v: np.ndarray) -> np.ndarray:
        lower = np.concatenate([[EDGES[0] - 1.0], EDGES])  # below the grid: anywhere below
        return lower[np.searchsorted(EDGES, v, side="right")]

    assert ks == pytest.approx(stats.ks_2samp(snapped(a), snapped(b)).statistic, abs=1e-12)
    exact = np.abs((a[:, None] < EDGES).mean(0) - (b[:, None] < EDGES).mean(0)).max()
    assert ks == pytest.approx(exact, abs=1e-12)
    assert ks <= stats.ks_2samp(a, b).statistic + 1e-12
    assert binned_cdf(bins_a).shape == (EDGES.size,)


def test_the_critical_value_is_kolmogorovs_for_two_sizes() -> None:
    """``c(alpha) sqrt((n + m) / (n m))`` with c(alpha) = sqrt(-ln(alpha / 2) / 2): 1.358 at
    5 % (the value the rest of evaluate uses), Kolmogorov's limit law's quantile to its next
    term, 2 exp(-8 c^2) against alpha: 3e-6 relative at 5 %, 2e-5 at 10 %."""
    for alpha, rel in ((0.1, 3e-5), (0.05, 3e-6), (0.01, 1e-7)):
        assert ks_c_alpha(alpha) == pytest.approx(stats.kstwobign.isf(alpha), rel=rel)
    assert ks_c_alpha(0.05) == pytest.approx(1.358, abs=5e-4)
    n, m = 20_000, 100_000
    assert ks_critical_value(n, m, ks_c_alpha(0.05)) == pytest.approx(
        1.3581 * math.sqrt((n + m) / (n * m)), rel=1e-4)  # fmt: skip
    with pytest.raises(ValueError, match="alpha"):
        ks_c_alpha(0.0)


def test_the_rule_takes_the_floor_the_critical_value_and_a_cap() -> None:
    assert float(noise_threshold(0.02, 0.01, 1.5)) == pytest.approx(0.03)
    assert float(noise_threshold(0.001, 0.01, 1.5)) == pytest.approx(0.01)
    assert float(noise_threshold(math.nan, 0.01, 1.5)) == pytest.approx(0.01)  # no floor
    assert float(noise_threshold(0.1, 0.01, 1.5, cap=0.06)) == pytest.approx(0.06)


def test_identical_profiles_are_zero_apart_and_pass() -> None:
    p = band(2000, 0.0, seed=0)
    table = compare_profiles(p, p)
    assert table["t"].tolist() == T.tolist()
    assert (table[["ks", "c_l1", "c_linf"]].to_numpy() == 0).all()
    assert (table["front_diff"].dropna() == 0).all() and table["front_diff"].notna().sum() >= 9
    summary = summarise_pair(table, H)
    assert summary["max_ks"] == 0 and summary["front_rms"] == 0 and summary["speed_diff"] == 0
    assert summary["speed_reference"] == pytest.approx(SPEED, rel=0.05)
    checks = judge(summary, summary)
    assert [c["check"] for c in checks] == ["max_ks", "front_rms", "speed_diff"]
    assert all(c["passed"] for c in checks)


def test_a_shifted_band_fails_where_the_same_band_at_another_size_passes() -> None:
    """The full model at 20,000 cells and its floor (another draw), a candidate at 100,000:
    drawn from the same band it passes every check (densities, not counts, are compared);
    shifted by 0.1 mm (5 columns, 2/3 of the band's s.d.) its KS (0.27) is far above the
    critical value (0.011) and the floor's (0.013), and its front 10 half-columns off (the
    floor's is 0: one deterministic profile), so both fail."""
    full, repeat = band(20_000, 0.0, seed=1), band(20_000, 0.0, seed=2)
    floor = summarise_pair(compare_profiles(full, repeat), H)
    assert floor["max_ks"] < 2 * floor["ks_critical"]
    same = summarise_pair(compare_profiles(full, band(100_000, 0.0, seed=3)), H)
    assert all(c["passed"] for c in judge(same, floor))
    shifted = compare_profiles(full, band(100_000, 0.1, seed=4))
    assert shifted["ks_critical"].iloc[0] == pytest.approx(
        ks_critical_value(20_000, 100_000, ks_c_alpha(0.05)))  # fmt: skip
    checks = {c["check"]: c for c in judge(summarise_pair(shifted, H), floor)}
    assert not checks["max_ks"]["passed"] and checks["max_ks"]["value"] > 0.2
    assert not checks["front_rms"]["passed"]
    assert checks["front_rms"]["value"] == pytest.approx(0.1, abs=H / 2)
    assert checks["speed_diff"]["passed"]  # a shift, not a speed: the fronts stay parallel


def test_runs_on_other_grids_or_times_are_refused() -> None:
    p = band(500, 0.0, seed=0)
    other = Profiles(t=p.t, edges=p.edges * 2, counts=p.counts, below=p.below, above=p.above,
                     concentration=p.concentration, read="serine", n_cells=500)  # fmt: skip
    with pytest.raises(ValueError, match="grids differ"):
        compare_profiles(p, other)
    later = Profiles(t=p.t + 5.0, edges=p.edges, counts=p.counts, below=p.below, above=p.above,
                     concentration=p.concentration, read="serine", n_cells=500)  # fmt: skip
    with pytest.raises(ValueError, match="no record time"):
        compare_profiles(p, later)


def test_the_figure_draws_every_run() -> None:
    full, repeat, cand = band(1000, 0.0, 1), band(1000, 0.0, 2), band(3000, 0.05, 3)
    tables = {
        "full_repeat": compare_profiles(full, repeat),
        "abstract": compare_profiles(full, cand),
    }
    fig = plot_band_fidelity({"full": full, "full_repeat": repeat, "abstract": cand}, tables,
                             "full_repeat", {"abstract": 0.05})  # fmt: skip
    assert len(fig.axes) == 2 and len(fig.axes[0].lines) == 3
    assert isinstance(tables["abstract"], pd.DataFrame)
    assert position_bins(full).shape == (T.size, X.size + 2)
