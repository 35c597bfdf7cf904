"""What every benchmark run starts from: its settings (:func:`bench_settings`), the machine it
runs on (:func:`machine_info`, :func:`read_load`), torch's thread count (:func:`num_threads`) and
the model, field and device a config names (:func:`setup`)."""

from __future__ import annotations

import os
import platform
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from datetime import datetime
from pathlib import Path
from typing import Any

import torch

from surrogate.config import build_field, build_model, resolve_device, to_dict
from surrogate.fields import Field
from surrogate.models.base import Model


def bench_settings(cfg: Mapping[str, Any]) -> dict[str, Any]:
    """Plain settings of a bench config, with ``quick_settings`` applied when ``quick``."""
    data = to_dict(cfg)
    quick = data.pop("quick_settings", {}) or {}
    if data.get("quick"):
        data.update(quick)
    return data


def read_load() -> list[float]:
    """1/5/15-minute load averages (empty where unsupported)."""
    try:
        return [round(v, 2) for v in os.getloadavg()]
    except OSError:
        return []


def machine_info(device: torch.device) -> dict[str, Any]:
    """CPU model, cores, torch threads and versions, device, load."""
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    info: dict[str, Any] = {
        "cpu": cpu,
        "cores": os.cpu_count(),
        "torch_threads": torch.get_num_threads(),
        "torch": torch.__version__,
        "python": platform.python_version(),
        "device": str(device),
        "host": platform.node(),
        "load_average": read_load(),
    }
    if device.type == "cuda":
        info["gpu"] = torch.cuda.get_device_name(device)
    return info


@contextmanager
def num_threads(n: int) -> Iterator[None]:
    """Temporarily set torch's intra-op thread count."""
    before = torch.get_num_threads()
    torch.set_num_threads(int(n))
    try:
        yield
    finally:
        torch.set_num_threads(before)


def sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def setup(
    cfg: Mapping[str, Any],
) -> tuple[dict[str, Any], torch.device, Model, Field, float, dict[str, Any]]:
    """What every benchmark run starts from: its settings, device, model, field and dt (torch
    seeded), and the head of its results (start time, machine, settings)."""
    s = bench_settings(cfg)
    device = resolve_device(cfg.get("device", "cpu"))
    torch.manual_seed(int(cfg["seed"]))
    head = {
        "started": datetime.now().isoformat(timespec="seconds"),
        "machine": machine_info(device),
        "settings": {k: v for k, v in s.items() if k not in ("hydra",)},
    }
    return s, device, build_model(cfg["model"]), build_field(cfg["field"]), float(cfg["dt"]), head


__all__ = ["bench_settings", "machine_info", "num_threads", "read_load", "setup", "sync"]
