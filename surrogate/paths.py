"""Settings-derived artefact directories of the stages: collect -> train -> simulate -> evaluate.

A stage's directory is a function of exactly the settings that define its output, so stages
chain without passing paths, reruns find what exists, and sweep jobs never collide.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

from surrogate.config import field_config, field_name, to_dict
from surrogate.io import artefact_dir

COLLECT_CMD = "python scripts/collect.py"
TRAIN_CMD = "python scripts/train.py"
SIMULATE_CMD = "python scripts/simulate.py"


def collect_settings(cfg: Mapping[str, Any]) -> dict[str, Any]:
    """Everything that defines a transitions table."""
    return {
        "model": to_dict(cfg["model"]),
        "field": to_dict(cfg["field"]),
        "dt": float(cfg["dt"]),
        "seed": int(cfg["seed"]),
        "collect": to_dict(cfg["collect"]),
    }


def train_settings(cfg: Mapping[str, Any]) -> dict[str, Any]:
    """Everything that defines a trained abstraction (its data and the GP settings)."""
    return {**collect_settings(cfg), "gp": to_dict(cfg["gp"])}


def collect_dir(cfg: Mapping[str, Any]) -> Path:
    """``data/collect/field=..._dt=..._seed=...-<hash>``."""
    s = collect_settings(cfg)
    label = {"field": field_name(s["field"]), "dt": s["dt"], "seed": s["seed"]}
    return artefact_dir(cfg["data_dir"], "collect", label, s)


def collect_command(cfg: Mapping[str, Any]) -> str:
    """The command that makes the collect artefact this config needs."""
    return (
        f"{COLLECT_CMD} field={field_name(to_dict(cfg['field']))} dt={cfg['dt']} seed={cfg['seed']}"
    )


def train_dir(cfg: Mapping[str, Any]) -> Path:
    """``data/train/field=..._dt=..._kernel=..._inducing=..._seed=...-<hash>``."""
    s = train_settings(cfg)
    label = {
        "field": field_name(s["field"]),
        "dt": s["dt"],
        "kernel": s["gp"]["kernel"],
        "inducing": s["gp"]["n_inducing"],
        "seed": s["seed"],
    }
    return artefact_dir(cfg["data_dir"], "train", label, s)


def train_command(cfg: Mapping[str, Any]) -> str:
    """The command that makes the train artefact this config needs."""
    gp = to_dict(cfg["gp"])
    return (
        f"{TRAIN_CMD} field={field_name(to_dict(cfg['field']))} dt={cfg['dt']} seed={cfg['seed']} "
        f"gp.kernel={gp['kernel']} gp.n_inducing={gp['n_inducing']}"
    )


def abstraction_config(cfg: Mapping[str, Any]) -> dict[str, Any]:
    """The train-stage config behind ``decision=abstract``: same settings, but the field the
    abstraction was trained on (``decision.train_field``), which may differ from the simulated one."""
    train_field = str(cfg["decision"]["train_field"])
    current = to_dict(cfg["field"])
    field = current if field_name(current) == train_field else to_dict(field_config(train_field))
    return {**to_dict(cfg), "field": field}


def simulate_settings(cfg: Mapping[str, Any]) -> dict[str, Any]:
    """Everything that defines a population run."""
    s = {
        "model": to_dict(cfg["model"]),
        "field": to_dict(cfg["field"]),
        "decision": to_dict(cfg["decision"]),
        **{k: to_dict(cfg)[k] for k in ("dt", "seed", "n_cells", "t_end", "record_interval",
                                        "start", "equilibration_time", "record_durations")},
    }  # fmt: skip
    if s["decision"]["name"] == "abstract":
        s["abstraction"] = train_settings(abstraction_config(cfg))
    return s


def simulate_dir(cfg: Mapping[str, Any]) -> Path:
    """``data/simulate/<decision>_field=..._dt=..._n=..._T=..._seed=...-<hash>``."""
    s = simulate_settings(cfg)
    return artefact_dir(cfg["data_dir"], "simulate", simulate_label(s), s)


def simulate_label(s: Mapping[str, Any]) -> dict[str, Any]:
    """The readable part of a simulation directory's name, from its settings."""
    return {
        "decision": s["decision"]["name"],
        "field": field_name(s["field"]),
        "dt": s["dt"],
        "n": s["n_cells"],
        "T": s["t_end"],
        "seed": s["seed"],
    }
