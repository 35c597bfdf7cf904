"""The SBML discrete stochastic model test suite (DSMTS), checked as the suite prescribes.

A case is a folder ``cases/stochastic/NNNNN`` of github.com/sbmlteam/sbml-test-suite (LGPL
2.1+): the model (``NNNNN-sbml-l3v1.xml``), its settings (``NNNNN-settings.txt``: start,
duration, steps, the output variables as amounts or concentrations, the accepted ranges) and
the exact (or long-run) mean and standard deviation of every output at ``steps + 1`` evenly
spaced times (``NNNNN-results.csv``). ``n`` independent runs go through the compiled per-cell
SSA (:class:`~surrogate.ctmc.CompiledSSA`; or the batched torch SSA), window by window from one
output time to the next, each run on its own clock for the model's events; at every time and
output the suite's statistics (DSMTS user guide 3.1 and 3.2):

    Z_t = sqrt(n) (mean_t - mu_t) / sigma_t                      in meanRange, e.g. (-3, 3)
    Y_t = sqrt(n / 2) (S_t^2 / sigma_t^2 - 1),  S_t^2 = sum_i (X_t^(i) - mu_t)^2 / n
                                                                 in sdRange, e.g. (-5, 5)

(where sigma_t = 0 every run must equal mu_t). The guide asks for n >= 1,000 (10,000 to see
small errors) and expects a correct simulator to fail a few of the suite's thousands of checks by
chance, so a case that fails once is run again with another seed before it is called a
failure (:func:`run_case_twice`). A model the reader refuses (rate rules, event delays,
packages, ...) is reported with the reader's message, which names the construct.

Example::

    case = DsmtsCase.load("tests/data/dsmts/00001")
    result = run_case(case, n_runs=2000, seed=1)
    result.status, result.max_abs_z, result.max_abs_y    # ('passed', 2.1, 1.7)
"""

from __future__ import annotations

import math
import re
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd
import torch

from surrogate.sbml.errors import SbmlError
from surrogate.sbml.reader import SbmlModel, read_sbml

__all__ = ["DsmtsCase", "DsmtsResult", "run_case", "run_case_twice"]


def _ids(text: str) -> tuple[str, ...]:
    return tuple(v.strip() for v in text.split(",") if v.strip())


def _range(text: str) -> tuple[float, float]:
    lo, hi = (float(v) for v in text.strip().strip("()").split(","))
    return lo, hi


def _columns(results: pd.DataFrame, variables: tuple[str, ...], kind: str) -> pd.DataFrame:
    """``T x V`` expected ``mean`` or ``sd`` of each variable; NaN where the case gives none
    (e.g. no sd for a Cauchy output, or a ln(X) output): those are not checked."""
    nan = np.full(len(results), np.nan)
    return pd.DataFrame({v: results.get(f"{v}-{kind}", nan) for v in variables})


@dataclass(frozen=True)
class DsmtsCase:
    """One case of the suite, as its files give it.

    Attributes:
        id: ``"00001"``.
        directory: the case's folder.
        times: ``(T,)`` output times.
        variables: output ids (species of the model).
        concentration: the outputs reported as concentrations (the others as amounts).
        mean, sd: ``T x V`` expected mean and standard deviation (columns: ``variables``).
        mean_range, sd_range: the accepted ranges of Z and Y.
        synopsis: the model's name in its file (else the case's one-line synopsis).
    """

    id: str
    directory: Path
    times: np.ndarray
    variables: tuple[str, ...]
    concentration: tuple[str, ...]
    mean: pd.DataFrame
    sd: pd.DataFrame
    mean_range: tuple[float, float]
    sd_range: tuple[float, float]
    synopsis: str = ""

    @classmethod
    def load(cls, directory: str | Path) -> DsmtsCase:
        """Read a case folder (``NNNNN-settings.txt``, ``NNNNN-results.csv``, the model)."""
        directory = Path(directory)
        case = directory.name
        settings: dict[str, str] = {}
        for line in (directory / f"{case}-settings.txt").read_text().splitlines():
            key, _, value = line.partition(":")
            settings[key.strip()] = value.strip()
        start, duration = float(settings["start"]), float(settings["duration"])
        steps = int(settings["steps"])
        variables = _ids(settings["variables"])
        results = pd.read_csv(directory / f"{case}-results.csv")
        results.columns = [c.strip() for c in results.columns]
        times = np.linspace(start, start + duration, steps + 1)
        if not np.allclose(results["time"].to_numpy(float), times):
            raise ValueError(f"case {case}: results.csv times differ from the settings' grid")
        # the model's name in the SBML file (e.g. "Birth-death model (001), variant 01"), else
        # the synopsis of the case's description
        found = re.search(r'<model [^>]*name="([^"]+)"', (directory / f"{case}-sbml-l3v1.xml")
                          .read_text())  # fmt: skip
        described = directory / f"{case}-model.m"
        if found is None and described.exists():
            found = re.search(r"synopsis:\s*(.+)", described.read_text())
        synopsis = found.group(1).strip() if found else ""
        return cls(
            id=case,
            directory=directory,
            times=times,
            variables=variables,
            concentration=_ids(settings.get("concentration", "")),
            mean=_columns(results, variables, "mean"),
            sd=_columns(results, variables, "sd"),
            mean_range=_range(settings.get("meanRange", "(-3, 3)")),
            sd_range=_range(settings.get("sdRange", "(-5, 5)")),
            synopsis=synopsis,
        )

    @property
    def model_path(self) -> Path:
        """The case's SBML Level 3 Version 1 file."""
        return self.directory / f"{self.id}-sbml-l3v1.xml"


@dataclass
class DsmtsResult:
    """The outcome of one case.

    Attributes:
        case: the case id.
        status: ``passed``, ``failed`` (a Z or Y outside its range) or ``refused`` (the reader
            refuses the model; ``reason`` names the construct).
        runs: simulated runs ``n``.
        seed: the seed of the runs.
        checks: (time, output) pairs checked for Z and for Y (sigma > 0).
        z_outside, y_outside: how many Z and Y fell outside their ranges.
        max_abs_z, max_abs_y: their largest absolute values.
        reason: why a case failed or was refused.
        seconds: wall time (reading, compiling and simulating).
        retried: the first result, when this is a second run with another seed.
    """

    case: str
    status: str
    runs: int = 0
    seed: int = 0
    checks: int = 0
    z_outside: int = 0
    y_outside: int = 0
    max_abs_z: float = 0.0
    max_abs_y: float = 0.0
    reason: str = ""
    seconds: float = 0.0
    retried: DsmtsResult | None = field(default=None, repr=False)


def _outputs(case: DsmtsCase, model: SbmlModel) -> tuple[list[int], np.ndarray]:
    """Each output's species column and its divisor (compartment size for a concentration)."""
    columns, scale = [], []
    for name in case.variables:
        if name not in model.species:
            raise SbmlError(f"output {name!r} is not a species of the model")
        columns.append(model.species.index(name))
        if name in case.concentration:
            compartment = model.compartment_of(name)
            size = model.constants.get(compartment, math.nan)
            if not (size > 0 and math.isfinite(size)):
                raise SbmlError(f"output {name!r} as a concentration needs a compartment size")
            scale.append(size)
        else:
            scale.append(1.0)
    return columns, np.array(scale)


SSAS = ("compiled", "batched")


def simulate_outputs(
    model: SbmlModel,
    columns: Sequence[int],
    times: np.ndarray,
    n_runs: int,
    seed: int,
    parallel: bool = True,
    ssa: str = "compiled",
) -> np.ndarray:
    """``T x n x V`` outputs of ``n_runs`` independent runs at ``times`` (from ``times[0]``,
    the initial state, events at t = 0 fired), window by window with the compiled SSA
    (``ssa="compiled"``) or the batched torch SSA on the CPU (``"batched"``)."""
    from surrogate.ctmc import CellStreams, CompiledSSA, gillespie
    from surrogate.ctmc.events import EventProgram, start_events

    if ssa not in SSAS:
        raise ValueError(f"ssa must be one of {SSAS}, got {ssa!r}")
    kinetics = model.kinetics
    inputs = torch.zeros((n_runs, 0), dtype=torch.float64)
    state, clock = model.initial_states(n_runs), None
    if kinetics.has_rules_or_events:
        state, clock = start_events(kinetics, state, inputs)
    if ssa == "compiled":
        compiled = CompiledSSA(kinetics, parallel=parallel)
        streams = CellStreams.from_seed(seed, n_runs)
    else:
        generator = torch.Generator().manual_seed(seed)
        program = EventProgram.of(kinetics) if kinetics.has_rules_or_events else None
    out = np.empty((len(times), n_runs, len(columns)))
    out[0] = state[:, list(columns)].numpy()
    for k in range(1, len(times)):
        dt = float(times[k] - times[k - 1])
        if ssa == "compiled":
            state, _ = compiled.advance(state, inputs, dt, streams, clock=clock)
        else:
            state = gillespie(kinetics.network, state, inputs, dt, generator,
                              propensity=kinetics.torch_propensity, events=program,
                              clock=clock)  # fmt: skip
        out[k] = state[:, list(columns)].numpy()
    return out


def statistics(values: np.ndarray, mean: np.ndarray, sd: np.ndarray) -> tuple[np.ndarray, ...]:
    """The suite's Z and Y (``T x V``, NaN where sigma = 0), where sigma = 0 whether a run
    differs from the expected mean, and the spread of Y the outputs' own tails imply.

    Y is N(0, 1) only for normal outputs (the guide's approximation): with known mean its
    variance is (m4 / sigma^4 - 1) / 2, m4 the fourth central moment; for a population near
    extinction (heavy tails) that is far above 1. The last array is that spread, m4 estimated
    from the runs: a diagnostic for the report, not part of the suite's check.

    Args:
        values: ``T x n x V`` simulated outputs.
        mean, sd: ``T x V`` expected mean and standard deviation.
    """
    n = values.shape[1]
    deviation = values - mean[:, None, :]
    with np.errstate(divide="ignore", invalid="ignore"):
        z = math.sqrt(n) * (values.mean(1) - mean) / sd
        s2 = (deviation**2).mean(1)
        y = math.sqrt(n / 2) * (s2 / sd**2 - 1)
        spread = np.sqrt(np.maximum((deviation**4).mean(1) / sd**4 - 1, 0) / 2)
    degenerate = sd == 0
    exact = np.all(np.isclose(values, mean[:, None, :], rtol=1e-9, atol=1e-9), axis=1)
    z[degenerate], y[degenerate], spread[degenerate] = np.nan, np.nan, np.nan
    return z, y, degenerate & ~exact, spread


def run_case(
    case: DsmtsCase, n_runs: int, seed: int, parallel: bool = True, ssa: str = "compiled"
) -> DsmtsResult:
    """Simulate ``n_runs`` runs of ``case`` (with ``ssa``, see :func:`simulate_outputs`) and
    check the suite's Z and Y at every time."""
    t0 = time.perf_counter()
    try:
        model = read_sbml(case.model_path)
        columns, scale = _outputs(case, model)
    except SbmlError as error:
        reason = str(error).replace(f"{case.model_path}: ", "")
        return DsmtsResult(case.id, "refused", reason=reason, seconds=time.perf_counter() - t0)
    values = simulate_outputs(model, columns, case.times, n_runs, seed, parallel, ssa) / scale
    z, y, wrong, spread = statistics(values, case.mean.to_numpy(float), case.sd.to_numpy(float))
    (zlo, zhi), (ylo, yhi) = case.mean_range, case.sd_range
    checked = ~np.isnan(z)
    if not checked.any():
        reason = "the case gives no mean and standard deviation of its outputs to check"
        return DsmtsResult(case.id, "failed", runs=n_runs, seed=seed, reason=reason,
                           seconds=time.perf_counter() - t0)  # fmt: skip
    z_out = int(((z[checked] < zlo) | (z[checked] > zhi)).sum())
    outside = checked & ~np.isnan(y) & ((y < ylo) | (y > yhi))
    y_out = int(outside.sum())
    reasons = []
    if z_out or y_out:
        reasons.append(f"{z_out} Z outside {case.mean_range}, {y_out} Y outside {case.sd_range}")
    if y_out:
        t, v = np.argwhere(outside)[np.argmax(np.abs(y[outside]))]
        reasons.append(
            f"largest Y {y[t, v]:.2f} ({case.variables[v]} at t={case.times[t]:g}), where "
            f"the outputs' own tails give Y a spread of {spread[t, v]:.2f} (1 if normal)"
        )
    if wrong.any():
        t, v = np.argwhere(wrong)[0]
        reasons.append(f"{case.variables[v]} differs from its exact value at t={case.times[t]:g}")
    return DsmtsResult(
        case.id,
        "failed" if reasons else "passed",
        runs=n_runs,
        seed=seed,
        checks=int(checked.sum()),
        z_outside=z_out,
        y_outside=y_out,
        max_abs_z=float(np.nanmax(np.abs(z))) if checked.any() else 0.0,
        max_abs_y=float(np.nanmax(np.abs(y))) if checked.any() else 0.0,
        reason="; ".join(reasons),
        seconds=time.perf_counter() - t0,
    )


def run_case_twice(
    case: DsmtsCase, n_runs: int, seed: int, parallel: bool = True, ssa: str = "compiled"
) -> DsmtsResult:
    """:func:`run_case`; a failure is run once more with ``seed + 1`` (a marginal Z or Y at
    one time is expected now and then of a correct simulator) and the second result, carrying
    the first as ``retried``, decides."""
    first = run_case(case, n_runs, seed, parallel, ssa)
    if first.status != "failed":
        return first
    second = run_case(case, n_runs, seed + 1, parallel, ssa)
    second.retried = first
    return second
