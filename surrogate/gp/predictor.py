"""The pair of GP classifiers psi_0 (origin phi = 0) and psi_1 (origin phi = 1) as one callable
over the abstraction's declared input columns."""

from __future__ import annotations

import os
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import pandas as pd
import torch
from torch import Tensor

from surrogate.errors import ArtefactError, NumericalError
from surrogate.gp.fast import CachedPsi
from surrogate.gp.fitted import PREDICT_CHUNK, FittedClassifier
from surrogate.gp.settings import GPSettings
from surrogate.gp.training import fit_classifiers
from surrogate.gp.windows import row_windows
from surrogate.io import load_tensors, save_tensors

STATE_FORMAT = "surrogate.gp.psi/2"
LABELS = ("phi", "phi_next")

Domain = dict[str, tuple[float, float]]
#: inputs read on a log axis: name -> knee (s), each read as log(1 + value / knee)
Warps = dict[str, float]


def log_warp(z: Tensor, input_names: Sequence[str], warps: Mapping[str, float]) -> Tensor:
    """``z`` (``n x d``, columns ``input_names``) with each warped column read as
    ``log(1 + value / knee)`` (``warps``: name -> knee): linear below the knee, compressed
    beyond, so equal-width bins and one lengthscale resolve short values finely and long ones
    coarsely (a switch clock with a long cap, ``gp.clock_knee``). ``z`` itself when none is."""
    if not warps:
        return z
    knees = torch.tensor([warps.get(n, 1.0) for n in input_names], dtype=z.dtype, device=z.device)
    warped = torch.tensor([n in warps for n in input_names], device=z.device)
    return torch.where(warped, torch.log1p(z.clamp(min=0.0) / knees), z)


class PsiClassifier:
    """psi_phi(z) = p(phi' = 1 | phi, z): the pair of GP classifiers of a two-state abstraction.

    Args:
        psi_0: classifier trained on transitions from phi = 0 (e.g. TUMBLE).
        psi_1: classifier trained on transitions from phi = 1 (e.g. RUN).
        input_names: the names of the ``d`` input columns ``z`` (saved with the artefact, so a
            simulation can compute them from the model's inputs).
        domain: ``{name: (min, max)}`` of the training inputs, so users can tell when a
            simulation queries the abstraction outside the data it was fitted on.
        lump_names: names of phi = 0 and 1 (e.g. ``("tumble", "run")``), for reports.
        warps: inputs the classifiers read on a log axis (name -> knee, :func:`log_warp`);
            callers pass raw values, the domain is the raw values'.
        chunk_size: rows per GP evaluation, bounding memory (about ``chunk_size * M`` floats).

    Example:
        >>> psi = fit_psi(table, ("dG",))                     # doctest: +SKIP
        >>> psi(torch.tensor([0, 1]), torch.tensor([[0.6], [0.6]]))   # doctest: +SKIP
        tensor([0.2491, 0.9033])
    """

    def __init__(
        self,
        psi_0: FittedClassifier,
        psi_1: FittedClassifier,
        input_names: tuple[str, ...] | list[str],
        domain: Domain | None = None,
        lump_names: tuple[str, str] = ("0", "1"),
        chunk_size: int = PREDICT_CHUNK,
        warps: Mapping[str, float] | None = None,
    ) -> None:
        if psi_0.device != psi_1.device:
            raise ValueError(
                f"psi_0 and psi_1 must be on the same device, got {psi_0.device} and {psi_1.device}"
            )
        self.psi_0 = psi_0
        self.psi_1 = psi_1
        self.input_names = tuple(input_names)
        self.domain: Domain = dict(domain) if domain else {}
        self.lump_names = (str(lump_names[0]), str(lump_names[1]))
        self.chunk_size = int(chunk_size)
        self.warps: Warps = {str(k): float(v) for k, v in (warps or {}).items()}
        unknown = sorted(set(self.warps) - set(self.input_names))
        if unknown or not all(v > 0 for v in self.warps.values()):
            raise ValueError(f"warps {self.warps} must name inputs of {self.input_names} "
                             f"with knees > 0")  # fmt: skip
        self.check_finite = True

    @property
    def classifiers(self) -> tuple[FittedClassifier, FittedClassifier]:
        """(psi_0, psi_1), indexed by the origin phi."""
        return self.psi_0, self.psi_1

    @property
    def device(self) -> torch.device:
        """Device of the models."""
        return self.psi_1.device

    def to(self, device: torch.device | str) -> PsiClassifier:
        """Move both classifiers to ``device`` in place; return self."""
        self.psi_0.to(device)
        self.psi_1.to(device)
        return self

    @torch.no_grad()
    def __call__(self, phi: Tensor, z: Tensor) -> Tensor:
        """p(phi' = 1) for each row (``z``: ``n x d``), float32 on the input's device.

        NaN/inf inputs raise :class:`NumericalError` while ``check_finite`` is true (a host
        sync per call).
        """
        z = self._inputs(z)
        if self.check_finite and not bool(torch.isfinite(z).all()):
            raise NumericalError(f"PsiClassifier got NaN or infinite inputs {self.input_names}")
        return self.evaluate(phi, z)

    def _inputs(self, z: Tensor) -> Tensor:
        d = len(self.input_names)
        if z.dim() == 1 and d == 1:
            z = z.reshape(-1, 1)
        if z.dim() != 2 or z.shape[1] != d:
            raise ValueError(
                f"psi takes {len(self.input_names)} input column(s) {self.input_names}, got "
                f"{z.shape[1]}"
            )
        return z

    @torch.no_grad()
    def evaluate(self, phi: Tensor, z: Tensor) -> Tensor:
        """:meth:`__call__` without the finiteness check.

        Each classifier is evaluated only on its own rows (measured about twice as fast as
        evaluating both on every row and selecting; the cost is one host sync for the
        boolean-mask sizes).
        """
        z = self._inputs(z)
        out_device = z.device
        dev = self.device
        one = phi.to(dev).reshape(-1).bool()
        x = log_warp(z.to(dev, torch.float32), self.input_names, self.warps)
        if one.shape[0] != x.shape[0]:
            raise ValueError(f"phi has {one.shape[0]} rows but the inputs have {x.shape[0]}")
        out = torch.empty(x.shape[0], dtype=torch.float32, device=dev)
        for clf, rows in (
            (self.psi_1, one.nonzero().squeeze(1)),
            (self.psi_0, (~one).nonzero().squeeze(1)),
        ):
            if rows.numel():
                out[rows] = clf.predict_proba(x[rows], self.chunk_size).float()
        return out.to(out_device)

    def tabulator(self) -> Callable[[Tensor, Tensor], Tensor]:
        """The same predictive as a faster function ``(phi, z) -> p`` for many rows at once,
        which :meth:`PsiLookupTable.from_function <surrogate.gp.lookup.PsiLookupTable.from_function>`
        tabulates with: :meth:`CachedPsi.tabulate <surrogate.gp.fast.CachedPsi.tabulate>` (the
        closed form with cached factors, 6-9x faster on a table's grid, equal to float32
        rounding) where the models allow it, else this classifier itself."""
        try:
            return CachedPsi.from_classifier(self).tabulate
        except TypeError:  # a kernel or strategy the closed form does not cover
            return self

    def to_state(self) -> dict[str, Any]:
        """Plain-value export (tensors, numbers, strings, lists, dicts) of both classifiers."""
        return {
            "format": STATE_FORMAT,
            "psi_0": self.psi_0.to_state(),
            "psi_1": self.psi_1.to_state(),
            "input_names": list(self.input_names),
            "lump_names": list(self.lump_names),
            "domain": {k: [float(v[0]), float(v[1])] for k, v in self.domain.items()},
            "chunk_size": self.chunk_size,
            "warps": dict(self.warps),
        }

    @classmethod
    def from_state(
        cls, state: Mapping[str, Any], device: torch.device | str = "cpu"
    ) -> PsiClassifier:
        """Rebuild from :meth:`to_state`; predictions match the original exactly."""
        if state.get("format") != STATE_FORMAT:
            raise ArtefactError(
                f"not a psi classifier state (format {state.get('format')!r}, "
                f"expected {STATE_FORMAT!r}); re-train it with this version"
            )
        try:
            return cls(
                FittedClassifier.from_state(state["psi_0"], device),
                FittedClassifier.from_state(state["psi_1"], device),
                input_names=tuple(state["input_names"]),
                domain={k: (float(v[0]), float(v[1])) for k, v in state["domain"].items()},
                lump_names=tuple(state.get("lump_names", ("0", "1"))),
                chunk_size=int(state.get("chunk_size", PREDICT_CHUNK)),
                warps={str(k): float(v) for k, v in dict(state.get("warps", {})).items()},
            )
        except (KeyError, RuntimeError, ValueError) as exc:
            raise ArtefactError(
                f"psi classifier state is incomplete or inconsistent: {exc}"
            ) from exc


def data_domain(data: pd.DataFrame, columns: Sequence[str]) -> Domain:
    """Min/max of ``columns`` in a transitions table."""
    return {c: (float(data[c].min()), float(data[c].max())) for c in columns}


def fit_psi(  # noqa: PLR0913  # the public fit: its options are keyword-only
    data: pd.DataFrame,
    input_names: Sequence[str],
    settings: GPSettings | None = None,
    progress: bool = True,
    device: torch.device | str = "cpu",
    lump_names: tuple[str, str] = ("0", "1"),
    label: str = "phi_next",
    warps: Mapping[str, float] | None = None,
    *,
    processes: int = 1,
) -> PsiClassifier:
    """Fit psi_0 on rows with ``phi == 0`` and psi_1 on rows with ``phi == 1`` of ``data``.

    Args:
        data: a transitions table with the columns ``input_names``, ``phi`` and ``phi_next``
            (the outcome), e.g. from the collect stage or tracked cells of an experiment;
            where it has ``windows`` (collect.keep_switches), each row counts as that many.
        input_names: the ``d`` input columns the classifiers are functions of.
        settings: GP settings (kernel, inducing points, epochs, ...).
        label: the column trained on: ``phi_next`` (0/1 outcomes) or expected labels in
            [0, 1] such as ``phi_next_expected`` (binned training only); the held-out metrics
            always score the outcomes.
        warps: inputs read on a log axis (name -> knee, :func:`log_warp`): the classifiers
            are fitted, binned and evaluated on the warped values.
        processes: where the two are fitted one after the other (natural gradients, many
            bins), fit them in this many spawned processes instead, each on this process's
            torch threads: the same fits (:func:`~surrogate.gp.training.fit_classifiers`).
            From a script, call it under ``if __name__ == "__main__":`` (a spawned process
            imports the script first, as Python's multiprocessing says).

    Example:
        >>> psi = fit_psi(table, ["dG"], GPSettings(bins=500), label="phi_next_expected")
    """
    input_names = tuple(input_names)
    missing = [c for c in (*input_names, *LABELS, label) if c not in data.columns]
    if missing:
        raise ArtefactError(
            f"transition data lacks column(s) {missing}; it has {list(data.columns)} and needs "
            f"the inputs {list(input_names)} plus {sorted({*LABELS, label})}"
        )
    pairs = []
    for phi in (0, 1):
        rows = data[data["phi"] == phi]
        if len(rows) == 0:
            raise ArtefactError(f"transition data has no rows with phi == {phi} to fit psi_{phi}")
        x = torch.tensor(rows[list(input_names)].to_numpy(dtype="float32"))
        x = log_warp(x, input_names, warps or {})
        y = torch.tensor(rows[label].to_numpy(dtype="float32"))
        outcomes = torch.tensor(rows["phi_next"].to_numpy(dtype="float32"))
        windows = row_windows(rows)  # a collection that keeps every switch: rows weighted
        pairs.append((x, y, outcomes) if windows is None
                     else (x, y, outcomes, torch.tensor(windows, dtype=torch.float32)))  # fmt: skip
    # side by side (one batched GP) where the settings allow; the same steps as one by one
    label = f"psi_0, psi_1 (from {lump_names[0]}, {lump_names[1]})"
    fitted = fit_classifiers(pairs, settings, progress=progress, device=device, desc=label,
                             processes=processes)  # fmt: skip
    return PsiClassifier(
        fitted[0],
        fitted[1],
        input_names,
        domain=data_domain(data, input_names),
        lump_names=lump_names,
        warps=warps,
    )


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


__all__ = ["PsiClassifier", "data_domain", "fit_psi", "load_psi", "log_warp", "save_psi"]
