"""Advice that runs: every setting the inspector or the verdict prints, checked before it is.

A recommendation is printed as Hydra overrides (``gp=classes gp.class_moves=relaxation``) and,
for a yaml model, keys of the model's yaml (``classes: {auto: {bins: 16}}``). :func:`check_advice`
applies them to the resolved config of the run that measured (the same strings, parsed by
Hydra's own override grammar; a group selection replaces the group by its shipped config as
Hydra composes it, :func:`~surrogate.config.group_config`) and builds the typed settings of
every stage ``scripts/reproduce.py`` would run (collect, train, simulate, evaluate): the
up-front checks each stage makes before any work. What they refuse is never printed as advice.

Building the model is part of those checks: ``classes: auto`` runs its chooser (seeded and
cached on disk, so the next stage reuses it).
"""

from __future__ import annotations

import copy
import logging
from collections.abc import Mapping, Sequence
from typing import Any

import yaml
from omegaconf import DictConfig, OmegaConf

from surrogate.config import CONF_DIR, group_config, to_dict
from surrogate.errors import ConfigError

log = logging.getLogger(__name__)


def apply_overrides(config: Mapping[str, Any], overrides: Sequence[str]) -> dict[str, Any]:
    """``config`` with command-line ``overrides`` applied as Hydra applies them to a composed
    config: ``group=option`` selects a shipped group config; ``key=value`` changes a key that
    exists (else a ConfigError, as Hydra's struct mode refuses it); ``+key=value`` adds one
    that does not; ``++key=value`` sets it either way; ``~key`` deletes it.

    Args:
        config: a resolved config (plain mappings).
        overrides: override strings, e.g. ``["gp=classes", "++model.classes=auto"]``.

    Returns:
        A new plain dict.
    """
    from hydra.core.override_parser.overrides_parser import OverridesParser
    from hydra.errors import HydraException

    try:
        parsed = OverridesParser.create().parse_overrides(list(overrides))
    except HydraException as error:
        raise ConfigError(f"advice {list(overrides)} is no valid override: {error}") from error
    cfg = OmegaConf.create(copy.deepcopy(to_dict(config)))
    for o in parsed:
        key = o.key_or_group
        if o.is_sweep_override():
            raise ConfigError(f"advice {o.input_line!r} is a sweep, not one setting")
        if o.is_delete():
            _delete(cfg, key)
            continue
        value = o.value()
        exists = OmegaConf.select(cfg, key, default=_MISSING) is not _MISSING
        if "." not in key and (CONF_DIR / key).is_dir() and not o.is_add() \
                and not o.is_force_add():  # fmt: skip
            OmegaConf.update(cfg, key, group_config(key, str(value)), merge=False)
        elif o.is_add() and exists:
            raise ConfigError(f"advice {o.input_line!r}: {key} exists already (use {key}=...)")
        elif not o.is_add() and not o.is_force_add() and not exists:
            raise ConfigError(f"advice {o.input_line!r}: {key} is not in the config (Hydra "
                              f"refuses it; +{key}=... adds it)")  # fmt: skip
        else:
            OmegaConf.update(cfg, key, value, merge=False, force_add=True)
    return to_dict(cfg)


_MISSING = object()


def _delete(cfg: Any, key: str) -> None:
    parent, _, leaf = key.rpartition(".")
    node = OmegaConf.select(cfg, parent) if parent else cfg
    if node is None or leaf not in node:
        raise ConfigError(f"advice ~{key}: {key} is not in the config")
    del node[leaf]


def check_advice(
    config: Mapping[str, Any], overrides: Sequence[str], model_yaml: str = ""
) -> str | None:
    """Why ``overrides`` (and ``model_yaml``) applied to ``config`` would be refused before any
    work, or None where every stage of ``scripts/reproduce.py`` accepts them.

    Args:
        config: the resolved config of the run that measured (inspect's or reproduce's).
        overrides: the advice as printed, as override strings.
        model_yaml: keys the advice puts in the model's yaml (``classes: {auto: {bins: 16}}``),
            as printed; they override the model's own (a yaml model's keys given in the
            config override its file's).

    Returns:
        The refusal's message (a ConfigError's), or None.
    """
    from surrogate.stages.settings import ReproduceSettings
    from surrogate.stages.settings.choice import collecting_pending

    try:
        cfg = apply_overrides(config, overrides)
        if model_yaml:
            try:
                keys = OmegaConf.create(model_yaml)
            except yaml.YAMLError as error:
                raise ConfigError(f"advice {model_yaml!r} is not yaml: {error}") from error
            if not isinstance(keys, DictConfig):
                raise ConfigError(f"advice {model_yaml!r} is not yaml keys")
            cfg["model"] = {**cfg["model"], **to_dict(keys)}
        cfg.pop("inspect", None)  # reproduce's keys only: the inspector's are its own
        # a measured choice the advice's collection has not made yet is no refusal: reproduce,
        # the command advised, makes it (its other settings are checked with the rule's chain)
        with collecting_pending():
            settings = ReproduceSettings.from_config(cfg)
            settings.runs()
    except ConfigError as error:
        return str(error)
    return None


def checked(
    config: Mapping[str, Any] | None, overrides: Sequence[str], what: str, model_yaml: str = ""
) -> str | None:
    """:func:`check_advice`, logged where it refuses (``what``: the advice, for the log); None
    where ``config`` is None (nothing to check against) or the advice sets nothing."""
    if config is None or not (overrides or model_yaml):
        return None
    reason = check_advice(config, overrides, model_yaml)
    if reason is not None:
        log.warning("not advising %s (%s): %s", what, " ".join(overrides), reason)
    return reason


__all__ = ["apply_overrides", "check_advice", "checked"]
