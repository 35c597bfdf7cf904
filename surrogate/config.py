"""From Hydra configs to objects, with validation up front (before any work starts).

Every check raises :class:`~surrogate.errors.ConfigError` naming the setting and what is allowed.
Models and fields are built here, at the edge, from their config group's ``_target_``; stages
pass the objects down (see :mod:`surrogate.stages.settings`).

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

import copy
import functools
import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import torch
from omegaconf import DictConfig, ListConfig, OmegaConf

from surrogate.errors import ConfigError
from surrogate.fields import BUILTIN_FIELDS, Field
from surrogate.models.base import Model
from surrogate.models.capabilities import check_members

CONF_DIR = Path(__file__).resolve().parents[1] / "conf"


def to_dict(cfg: Any) -> dict[str, Any]:
    """Resolved plain-dict copy of a config (or mapping)."""
    if isinstance(cfg, DictConfig):
        return OmegaConf.to_container(cfg, resolve=True)  # type: ignore[return-value]
    return dict(cfg)


def group_options(group: str) -> list[str]:
    """Names of the configs shipped in ``conf/<group>``."""
    return sorted(p.stem for p in (CONF_DIR / group).glob("*.yaml"))


def available_fields() -> list[str]:
    """Names of the field configs shipped in ``conf/field``."""
    return group_options("field")


@functools.lru_cache(maxsize=256)
def _load_yaml(path: Path, mtime_ns: int) -> dict[str, Any]:
    """A YAML file as a plain dict, parsed once per version of the file (commands and
    identities ask for the same shipped configs hundreds of times in a report)."""
    return to_dict(OmegaConf.load(path))


def _shipped(path: Path) -> dict[str, Any]:
    return copy.deepcopy(_load_yaml(path, path.stat().st_mtime_ns))


def group_config(group: str, name: str) -> dict[str, Any]:
    """The shipped config ``conf/<group>/<name>.yaml`` as a plain dict, composed as Hydra
    composes it when it is selected (``<group>=<name>``): its ``defaults`` list, if it has one,
    merged in order (see :func:`_compose_defaults`)."""
    path = CONF_DIR / group / f"{name}.yaml"
    if not path.exists():
        raise ConfigError(f"unknown {group} {name!r}; available: {group_options(group)}")
    return copy.deepcopy(_composed(group, path, _group_stamp(group)))


def _group_stamp(group: str) -> tuple[tuple[str, int], ...]:
    """Each YAML file of ``conf/<group>`` (nested too) with its modification time: a composed
    config is reused while none of the files it may read has changed."""
    return tuple(sorted((str(p), p.stat().st_mtime_ns) for p in (CONF_DIR / group).rglob("*.yaml")))


@functools.lru_cache(maxsize=256)
def _composed(group: str, path: Path, stamp: tuple[tuple[str, int], ...]) -> dict[str, Any]:
    """:func:`_compose_defaults`, once per version of the group's files (a report's settings
    ask for the same shipped groups ~120 times: 2.9 s of merging each time they are built)."""
    return _compose_defaults(group, path)


def _compose_defaults(group: str, path: Path) -> dict[str, Any]:
    """A group config with its ``defaults`` list applied, for the entries the shipped group
    configs use: another config of the same group (``ecoli``), one in a folder of the group
    merged at the config's own level (``base/ecoli_cell@_here_``), and ``_self_`` (the file's
    own keys; last when not listed, as in Hydra >= 1.1). Later entries override earlier ones.
    """
    data = _shipped(path)
    defaults = data.pop("defaults", None)
    if defaults is None:
        return data
    entries = list(defaults)
    if "_self_" not in entries:
        entries.append("_self_")
    merged: DictConfig | ListConfig = OmegaConf.create()
    for entry in entries:
        if entry == "_self_":
            part = data
        else:
            name, _, package = str(entry).partition("@")
            same_level = package == "_here_" or (package == "" and "/" not in name)
            if not isinstance(entry, str) or not name or name.startswith("/") or not same_level:
                raise ConfigError(
                    f"{path}: defaults entry {entry!r} is not one this reader composes (a config "
                    f"of the group, `folder/name@_here_` or `_self_`)"
                )
            base = CONF_DIR / group / f"{name}.yaml"
            if not base.exists():
                raise ConfigError(f"{path}: defaults entry {entry!r}: no {base}")
            part = _compose_defaults(group, base)
        merged = OmegaConf.merge(merged, part)
    return to_dict(merged)


def field_config(name: str) -> dict[str, Any]:
    """The shipped config of field ``name`` (to rebuild the field an abstraction was trained on)."""
    path = CONF_DIR / "field" / f"{name}.yaml"
    if not path.exists():
        raise ConfigError(f"unknown field {name!r}; available fields: {available_fields()}")
    return _shipped(path)


@functools.lru_cache(maxsize=1)
def _shipped_fields() -> tuple[tuple[str, Any], ...]:
    return tuple((name, _plain(field_config(name))) for name in available_fields())


def field_name(cfg_field: Mapping[str, Any]) -> str:
    """A short name for a field config: the shipped config it equals, its class's ``name``, or
    the target's last part."""
    data = _plain(to_dict(cfg_field))
    for name, shipped in _shipped_fields():
        if shipped == data:
            return name
    target = str(data.get("_target_", ""))
    for name, cls in BUILTIN_FIELDS.items():
        if target == f"{cls.__module__}.{cls.__qualname__}":
            return name
    return target.rsplit(".", 1)[-1] or "field"


def _plain(data: Mapping[str, Any]) -> Any:
    """A comparable form of a config (numbers as floats: ``1`` and ``1.0`` are one setting)."""

    def norm(v: Any) -> Any:
        if isinstance(v, Mapping):
            return {k: norm(x) for k, x in sorted(v.items())}
        if isinstance(v, list | tuple):
            return [norm(x) for x in v]
        if isinstance(v, int | float) and not isinstance(v, bool):
            return float(v)
        return v

    return norm(dict(data))


def _instantiate(cfg: Mapping[str, Any], group: str, what: str) -> Any:
    """``hydra.utils.instantiate`` with errors as ConfigError naming the group's target."""
    from hydra.errors import InstantiationException
    from hydra.utils import instantiate

    data = to_dict(cfg)
    if "_target_" not in data:
        raise ConfigError(
            f"{group} config needs a `_target_` ({what}); got keys {sorted(data)}; shipped "
            f"{group} configs: {group_options(group)}"
        )
    try:
        return instantiate(data, _convert_="all")
    except InstantiationException as exc:
        cause = exc.__cause__
        if isinstance(cause, ConfigError):
            raise cause from None
        raise ConfigError(f"could not build {group} {data.get('_target_')!r}: {exc}") from exc


def build_field(cfg_field: Mapping[str, Any]) -> Field:
    """Instantiate a field from its config (``_target_`` + keyword arguments)."""
    field = _instantiate(cfg_field, "field", "a Field class")
    if not isinstance(field, Field):
        raise ConfigError(
            f"field target {to_dict(cfg_field)['_target_']!r} is not a surrogate.fields.Field"
        )
    return field


def build_model(cfg_model: Mapping[str, Any]) -> Model:
    """Instantiate an agent model from the ``model`` config group (``_target_`` + settings),
    refusing an internal model with a misspelt optional member
    (:func:`~surrogate.models.capabilities.check_members`)."""
    model = _instantiate(cfg_model, "model", "a surrogate.models.Model, e.g. EcoliModel")
    target = to_dict(cfg_model)["_target_"]
    if not isinstance(model, Model):
        raise ConfigError(
            f"model target {target!r} did not return a surrogate.models.Model (got "
            f"{type(model).__name__})"
        )
    internal = getattr(model, "internal", None)  # a model without one fails where it is used
    if internal is not None:
        check_members(internal, f"model target {target!r}")
    return model


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


def seed_setting(cfg: Mapping[str, Any]) -> int:
    """The run's seed: a non-negative integer."""
    seed = cfg.get("seed")
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        raise ConfigError(f"seed must be a non-negative integer, got {seed!r}")
    return seed


def grid_size(value: Any, name: str, axes: int | None = None) -> tuple[int, ...] | None:
    """Integers >= 2 (grid nodes per axis; ``axes`` of them if given), None (the caller's
    default), or a ConfigError naming ``name``. A single integer means the same number on every
    axis."""
    if value is None:
        return None
    if isinstance(value, int) and not isinstance(value, bool) and value >= 2 and axes:
        return (value,) * axes
    ok = (
        not isinstance(value, str | bytes | Mapping)
        and hasattr(value, "__len__")
        and len(value) >= 1
        and all(isinstance(s, int) and not isinstance(s, bool) and s >= 2 for s in value)
    )
    if not ok or (axes is not None and len(value) not in (axes, 1)):
        want = f"{axes} integers" if axes else "integers"
        raise ConfigError(f"{name} must be {want} >= 2 (or one for every axis), got {value!r}")
    sizes = tuple(int(s) for s in value)
    return sizes * axes if axes is not None and len(sizes) == 1 else sizes


def validate_start(
    cfg: Mapping[str, Any], key: str = "start", prefix: str = "", size: int | None = 2
) -> tuple[float, ...]:
    """A start position: ``size`` finite coordinates (the body's ``start_size``, see
    :func:`surrogate.models.capabilities.start_size_of`: two, [x, y] in mm, for the bodies in
    the plane), or any non-empty list of finite numbers where ``size`` is None."""
    start = cfg.get(key)
    want = "two coordinates [x, y] in mm" if size == 2 else (
        f"{size} coordinates" if size else "a non-empty list of coordinates")  # fmt: skip
    try:
        coords = tuple(float(v) for v in start)  # type: ignore[union-attr]
    except (TypeError, ValueError):
        coords = ()
    if not coords or (size is not None and len(coords) != size):
        raise ConfigError(f"{prefix}{key} must be {want}, got {start!r}")
    if not all(math.isfinite(v) for v in coords):
        raise ConfigError(f"{prefix}{key} must be finite, got {start!r}")
    return coords


def seed_everything(seed: int) -> None:
    """Seed torch's global generators (CPU and every CUDA device) for a run (see the module
    docstring for how every stage's draws derive from it)."""
    torch.manual_seed(int(seed))
