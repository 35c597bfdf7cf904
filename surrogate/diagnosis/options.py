"""The inspection's options, typed: the ``inspect`` keys of ``conf/inspect.yaml`` (their
meaning and defaults are there), validated by the inspect stage's settings and built once at
its entry (:meth:`InspectOptions.from_mapping`)."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, fields
from typing import Any

from surrogate.errors import ConfigError


@dataclass(frozen=True)
class InspectOptions:
    """The ``inspect`` keys, as the stage's settings validated them (values kept as given:
    an integer where the yaml has one, so every figure written from them is unchanged).

    Attributes:
        population_cells: cells per field in the population runs (item 2).
        population_share: the population runs' share of ``t_end``.
        quantiles: ``(low, high)``: the input range, as quantiles of what the population sees.
        grid_points: values of each input on the grid of fixed inputs.
        n_cells: cells per grid point (simulated).
        min_time: the settling run's first horizon (s).
        max_time: its longest horizon (s).
        record_windows: windows of dt recorded at stationarity at the median inputs.
        max_seconds: estimated seconds of simulation for the whole inspection.
        exact_max_states: networks enumerated up to this many states are analysed exactly.
        min_occupancy: a lump true in less than this share (or more than 1 - it) at every
            grid point is refused.
        settle_tolerance: settled: the mean stays within this share (or the noise) of its
            final value.
        burn_in_factor: ``model.burn_in`` recommended at this many times the settling time.
        min_switches: switches per origin the recommended collection gives.
        effect_threshold: an input moving its propensities by less than this share has none.
        markov_alpha: significance of the hazard's dependence on the time since phi changed.
        memory_effect: the relative change of the hazard that counts as memory.
        oscillation_depth: the autocorrelation's dip below which phi oscillates.
        pilot: ``inspect.pilot``: the pilot's measured choice of the chain kind
            (``enabled``, ``n_per_state``, ``n_cells``, ``t_end``;
            :mod:`surrogate.stages.pilot`).
    """

    population_cells: int
    population_share: float
    quantiles: tuple[float, float]
    grid_points: int
    n_cells: int
    min_time: float
    max_time: float
    record_windows: int
    max_seconds: float
    exact_max_states: int
    min_occupancy: float
    settle_tolerance: float
    burn_in_factor: float
    min_switches: int
    effect_threshold: float
    markov_alpha: float
    memory_effect: float
    oscillation_depth: float
    pilot: dict[str, Any]

    @classmethod
    def from_mapping(cls, options: Mapping[str, Any]) -> InspectOptions:
        """The options of a validated ``inspect`` mapping (``InspectSettings.options``).

        Raises:
            ConfigError: a key missing or unknown, named.
        """
        names = [f.name for f in fields(cls)]
        missing = [n for n in names if n not in options]
        unknown = sorted(set(options) - set(names))
        if missing or unknown:
            raise ConfigError(
                "inspect options: "
                + "; ".join(
                    ([f"missing inspect.{', inspect.'.join(missing)}"] if missing else [])
                    + ([f"unknown inspect.{', inspect.'.join(unknown)}"] if unknown else [])
                )
            )
        values = dict(options)
        low, high = values["quantiles"]
        values["quantiles"] = (low, high)
        return cls(**{n: values[n] for n in names})


__all__ = ["InspectOptions"]
