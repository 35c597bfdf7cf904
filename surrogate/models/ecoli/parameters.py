"""Constants of the E. coli chemotaxis model.

Values and sources are listed in ``conf/model/base/ecoli_cell.yaml`` (the cell's constants, shared
by ``model=ecoli`` and ``model=ecoli_phospho``) and ``conf/model/ecoli.yaml`` (``motor_sampler``);
the reference C++ simulator of Sneddon, Pontius & Emonet, PNAS 2012, BHIVE/BHIVE. This dataclass
is the typed, validated form of those configs; its defaults equal them and serve where no config
is read (``EcoliParameters()``, a yaml model's ``body: {kind: chemotaxis}``).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import asdict, dataclass, fields
from typing import Any

from surrogate.errors import ConfigError
from surrogate.validation import known_keys, yaml_hint

TUMBLE_MODES = ("per_step", "per_tumble")
MOTOR_SAMPLERS = ("transition_matrix", "ssa")


def _is_number(value: Any) -> bool:
    """A finite int or float (bool is an int in Python, but `model.mu=true` is a typo)."""
    return isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)


@dataclass(frozen=True)
class EcoliParameters:
    """All constants of the signalling, motor and movement layers (units: mM, uM, s, mm)."""

    # receptor cluster (MWC)
    n_tar: int = 6
    n_tsr: int = 13
    eps0: float = 19.0
    eps1: float = -8.55
    k_tar_off: float = 0.02
    k_tar_on: float = 0.5
    k_tsr_off: float = 100.0
    k_tsr_on: float = 1.0e6
    alpha: float = 6.0
    # motor switching
    omega: float = 1.3
    g0: float = 40.0
    g1: float = 40.0
    k_d: float = 3.06
    # flagella / motor pCTMC
    mu: float = 5.0
    n_motors: int = 4
    motor_sampler: str = "transition_matrix"
    # methylation (OU)
    yp_adapted: float = 2.7
    cv: float = 0.1
    tau: float = 15.0
    m_min: float = 0.0
    m_max: float = 8.0
    # movement
    speed: float = 0.02
    tumble_shape: float = 4.0
    tumble_scale_deg: float = 18.32
    tumble_mode: str = "per_step"

    def __post_init__(self) -> None:
        positive = [
            "n_tar", "n_tsr", "k_tar_off", "k_tar_on", "k_tsr_off", "k_tsr_on", "alpha", "omega",
            "k_d", "mu", "n_motors", "cv", "tau", "speed", "tumble_shape", "tumble_scale_deg",
        ]  # fmt: skip
        for f in fields(self):
            value = getattr(self, f.name)
            if f.type in ("int", "float") and not _is_number(value):
                # checked first, so the range checks below never compare a string or a bool
                raise ConfigError(f"model.{f.name} must be a finite number, got {value!r}"
                                  f"{yaml_hint(value)}")  # fmt: skip
        for name in positive:
            value = getattr(self, name)
            if not value > 0:
                raise ConfigError(f"model.{name} must be a positive number, got {value!r}")
        if not 0 < self.yp_adapted < self.alpha:
            raise ConfigError(
                f"model.yp_adapted must lie in (0, model.alpha={self.alpha}) uM, got {self.yp_adapted!r}"
            )
        if not self.m_min < self.m_max:
            raise ConfigError(
                f"model.m_min ({self.m_min}) must be below model.m_max ({self.m_max})"
            )
        if self.tumble_mode not in TUMBLE_MODES:
            raise ConfigError(
                f"model.tumble_mode must be one of {TUMBLE_MODES}, got {self.tumble_mode!r}"
            )
        if self.motor_sampler not in MOTOR_SAMPLERS:
            raise ConfigError(
                f"model.motor_sampler must be one of {MOTOR_SAMPLERS}, got {self.motor_sampler!r}"
            )
        if int(self.n_motors) != self.n_motors:
            raise ConfigError(f"model.n_motors must be an integer, got {self.n_motors!r}")

    @classmethod
    def from_config(cls, cfg: Mapping[str, Any]) -> EcoliParameters:
        """Build from a ``model`` config group, refusing unknown keys (typos) by name."""
        data = {k: v for k, v in dict(cfg).items() if not k.startswith("_") and k != "name"}
        return cls(**known_keys(data, sorted(f.name for f in fields(cls)), "model"))

    def to_dict(self) -> dict[str, Any]:
        """Plain dict of all constants (for manifests)."""
        return asdict(self)

    # derived constants --------------------------------------------------------------------
    @property
    def sigma_m(self) -> float:
        """Stationary s.d. of methylation: cv / (|eps1| (1 - Yp*/alpha)) (~0.0213 by default)."""
        return self.cv / (abs(self.eps1) * (1.0 - self.yp_adapted / self.alpha))

    @property
    def delta_g_adapted(self) -> float:
        """Free-energy difference dG at the adapted CheY-P level Yp*."""
        x = self.yp_adapted / (self.yp_adapted + self.k_d)
        return self.g0 / 4.0 - self.g1 / 2.0 * x

    @property
    def cw_bias_adapted(self) -> float:
        """Steady-state CW motor bias mb0 = k- / (k+ + k-) at Yp* (~0.223 by default)."""
        return 1.0 / (1.0 + math.exp(2.0 * self.delta_g_adapted))

    @property
    def tumble_mean_deg(self) -> float:
        """Mean tumble angle in degrees (shape * scale)."""
        return self.tumble_shape * self.tumble_scale_deg
