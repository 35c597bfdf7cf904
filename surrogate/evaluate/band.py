"""Travelling-band observables from a run's profiles along the channel (issue 39).

A band of cells consuming an attractant leaves it depleted behind and moves into fresh
attractant ahead. Two positions per record time, from the profiles a run in a grid field keeps
(:mod:`surrogate.simulate.profiles`):

**Front** (:func:`front_position`, the headline): the depletion front, the x where the read
species' y-averaged concentration, relative to its own initial value in that column, crosses
``threshold`` (1/2): the crossing farthest in the band's direction (``+1``: towards larger x)
that has undepleted attractant beyond it, found between the two column centres around it by
linear interpolation. It is robust because the concentration is smooth (diffusion averages
over many cells' uptake), so it needs no smoothing and no choice of region, and it divides by
the initial profile, so a non-uniform initial concentration moves it only where cells took it.
It is NaN while nothing is depleted to half (before the band forms) and once the depletion
reaches the channel's end (no crossing is left inside).

**Peak** (:func:`peak_position`): the band's centre in the density: among the columns beyond
``beyond`` (the initial region, where cells that never joined the band stay), the column of the
largest density after a Gaussian smoothing of ``smooth`` columns' s.d. (so one column's
counting noise does not pick it), then the count-weighted mean x of the unsmoothed counts over
``window`` columns either side of it (sub-column resolution; for a skewed band, the centre of
mass of its top, not the mode). NaN where no cell is beyond ``beyond``.

**Speed** (:func:`band_speed`): the least-squares slope of a position over the record times
where it is finite (optionally from ``t_min``: a band forms first, then travels), with its
standard error ``sqrt(s^2 / sum (t - mean t)^2)`` (s^2: the residuals' variance, n - 2
degrees of freedom). :func:`slope_resolution` is the most a slope can move when every
position is off by at most ``e`` (a column's half-width for a position read off the grid):
``e sum|t - mean t| / sum (t - mean t)^2``, about ``3 e / duration``.

**Mass balance** (:func:`mass_balance_speed`): the speed a front must have when everything
the cells take up comes out of the attractant ahead of it, the band carrying a region emptied
of it along: ``v = U / (A c_ahead)``, with ``U`` the cells' Michaelis-Menten uptake
``sum_j n_j q c_j / (K + c_j)`` (``n_j`` cells in column ``j``, ``c_j`` its y-averaged
concentration, ``q = vmax``), ``A`` the channel's cross-section and ``c_ahead`` the
concentration ahead (the initial profile's largest value). Saturated uptake by ``N`` cells
gives the issue's ``q N / (A c_ahead)``; diffusion only moves the attractant, so the measured
front speed meets it as the depleted profile keeps its shape.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
import pandas as pd
from scipy.ndimage import gaussian_filter1d

from surrogate.grid.species import MOLECULES_PER_NMOL
from surrogate.simulate.profiles import Profiles

__all__ = [
    "BandSpeed",
    "band_speed",
    "band_summary",
    "band_table",
    "front_position",
    "mass_balance_speed",
    "peak_position",
    "slope_resolution",
]


def _oriented(x: np.ndarray, values: np.ndarray, direction: int) -> tuple[np.ndarray, np.ndarray]:
    """``x`` and ``values`` (columns last) with the band's direction towards larger index."""
    if direction not in (1, -1):
        raise ValueError(f"direction must be +1 or -1, got {direction}")
    return (x, values) if direction == 1 else (x[::-1], values[..., ::-1])


def front_position(
    x: np.ndarray,
    concentration: np.ndarray,
    initial: np.ndarray | None = None,
    threshold: float = 0.5,
    direction: int = 1,
) -> np.ndarray:
    """The depletion front per record time (module docstring).

    Args:
        x: ``(n_x,)`` the columns' centres (mm), increasing.
        concentration: ``(T, n_x)`` the read species averaged over y (mM).
        initial: ``(n_x,)`` the reference concentration (default: the first record's); columns
            where it is not positive are never depleted.
        threshold: the fraction of the initial concentration the front is at (0 < f < 1).
        direction: ``+1`` the band travels towards larger x, ``-1`` towards smaller.

    Returns:
        ``(T,)`` the front's x (mm), NaN where there is none inside the channel.
    """
    if not 0.0 < threshold < 1.0:
        raise ValueError(f"threshold must be in (0, 1), got {threshold}")
    c = np.atleast_2d(np.asarray(concentration, dtype=np.float64))
    c0 = c[0] if initial is None else np.asarray(initial, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = np.where(c0 > 0, c / np.where(c0 > 0, c0, 1.0), np.nan)
    xs, r = _oriented(np.asarray(x, dtype=np.float64), ratio, direction)
    n_t, n_x = r.shape
    depleted = r <= threshold  # NaN: never
    found = depleted.any(axis=1)
    last = n_x - 1 - np.argmax(depleted[:, ::-1], axis=1)  # farthest depleted column
    inside = found & (last < n_x - 1)
    i = np.minimum(last, n_x - 2)
    rows = np.arange(n_t)
    r0, r1 = r[rows, i], r[rows, i + 1]  # r0 <= threshold < r1 (or r1 NaN)
    with np.errstate(divide="ignore", invalid="ignore"):
        frac = (threshold - r0) / (r1 - r0)
    position = xs[i] + frac * (xs[i + 1] - xs[i])
    return np.where(inside & np.isfinite(position), position, np.nan)


def peak_position(
    x: np.ndarray,
    counts: np.ndarray,
    beyond: float | None = None,
    smooth: float = 1.0,
    window: int = 5,
    direction: int = 1,
) -> np.ndarray:
    """The band's centre in the density per record time (module docstring).

    Args:
        x: ``(n_x,)`` the columns' centres (mm), increasing.
        counts: ``(T, n_x)`` cells per column.
        beyond: only columns whose centre is beyond this x (mm) in the band's direction count
            (default: every column).
        smooth: the s.d. (columns) of the Gaussian smoothing that finds the peak's column; 0:
            none.
        window: columns either side of the peak's column averaged over for its x.
        direction: ``+1`` the band travels towards larger x, ``-1`` towards smaller.

    Returns:
        ``(T,)`` the peak's x (mm), NaN where no cell is beyond ``beyond``.
    """
    if smooth < 0 or window < 0:
        raise ValueError(f"smooth and window must be >= 0, got {smooth}, {window}")
    xs, n = _oriented(np.asarray(x, dtype=np.float64),
                      np.atleast_2d(np.asarray(counts, dtype=np.float64)), direction)  # fmt: skip
    if beyond is not None:
        ahead = xs > beyond if direction == 1 else xs < beyond
        n = np.where(ahead, n, 0.0)
    smoothed = gaussian_filter1d(n, smooth, axis=1, mode="constant") if smooth > 0 else n
    peak = np.argmax(smoothed, axis=1)
    cols = np.arange(n.shape[1])
    near = np.abs(cols[None, :] - peak[:, None]) <= window
    weight = np.where(near, n, 0.0)
    total = weight.sum(axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        centre = (weight * xs).sum(axis=1) / total
    return np.where(total > 0, centre, np.nan)


@dataclass(frozen=True)
class BandSpeed:
    """A least-squares line through a band's positions over time.

    Attributes:
        speed: the slope (mm/s); NaN with fewer than two finite positions.
        stderr: its standard error (mm/s); NaN with fewer than three.
        intercept: the position at t = 0 (mm).
        n: the positions fitted.
        t_min: the first time fitted (s).
        t_max: the last time fitted (s).
    """

    speed: float
    stderr: float
    intercept: float
    n: int
    t_min: float
    t_max: float

    def as_dict(self) -> dict[str, Any]:
        """The fields, NaN as None (for JSON)."""
        return {k: (None if isinstance(v, float) and not math.isfinite(v) else v)
                for k, v in asdict(self).items()}  # fmt: skip


def band_speed(
    t: np.ndarray, position: np.ndarray, t_min: float | None = None, t_max: float | None = None
) -> BandSpeed:
    """The band's speed: the least-squares slope of ``position`` over ``t`` (module docstring).

    Args:
        t: ``(T,)`` record times (s).
        position: ``(T,)`` positions (mm); NaN ones are left out.
        t_min: fit only from this time on (s).
        t_max: fit only up to this time (s).
    """
    t = np.asarray(t, dtype=np.float64)
    p = np.asarray(position, dtype=np.float64)
    keep = np.isfinite(p) & np.isfinite(t)
    if t_min is not None:
        keep &= t >= t_min
    if t_max is not None:
        keep &= t <= t_max
    t, p = t[keep], p[keep]
    n = int(t.size)
    nan = math.nan
    if n < 2 or np.ptp(t) == 0:
        return BandSpeed(nan, nan, nan, n, float(t.min()) if n else nan,
                         float(t.max()) if n else nan)  # fmt: skip
    dt = t - t.mean()
    sxx = float(dt @ dt)
    slope = float(dt @ (p - p.mean())) / sxx
    intercept = float(p.mean() - slope * t.mean())
    stderr = nan
    if n > 2:
        residual = p - (intercept + slope * t)
        stderr = math.sqrt(float(residual @ residual) / (n - 2) / sxx)
    return BandSpeed(slope, stderr, intercept, n, float(t[0]), float(t[-1]))


def slope_resolution(t: np.ndarray, error: float) -> float:
    """The most a least-squares slope over ``t`` changes when every position changes by at most
    ``error``: ``error sum|t - mean t| / sum (t - mean t)^2`` (mm/s for mm and s)."""
    t = np.asarray(t, dtype=np.float64)
    dt = t - t.mean()
    sxx = float(dt @ dt)
    return float(error * np.abs(dt).sum() / sxx) if sxx > 0 else math.inf


def mass_balance_speed(
    profiles: Profiles, vmax: float, km: float, c_ahead: float | None = None
) -> np.ndarray:
    """The front's speed by mass balance at each record time (module docstring).

    Args:
        profiles: a run's profiles (its cross-section and its read species).
        vmax: the read species' uptake per cell (molecules/s).
        km: its Michaelis constant (mM).
        c_ahead: the concentration ahead of the band (mM; default: the first record's largest).

    Returns:
        ``(T,)`` mm/s: the cells' uptake (nmol/s) over ``A c_ahead`` (nmol/mm).
    """
    if vmax < 0 or km <= 0:
        raise ValueError(f"vmax must be >= 0 and km > 0, got {vmax}, {km}")
    c = np.clip(profiles.read_concentration(), 0.0, None)
    ahead = float(c[0].max()) if c_ahead is None else float(c_ahead)
    area = profiles.cross_section
    if not (ahead > 0 and math.isfinite(area) and area > 0):
        raise ValueError(f"no mass balance without a concentration ahead ({ahead}) and a "
                         f"cross-section ({area} mm^2)")  # fmt: skip
    uptake = (profiles.counts * c / (km + c)).sum(axis=1) * (vmax / MOLECULES_PER_NMOL)
    return uptake / (area * ahead)


def _beyond(profiles: Profiles, direction: int) -> float | None:
    """The far edge, in the band's direction, of the columns the cells fill at the first
    record: the initial region's end."""
    filled = np.flatnonzero(profiles.counts[0])
    if not filled.size:
        return None
    edges = profiles.edges
    return float(edges[filled[-1] + 1]) if direction == 1 else float(edges[filled[0]])


def band_table(
    profiles: Profiles, direction: int = 1, beyond: float | None = None, **peak: Any
) -> pd.DataFrame:
    """``t``, ``front`` and ``peak`` (mm) per record time of a run's profiles: the front of its
    read species and the density's peak beyond ``beyond`` (default: the initial region's far
    edge, :func:`_beyond`); ``peak`` passes ``smooth`` and ``window`` on."""
    x = profiles.centres
    beyond = _beyond(profiles, direction) if beyond is None else beyond
    return pd.DataFrame({
        "t": profiles.t,
        "front": front_position(x, profiles.read_concentration(), direction=direction),
        "peak": peak_position(x, profiles.counts, beyond, direction=direction, **peak),
    })  # fmt: skip


def band_summary(
    profiles: Profiles,
    direction: int = 1,
    t_min: float | None = None,
    uptake: tuple[float, float] | None = None,
    **kwargs: Any,
) -> dict[str, Any]:
    """The band's speed from its front and from its peak (:class:`BandSpeed`, NaN as None), the
    slopes' resolution from the column width (:func:`slope_resolution` with half a column over
    the times each fitted), and the first and last finite positions; with ``uptake`` (the read
    species' ``(vmax, km)``) also ``mass_balance``: :func:`mass_balance_speed`'s mean over the
    records the front's speed was fitted on (and its range there), the speed the front's should
    meet. For a manifest or a report."""
    table = band_table(profiles, direction, **kwargs)
    out: dict[str, Any] = {"direction": direction, "column_width": profiles.width}
    for name in ("front", "peak"):
        fit = band_speed(table["t"].to_numpy(), table[name].to_numpy(), t_min=t_min)
        finite = table.loc[table[name].notna()]
        if t_min is not None:
            finite = finite.loc[finite["t"] >= t_min]
        out[name] = {
            **fit.as_dict(),
            "resolution": slope_resolution(finite["t"].to_numpy(), profiles.width / 2)
            if fit.n >= 2 else None,
            "first": float(finite[name].iloc[0]) if len(finite) else None,
            "last": float(finite[name].iloc[-1]) if len(finite) else None,
        }  # fmt: skip
    if uptake is not None:
        front = out["front"]
        balance = mass_balance_speed(profiles, *uptake)
        fitted = np.zeros(len(profiles.t), dtype=bool)
        if front["n"] >= 2:
            fitted = (table["front"].notna() & (table["t"] >= front["t_min"])
                      & (table["t"] <= front["t_max"])).to_numpy()  # fmt: skip
        values = balance[fitted]
        out["mass_balance"] = {
            "speed": float(values.mean()) if values.size else None,
            "min": float(values.min()) if values.size else None,
            "max": float(values.max()) if values.size else None,
            "n": int(values.size),
        }
    return out
