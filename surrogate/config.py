"""From Hydra configs to objects, with validation up front (before any work starts).

Every check raises :class:`~surrogate.errors.ConfigError` naming the setting and what is allowed.

Seeds: every random draw of a stage follows from the one ``seed`` setting, recorded in each
manifest. A stage calls :func:`seed_everything` (torch's CPU and CUDA generators) before its
first draw; the GP training takes its split, inducing points and minibatches from its own
generator seeded with the same ``seed``; collect's subsample draws a NumPy seed from the torch
stream; evaluate's second full run (the noise floor) uses ``seed + evaluate.noise_seed_offset``
and its duration subsample uses ``seed``; shard i of a sharded population (``shard.count=K``)
uses child i of ``numpy.random.SeedSequence(seed).spawn(K)``. Nothing depends on time, PID or
job number, so parallel jobs (Hydra ``--multirun``, joblib or SLURM launchers) draw independent
streams only when their ``seed`` (or shard index) differs: sweep it explicitly
(``--multirun seed=0,1,2``); jobs with the same settings and seed produce the same artefact in
the same directory (stages that write under :func:`surrogate.io.artefact_lock` take turns).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import torch
from omegaconf import DictConfig, OmegaConf

from surrogate.errors import ConfigError
from surrogate.fields import BUILTIN_FIELDS, Field
from surrogate.models.ecoli import EcoliParameters

CONF_DIR = Path(__file__).resolve().parents[1] / "conf"


def to_dict(cfg: Any) -> dict[str, Any]:
    """Resolved plain-dict copy of a config (or mapping)."""
    if isinstance(cfg, DictConfig):
        return OmegaConf.to_container(cfg, resolve=True)  # type: ignore[return-value]
    return dict(cfg)


def available_fields() -> list[str]:
    """Names of the field configs shipped in ``conf/field``."""
    return sorted(p.stem for p in (CONF_DIR / "field").glob("*.yaml"))


def field_config(name: str) -> DictConfig:
    """The shipped config of field ``name`` (used to rebuild the field an abstraction was trained on)."""
    path = CONF_DIR / "field" / f"{name}.yaml"
    if not path.exists():
        raise ConfigError(f"unknown field {name!r}; available fields: {available_fields()}")
    return OmegaConf.load(path)  # type: ignore[return-value]


def field_name(cfg_field: Mapping[str, Any]) -> str:
    """A short name for a field config: its class's ``name`` or the target's last part."""
    target = str(cfg_field.get("_target_", ""))
    for name, cls in BUILTIN_FIELDS.items():
        if target == f"{cls.__module__}.{cls.__qualname__}":
            if name == "constant" and float(cfg_field.get("value", 0.0)) == 0.0:
                return "zero"
            return name
    return target.rsplit(".", 1)[-1] or "field"


def build_field(cfg_field: Mapping[str, Any]) -> Field:
    """Instantiate a field from its config (``_target_`` + keyword arguments)."""
    from hydra.errors import InstantiationException
    from hydra.utils import instantiate

    data = to_dict(cfg_field)
    if "_target_" not in data:
        raise ConfigError(
            f"field config needs a `_target_` (a Field class); got keys {sorted(data)}; "
            f"built-in fields: {available_fields()}"
        )
    try:
        field = instantiate(data)
    except InstantiationException as exc:
        cause = exc.__cause__
        if isinstance(cause, ConfigError):
            raise cause from None
        raise ConfigError(f"could not build field {data.get('_target_')!r}: {exc}") from exc
    if not callable(field) or not hasattr(field, "distance_from_peak"):
        raise ConfigError(f"field target {data['_target_']!r} is not a surrogate.fields.Field")
    return field


def build_params(cfg_model: Mapping[str, Any]) -> EcoliParameters:
    """Validated model constants from the ``model`` config group."""
    return EcoliParameters.from_config(to_dict(cfg_model))


def resolve_device(name: str) -> torch.device:
    """A torch device, refusing ``cuda`` where CUDA is not available."""
    try:
        device = torch.device(str(name))
    except RuntimeError as exc:
        raise ConfigError(
            f"device={name!r} is not a torch device (use cpu, cuda or cuda:N)"
        ) from exc
    if device.type == "cuda" and not torch.cuda.is_available():
        raise ConfigError(
            f"device={name!r} was asked for but CUDA is not available on this machine; use device=cpu"
        )
    if (
        device.type == "cuda"
        and device.index is not None
        and device.index >= torch.cuda.device_count()
    ):
        raise ConfigError(
            f"device={name!r}: only {torch.cuda.device_count()} CUDA device(s) present"
        )
    if device.type not in ("cpu", "cuda"):
        raise ConfigError(f"device={name!r} is not supported; use cpu or cuda")
    return device


def positive(cfg: Mapping[str, Any], key: str, prefix: str = "", integer: bool = False) -> float:
    """Return ``cfg[key]``, refusing a missing, non-finite or non-positive value."""
    name = f"{prefix}{key}"
    if key not in cfg or cfg[key] is None:
        raise ConfigError(f"{name} is required")
    value = cfg[key]
    if (
        isinstance(value, bool)
        or not isinstance(value, int | float)
        or not math.isfinite(value)
        or value <= 0
    ):
        raise ConfigError(f"{name} must be a positive number, got {value!r}")
    if integer and int(value) != value:
        raise ConfigError(f"{name} must be a positive integer, got {value!r}")
    return value


def non_negative(cfg: Mapping[str, Any], key: str, prefix: str = "") -> float:
    """Return ``cfg[key]``, refusing a negative or non-finite value."""
    value = cfg.get(key)
    if (
        isinstance(value, bool)
        or not isinstance(value, int | float)
        or not math.isfinite(value)
        or value < 0
    ):
        raise ConfigError(f"{prefix}{key} must be a non-negative number, got {value!r}")
    return value


def validate_common(cfg: Mapping[str, Any]) -> None:
    """Checks shared by every stage: dt, seed, device, model constants, field."""
    dt = positive(cfg, "dt")
    seed = cfg.get("seed")
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        raise ConfigError(f"seed must be a non-negative integer, got {seed!r}")
    resolve_device(cfg.get("device", "cpu"))
    params = build_params(cfg["model"])
    # the methylation OU is stepped by Euler-Maruyama: dt >= tau overshoots its drift
    if dt >= params.tau:
        raise ConfigError(
            f"dt={dt:g} s must be smaller than model.tau={params.tau:g} s (the adaptation time, "
            f"stepped by Euler-Maruyama); the paper uses dt=0.05"
        )
    build_field(cfg["field"])


def grid_shape(value: Any, name: str) -> tuple[int, int]:
    """Two integers >= 2 (a grid's nodes in m and L), or a ConfigError naming ``name``."""
    if not (
        not isinstance(value, str | bytes | Mapping)
        and hasattr(value, "__len__")
        and len(value) == 2
        and all(isinstance(s, int) and not isinstance(s, bool) and s >= 2 for s in value)
    ):
        raise ConfigError(f"{name} must be two integers >= 2, got {value!r}")
    return int(value[0]), int(value[1])


def validate_start(
    cfg: Mapping[str, Any], key: str = "start", prefix: str = ""
) -> tuple[float, float]:
    """A start position: two finite coordinates in mm."""
    start = cfg.get(key)
    try:
        x, y = (float(v) for v in start)  # type: ignore[union-attr]
    except (TypeError, ValueError):
        raise ConfigError(
            f"{prefix}{key} must be two coordinates [x, y] in mm, got {start!r}"
        ) from None
    if not (math.isfinite(x) and math.isfinite(y)):
        raise ConfigError(f"{prefix}{key} must be finite, got {start!r}")
    return x, y


def seed_everything(seed: int) -> None:
    """Seed torch's global generators (CPU and every CUDA device) for a run (see the module
    docstring for how every stage's draws derive from it)."""
    torch.manual_seed(int(seed))
