"""The gp config group's settings (:class:`GPSettings`) and the untrained model they
describe (:func:`psi_gp`)."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, fields
from typing import Any

from torch import Tensor

from surrogate.errors import ConfigError
from surrogate.gp.model import DEFAULT_MEAN, KERNELS, MEANS, PsiGP
from surrogate.validation import known_keys


@dataclass
class GPSettings:
    """Hyperparameters of one GP classifier (the ``gp`` config group).

    Validated on construction; every error names the offending ``gp.<key>``.
    """

    kernel: str = "rbf"
    ard: bool = True
    n_inducing: int = 100
    learn_inducing: bool = True
    epochs: int = 40
    batch_size: int = 1000
    lr: float = 0.05
    natural_gradient: bool = False
    natural_lr: float = 0.1
    validation_fraction: float = 0.2
    #: equal-width bins per (normalised) input axis, one count for every axis or one per axis
    #: (e.g. ``[500, 25]``: a coarse axis for the switch clock); 0: no binning (minibatches)
    bins: int | tuple[int, ...] = 0
    seed: int = 0
    #: the latent f's prior mean (:data:`~surrogate.gp.model.MEANS`)
    mean: str = DEFAULT_MEAN
    #: the batched binned fit's optimiser: ``adam`` (``epochs`` steps of ``lr``), ``lbfgs``
    #: (at most ``epochs`` L-BFGS iterations with a strong-Wolfe line search, stopping on its own
    #: tolerance; docs/performance.md, "Faster fits: measured") or ``newton`` (q(u) solved
    #: exactly by Newton's method at every step, ``epochs`` Adam steps of ``lr`` on the
    #: hyperparameters; ``natural_gradient`` has no effect there: :mod:`surrogate.gp.newton`);
    #: opt-in, not in the identity of a fit with ``adam``
    optimizer: str = "adam"

    def __post_init__(self) -> None:
        if not isinstance(self.kernel, str) or self.kernel not in KERNELS:
            raise ConfigError(
                f"gp.kernel: unknown kernel {self.kernel!r}; allowed values are {KERNELS}"
            )
        if not isinstance(self.mean, str) or self.mean not in MEANS:
            raise ConfigError(f"gp.mean: unknown mean {self.mean!r}; allowed values are {MEANS}")
        for name in ("ard", "learn_inducing", "natural_gradient"):
            if not isinstance(getattr(self, name), bool):
                raise ConfigError(f"gp.{name} must be true or false, got {getattr(self, name)!r}")
        for name in ("n_inducing", "epochs", "batch_size"):
            _check_int(name, getattr(self, name), minimum=1)
        _check_int("seed", self.seed, minimum=0)
        if isinstance(self.bins, Sequence) and not isinstance(self.bins, str):
            if not self.bins:
                raise ConfigError("gp.bins: give one count for every axis or one per axis, got []")
            self.bins = tuple(_check_int("bins", b, minimum=1) for b in self.bins)
        else:
            _check_int("bins", self.bins, minimum=0)
        for name in ("lr", "natural_lr"):
            value = _check_float(name, getattr(self, name))
            if value <= 0:
                raise ConfigError(f"gp.{name} must be > 0, got {value!r}")
        if not isinstance(self.optimizer, str) or self.optimizer not in OPTIMIZERS:
            raise ConfigError(
                f"gp.optimizer: unknown optimizer {self.optimizer!r}; allowed values are "
                f"{OPTIMIZERS}"
            )
        if self.optimizer != "adam" and not self.bins:
            raise ConfigError(
                f"gp.optimizer={self.optimizer} fits the batched binned GP only: it needs "
                f"gp.bins > 0 (now {self.bins!r}); or set gp.optimizer=adam"
            )
        if self.optimizer == "lbfgs" and self.natural_gradient:
            raise ConfigError(
                "gp.optimizer=lbfgs takes no natural gradient: set gp.natural_gradient=false "
                "(now true), or gp.optimizer=adam"
            )
        value = _check_float("validation_fraction", self.validation_fraction)
        if not 0.0 <= value < 1.0:
            raise ConfigError(f"gp.validation_fraction must lie in [0, 1), got {value!r}")

    @classmethod
    def from_config(cls, mapping: Mapping[str, Any] | None) -> GPSettings:
        """Build settings from a mapping (e.g. a Hydra ``DictConfig``); unknown keys are errors."""
        if mapping is None:
            return cls()
        allowed = [f.name for f in fields(cls)]
        values = known_keys({str(k): v for k, v in dict(mapping).items()}, allowed, "gp")
        # Config files may write 1 for 1.0; store the declared type so the state dict is stable.
        for name in ("lr", "natural_lr", "validation_fraction"):
            v = values.get(name)
            if isinstance(v, int) and not isinstance(v, bool):
                values[name] = float(v)
        return cls(**values)

    def to_dict(self) -> dict[str, Any]:
        """Plain dict of the settings (JSON-able and ``weights_only``-loadable); the default
        optimiser is left out, so fits before ``gp.optimizer`` keep their bytes."""
        out = asdict(self)
        if out["optimizer"] == "adam":
            del out["optimizer"]
        return out


#: the batched binned fit's optimisers (``gp.optimizer``)
OPTIMIZERS = ("adam", "lbfgs", "newton")


def _check_int(name: str, value: Any, minimum: int) -> int:
    if isinstance(value, bool) or not isinstance(value, int):
        raise ConfigError(f"gp.{name} must be an integer, got {value!r}")
    if value < minimum:
        raise ConfigError(f"gp.{name} must be >= {minimum}, got {value!r}")
    return value


def _check_float(name: str, value: Any) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ConfigError(f"gp.{name} must be a number, got {value!r}")
    if not math.isfinite(value):
        raise ConfigError(f"gp.{name} must be finite, got {value!r}")
    return float(value)


def psi_gp(inducing: Tensor, settings: GPSettings) -> PsiGP:
    """The untrained :class:`PsiGP` over ``inducing`` points (``(M, d)``, or ``(B, M, d)``
    batched) that ``settings`` describes: the one place the gp group's model keys (kernel, ard,
    learn_inducing, natural_gradient, mean) reach the model, so a fit and its reload agree."""
    # the Newton fit solves q(u) itself, natural gradient or not: a Cholesky q stores it
    natural = settings.natural_gradient and settings.optimizer != "newton"
    return PsiGP(inducing, kernel=settings.kernel, ard=settings.ard,
                 learn_inducing=settings.learn_inducing, natural=natural,
                 mean=settings.mean)  # fmt: skip


__all__ = ["GPSettings", "psi_gp"]
