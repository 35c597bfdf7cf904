"""The pair of GP classifiers psi_0 (origin TUMBLE) and psi_1 (origin RUN) as one callable."""

from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import pandas as pd
import torch
from torch import Tensor

from surrogate.errors import ArtefactError, NumericalError
from surrogate.gp.training import PREDICT_CHUNK, FittedClassifier, GPSettings, fit_classifier
from surrogate.io import load_tensors, save_tensors

STATE_FORMAT = "surrogate.gp.psi/1"
COLUMNS = ("m", "L", "phi", "phi_next")

Domain = dict[str, tuple[float, float]]


class PsiClassifier:
    """psi_phi(m, L) = p(phi' = RUN | phi, m, L), with phi = 0 (TUMBLE) or 1 (RUN).

    Args:
        psi_tumble: classifier trained on transitions from TUMBLE (psi_0).
        psi_run: classifier trained on transitions from RUN (psi_1).
        domain: ``{"m": (min, max), "L": (min, max)}`` of the training inputs, so users can tell
            when a simulation queries the surrogate outside the data it was fitted on.
        chunk_size: rows per GP evaluation, bounding memory (about ``chunk_size * M`` floats).
    """

    def __init__(
        self,
        psi_tumble: FittedClassifier,
        psi_run: FittedClassifier,
        domain: Domain | None = None,
        chunk_size: int = PREDICT_CHUNK,
    ) -> None:
        if psi_tumble.device != psi_run.device:
            raise ValueError(
                f"psi_tumble and psi_run must be on the same device, got {psi_tumble.device} "
                f"and {psi_run.device}"
            )
        self.psi_tumble = psi_tumble
        self.psi_run = psi_run
        self.domain: Domain = dict(domain) if domain else {}
        self.chunk_size = int(chunk_size)
        self.check_finite = True

    @property
    def device(self) -> torch.device:
        """Device of the models."""
        return self.psi_run.device

    def to(self, device: torch.device | str) -> PsiClassifier:
        """Move both classifiers to ``device`` in place; return self."""
        self.psi_tumble.to(device)
        self.psi_run.to(device)
        return self

    @torch.no_grad()
    def __call__(self, phi: Tensor, m: Tensor, L: Tensor) -> Tensor:
        """p(RUN at the next step) for each row, float32 on the input's device.

        Each classifier is evaluated only on its own rows (measured about twice as fast as
        evaluating both on every row and selecting with ``torch.where``; the cost is one host
        sync for the boolean-mask sizes). NaN/inf inputs raise :class:`NumericalError` while
        ``check_finite`` is true (the default; the simulation loop turns it off and checks its
        state at record times instead).
        """
        out_device = m.device
        dev = self.device
        run = phi.to(dev).reshape(-1).bool()
        x = torch.stack(
            [m.to(dev, torch.float32).reshape(-1), L.to(dev, torch.float32).reshape(-1)], dim=1
        )
        if run.shape[0] != x.shape[0]:
            raise ValueError(f"phi has {run.shape[0]} rows but m and L have {x.shape[0]}")
        if self.check_finite and not bool(torch.isfinite(x).all()):
            raise NumericalError("PsiClassifier got NaN or infinite inputs (m or L)")
        out = torch.empty(x.shape[0], dtype=torch.float32, device=dev)
        idx_run = run.nonzero().squeeze(1)
        idx_tumble = (~run).nonzero().squeeze(1)
        if idx_run.numel():
            out[idx_run] = self.psi_run.predict_proba(x[idx_run], self.chunk_size).float()
        if idx_tumble.numel():
            out[idx_tumble] = self.psi_tumble.predict_proba(x[idx_tumble], self.chunk_size).float()
        return out.to(out_device)

    def to_state(self) -> dict[str, Any]:
        """Plain-value export (tensors, numbers, strings, lists, dicts) of both classifiers."""
        return {
            "format": STATE_FORMAT,
            "psi_tumble": self.psi_tumble.to_state(),
            "psi_run": self.psi_run.to_state(),
            "domain": {k: [float(v[0]), float(v[1])] for k, v in self.domain.items()},
            "chunk_size": self.chunk_size,
        }

    @classmethod
    def from_state(
        cls, state: Mapping[str, Any], device: torch.device | str = "cpu"
    ) -> PsiClassifier:
        """Rebuild from :meth:`to_state`; predictions match the original exactly."""
        if state.get("format") != STATE_FORMAT:
            raise ArtefactError(
                f"not a psi classifier state (format {state.get('format')!r}, "
                f"expected {STATE_FORMAT!r})"
            )
        try:
            return cls(
                FittedClassifier.from_state(state["psi_tumble"], device),
                FittedClassifier.from_state(state["psi_run"], device),
                domain={k: (float(v[0]), float(v[1])) for k, v in state["domain"].items()},
                chunk_size=int(state.get("chunk_size", PREDICT_CHUNK)),
            )
        except (KeyError, RuntimeError) as exc:
            raise ArtefactError(
                f"psi classifier state is incomplete or inconsistent: {exc}"
            ) from exc


def data_domain(data: pd.DataFrame) -> Domain:
    """Min/max of ``m`` and ``L`` in a transition table."""
    return {c: (float(data[c].min()), float(data[c].max())) for c in ("m", "L")}


def fit_psi(
    data: pd.DataFrame,
    settings: GPSettings | None = None,
    progress: bool = True,
    device: torch.device | str = "cpu",
) -> PsiClassifier:
    """Fit psi_0 on rows with ``phi == 0`` and psi_1 on rows with ``phi == 1`` of ``data``.

    ``data`` has columns ``m``, ``L``, ``phi`` and ``phi_next``; the label is ``phi_next``.
    """
    missing = [c for c in COLUMNS if c not in data.columns]
    if missing:
        raise ArtefactError(f"transition data lacks column(s) {missing}; expected {list(COLUMNS)}")
    fitted = {}
    for phi, name in ((0, "psi_tumble"), (1, "psi_run")):
        rows = data[data["phi"] == phi]
        if len(rows) == 0:
            raise ArtefactError(f"transition data has no rows with phi == {phi} to fit {name}")
        x = torch.tensor(rows[["m", "L"]].to_numpy(dtype="float32"))
        y = torch.tensor(rows["phi_next"].to_numpy(dtype="float32"))
        fitted[name] = fit_classifier(x, y, settings, progress=progress, device=device, desc=name)
    return PsiClassifier(fitted["psi_tumble"], fitted["psi_run"], domain=data_domain(data))


def save_psi(
    path: str | os.PathLike, classifier: PsiClassifier, metadata: Mapping[str, Any]
) -> Path:
    """Write the classifier and a plain ``metadata`` dict atomically to ``path``."""
    return save_tensors(path, {"psi": classifier.to_state(), "metadata": dict(metadata)})


def load_psi(
    path: str | os.PathLike, device: torch.device | str = "cpu"
) -> tuple[PsiClassifier, dict[str, Any]]:
    """Load what :func:`save_psi` wrote (``weights_only``-safe); return (classifier, metadata)."""
    obj = load_tensors(path, made_by="the GP training stage")
    if not isinstance(obj, dict) or "psi" not in obj:
        raise ArtefactError(f"{path} is not a saved psi classifier (no 'psi' entry)")
    try:
        classifier = PsiClassifier.from_state(obj["psi"], device=device)
    except ArtefactError as exc:
        raise ArtefactError(f"{path}: {exc}") from exc
    return classifier, dict(obj.get("metadata", {}))


__all__ = ["PsiClassifier", "data_domain", "fit_psi", "load_psi", "save_psi"]
