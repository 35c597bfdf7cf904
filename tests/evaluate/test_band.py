"""Band position and speed on synthetic profiles of known speed: a depletion front (an erf) and
a density bump (a Gaussian), each within a tolerance derived from the column width and the
record times."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from scipy import stats
from scipy.special import erf

from surrogate.evaluate.band import (
    band_speed,
    band_summary,
    band_table,
    front_position,
    mass_balance_speed,
    peak_position,
    slope_resolution,
)
from surrogate.grid.species import MOLECULES_PER_NMOL
from surrogate.simulate.profiles import Profiles

H = 0.05  # mm, the columns' width
EDGES = np.arange(0.0, 10.0 + H / 2, H)
X = 0.5 * (EDGES[1:] + EDGES[:-1])
T = np.arange(0.0, 20.0 + 0.5, 1.0)  # 21 record times, s
SPEED = 0.3  # mm/s


def erf_front(t: np.ndarray, x0: float, width: float, c0: np.ndarray) -> np.ndarray:
    """``(T, n_x)``: ``c0`` depleted behind a front at ``x0 + SPEED t`` (half of ``c0`` there)."""
    u = (X[None, :] - (x0 + SPEED * t[:, None])) / width
    return c0 * 0.5 * (1.0 + erf(u))


def interpolation_bound(width: float) -> float:
    """The most linear interpolation between centres ``H`` apart moves the half-crossing of an
    erf of ``width``: ``H^2 max|r''| / (8 min|r'|)`` over a column around it,
    ``<= H^3 exp((H / width)^2) / (4 width^2)``."""
    return H**3 * math.exp((H / width) ** 2) / (4 * width**2)


@pytest.mark.parametrize("direction", [1, -1])
def test_the_front_travels_at_its_speed_within_the_interpolations_bound(direction: int) -> None:
    """The front of a non-uniform attractant (so the ratio to the initial profile matters),
    either way along x: every position within linear interpolation's bound at this column
    width; the speed within that bound's slope resolution over the record times."""
    c0 = 0.05 + 0.01 * X  # mM, a gradient
    width = 0.3
    c = erf_front(T, 1.0, width, c0)
    truth = 1.0 + SPEED * T
    if direction == -1:  # the mirror image: the band travels towards smaller x
        c, truth = c[:, ::-1], 10.0 - truth
    pos = front_position(X, c, initial=c0 if direction == 1 else c0[::-1], direction=direction)
    bound = interpolation_bound(width)
    assert bound < 0.01 * H  # far finer than a column: no column-centre estimate passes
    assert np.nanmax(np.abs(pos - truth)) <= bound
    fit = band_speed(T, pos)
    assert fit.n == T.size
    assert abs(fit.speed - direction * SPEED) <= slope_resolution(T, bound)
    assert fit.stderr <= slope_resolution(T, bound)


def test_no_front_before_depletion_or_after_it_leaves_the_channel() -> None:
    """NaN while nothing is depleted to half and once the whole channel is; the first record
    is the default reference."""
    c0 = np.full(X.size, 0.1)
    t = np.array([0.0, 10.0, 40.0])
    c = np.vstack([c0, erf_front(t[1:2], 1.0, 0.3, c0), np.full(X.size, 0.01)])
    pos = front_position(X, c)
    assert math.isnan(pos[0]) and math.isnan(pos[2])
    assert pos[1] == pytest.approx(4.0, abs=interpolation_bound(0.3))
    with pytest.raises(ValueError, match="threshold"):
        front_position(X, c, threshold=1.0)


def bump_counts(
    rng: np.random.Generator | None, n: int, sigma: float, behind: float = 2.0
) -> np.ndarray:
    """``(T, n_x)`` cells per column: ``n`` in a Gaussian bump of s.d. ``sigma`` at
    ``2 + SPEED t`` and ``behind`` times as many left behind in the initial region around
    x = 0.5 (s.d. 0.2 mm; multinomial draws, or the expected counts for ``rng`` None)."""
    out = []
    total = round((1 + behind) * n)
    for t in T:
        p = np.diff(stats.norm.cdf(EDGES, 2.0 + SPEED * t, sigma))
        p = p + behind * np.diff(stats.norm.cdf(EDGES, 0.5, 0.2))
        p = p / p.sum()
        out.append(p * total if rng is None else rng.multinomial(total, p))
    return np.asarray(out, dtype=np.float64)


@pytest.mark.parametrize("noise", [False, True])
def test_the_peak_beyond_the_initial_region_travels_at_its_speed(noise: bool) -> None:
    """Positions within half a column of the truth without noise (the window's centroid lies
    between the peak and its column's centre), within a column with 2e5 cells' counting noise
    (a neighbouring column may win the smoothed maximum; a farther one is 16 s.d. of the noise
    away); the speed within the slope resolution of those errors. Without ``beyond``, the
    larger cluster left behind is the peak."""
    sigma = 0.3
    counts = bump_counts(np.random.default_rng(1) if noise else None, 200_000, sigma)
    truth = 2.0 + SPEED * T
    pos = peak_position(X, counts, beyond=1.3)
    error = H if noise else H / 2
    assert np.max(np.abs(pos - truth)) <= error
    fit = band_speed(T, pos)
    assert abs(fit.speed - SPEED) <= slope_resolution(T, error)
    early = peak_position(X, counts[:1])  # no beyond: the left-behind cluster is larger
    assert abs(early[0] - 0.5) < 2 * H
    assert np.isnan(peak_position(X, counts[:1], beyond=10.0)[0])  # no cell beyond


def test_the_speed_is_least_squares_with_its_standard_error() -> None:
    rng = np.random.default_rng(2)
    p = 1.0 + SPEED * T + rng.normal(0.0, 0.05, T.size)
    p[[0, 5]] = np.nan  # left out
    fit = band_speed(T, p)
    keep = np.isfinite(p)
    ref = stats.linregress(T[keep], p[keep])
    assert fit.n == keep.sum() and fit.t_min == 1.0 and fit.t_max == 20.0
    assert fit.speed == pytest.approx(ref.slope, rel=1e-12)
    assert fit.intercept == pytest.approx(ref.intercept, rel=1e-12)
    assert fit.stderr == pytest.approx(ref.stderr, rel=1e-10)
    late = band_speed(T, p, t_min=10.0)
    assert late.n == 11 and late.t_min == 10.0
    two = band_speed(T[:2], p[1:3])
    assert math.isnan(two.stderr) and math.isfinite(two.speed)
    assert math.isnan(band_speed(T[:1], p[1:2]).speed)
    assert two.as_dict()["stderr"] is None


def test_the_slope_resolution_is_attained_by_the_worst_errors() -> None:
    """Positions off by +-e, the sign of t - mean t, move the slope by exactly the resolution;
    random errors within +-e never move it more."""
    e = H / 2
    worst = SPEED * T + e * np.sign(T - T.mean())
    resolution = slope_resolution(T, e)
    assert band_speed(T, worst).speed - SPEED == pytest.approx(resolution, rel=1e-12)
    assert resolution == pytest.approx(3 * e * (T.size - 1) / ((T[-1] - T[0]) * T.size))
    rng = np.random.default_rng(3)
    for _ in range(200):
        p = SPEED * T + rng.uniform(-e, e, T.size)
        assert abs(band_speed(T, p).speed - SPEED) <= resolution


def profiles_of(counts: np.ndarray) -> Profiles:
    """Profiles of ``counts`` with every cell starting in column 10 (x = 0.5 to 0.55) and the
    attractant, uniform at the start, depleted behind a front at ``1 + SPEED t`` after."""
    counts = counts.round().astype(np.int64)
    n = int(counts[1].sum())
    counts[0] = 0
    counts[0, 10] = n
    c0 = np.full(X.size, 0.1)
    c = erf_front(T, 1.0, 0.3, c0)
    c[0] = c0
    return Profiles(t=T, edges=EDGES, counts=counts, below=np.zeros(T.size),
                    above=np.zeros(T.size), concentration={"s": c}, read="s",
                    n_cells=n)  # fmt: skip


def test_band_table_and_summary_from_profiles() -> None:
    """From a run's profiles: the front of the read species and the peak beyond the columns
    the cells filled at the first record (every cell joined the band); speeds within the
    half-column resolution. With cells left behind, their spread beyond the start's column
    outweighs the band until ``beyond`` leaves them out."""
    profiles = profiles_of(bump_counts(None, 1000, 0.3, behind=0.0))
    table = band_table(profiles)
    assert list(table.columns) == ["t", "front", "peak"]
    assert math.isnan(table["front"][0])  # nothing depleted at the start
    assert np.allclose(table["front"][1:], 1.0 + SPEED * T[1:], atol=interpolation_bound(0.3))
    assert np.allclose(table["peak"][1:], 2.0 + SPEED * T[1:], atol=H / 2)
    left = profiles_of(bump_counts(None, 1000, 0.3, behind=2.0))
    assert (band_table(left)["peak"][1:] < 1.0).all()  # the left-behind cells' edge
    assert np.allclose(band_table(left, beyond=1.3)["peak"][1:], table["peak"][1:], atol=H / 2)
    summary = band_summary(profiles, t_min=1.0)
    for name in ("front", "peak"):
        got = summary[name]
        assert got["n"] == T.size - 1 and got["resolution"] == pytest.approx(
            slope_resolution(T[1:], H / 2))  # fmt: skip
        assert abs(got["speed"] - SPEED) <= got["resolution"]
    assert summary["column_width"] == pytest.approx(H)


def test_mass_balance_speed_is_the_uptake_over_the_attractant_ahead() -> None:
    """``v = sum_j n_j q c_j / (K + c_j) / (A c_ahead)``: cells at K take half their vmax,
    cells where the attractant is gone none, saturated cells all of it; the summary averages
    it over the records the front was fitted on."""
    vmax, km, area = 1.57e5, 0.01, 0.04  # molecules/s, mM, mm^2
    q = vmax / MOLECULES_PER_NMOL  # nmol/s
    profiles = replace(profiles_of(bump_counts(None, 1000, 0.3, behind=0.0)), cross_section=area)
    c = np.zeros((T.size, X.size))
    c[:, :40] = km  # columns 0-39 at K, 40-59 empty, the rest at 10^4 K
    c[:, 60:] = 1e4 * km
    counts = np.zeros((T.size, X.size), dtype=np.int64)
    counts[:, 5], counts[:, 50], counts[:, 100] = 300, 200, 100
    data = replace(profiles, counts=counts, concentration={"s": c})
    want = (300 * q / 2 + 100 * q * 1e4 / (1 + 1e4)) / (area * 1e4 * km)
    assert mass_balance_speed(data, vmax, km) == pytest.approx(np.full(T.size, want), rel=1e-12)
    assert mass_balance_speed(data, vmax, km, c_ahead=km) == pytest.approx(want * 1e4, rel=1e-12)
    # the summary: its mean over the front's fitted records (here one value at every record)
    summary = band_summary(profiles, uptake=(vmax, km))
    balance = summary["mass_balance"]
    fitted = T[1:]  # the front exists from the second record on
    expected = mass_balance_speed(profiles, vmax, km)[1:]
    assert balance["n"] == fitted.size and balance["speed"] == pytest.approx(expected.mean())
    assert summary["front"]["first"] == pytest.approx(1.0 + SPEED * T[1], abs=1e-3)
    with pytest.raises(ValueError, match="cross-section"):
        mass_balance_speed(profiles_of(bump_counts(None, 10, 0.3, behind=0.0)), vmax, km)
    with pytest.raises(ValueError, match="km > 0"):
        mass_balance_speed(data, vmax, 0.0)
