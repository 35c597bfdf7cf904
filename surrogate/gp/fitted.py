"""A trained psi classifier: input normalisation (:class:`Normalizer`), prediction and
persistence (:class:`FittedClassifier`)."""

from __future__ import annotations

import copy
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import gpytorch
import torch
from torch import Tensor

from surrogate.gp.model import PsiGP
from surrogate.gp.settings import GPSettings, psi_gp

PREDICT_CHUNK = 65_536
_PAD = 64  # rows; a multiple of every SIMD width, see FittedClassifier._latent_padded


# ----------------------------------------------------------------------------------------------
# normalisation


class Normalizer:
    """Per-column standardisation ``(x - mean) / std`` fitted on the training inputs."""

    def __init__(self, mean: Tensor, std: Tensor) -> None:
        self.mean = mean
        self.std = std

    @classmethod
    def fit(cls, x: Tensor) -> Normalizer:
        """Fit mean and std per column of ``x`` (n, d)."""
        mean = x.mean(dim=0)
        std = x.std(dim=0) if x.shape[0] > 1 else torch.ones_like(mean)
        # A constant column (e.g. training data at a single ligand level) must not divide by 0.
        std = torch.where(std > 0, std, torch.ones_like(std))
        return cls(mean.detach().clone(), std.detach().clone())

    def transform(self, x: Tensor) -> Tensor:
        """Normalise ``x`` (n, d); ``x`` must be on the normaliser's device."""
        return (x - self.mean) / self.std

    def to(self, device: torch.device | str) -> Normalizer:
        """Move to ``device`` in place and return self."""
        self.mean = self.mean.to(device)
        self.std = self.std.to(device)
        return self

    def state_dict(self) -> dict[str, Tensor]:
        """The fitted statistics as CPU tensors."""
        return {"mean": self.mean.detach().cpu().clone(), "std": self.std.detach().cpu().clone()}

    @classmethod
    def from_state_dict(cls, state: Mapping[str, Tensor]) -> Normalizer:
        """Inverse of :meth:`state_dict`."""
        return cls(state["mean"].clone(), state["std"].clone())


# ----------------------------------------------------------------------------------------------
# fitted classifier


@dataclass
class FittedClassifier:
    """A trained GP classifier with everything needed to predict and to rebuild it."""

    model: PsiGP
    likelihood: gpytorch.likelihoods.BernoulliLikelihood
    normaliser: Normalizer
    settings: GPSettings
    history: list[float] = field(default_factory=list)
    validation: dict[str, Any] | None = None
    #: the fit against its own training rows (:func:`surrogate.gp.own_rows.own_rows_check`)
    own_rows: dict[str, Any] | None = None
    n_train: int = 0
    n_val: int = 0
    train_seconds: float = 0.0

    @property
    def device(self) -> torch.device:
        """Device holding the model parameters."""
        return self.model.variational_strategy.inducing_points.device

    @property
    def dtype(self) -> torch.dtype:
        """Floating-point type of the model parameters."""
        return self.model.variational_strategy.inducing_points.dtype

    def to(self, device: torch.device | str) -> FittedClassifier:
        """Move model, likelihood and normaliser to ``device`` in place; return self.

        GPyTorch's memoised predictive terms (the inducing points' Cholesky factor ...) are
        plain attributes that ``Module.to`` does not move: they are dropped, else a model
        fitted on CUDA and moved to the CPU solves against a CUDA factor (measured on an H200:
        train's psi grid failed, "Expected all tensors to be on the same device")."""
        self.model.to(device)
        self.likelihood.to(device)
        self.normaliser.to(device)
        self.model.variational_strategy._clear_cache()
        return self

    @torch.no_grad()
    def latent(self, x: Tensor, chunk_size: int = PREDICT_CHUNK) -> tuple[Tensor, Tensor]:
        """Mean and variance of the latent f at raw (un-normalised) inputs ``x`` (``n x d``)."""
        n = x.shape[0]
        mu, var = self._latent_padded(x, chunk_size)
        return mu[:n], var[:n]

    @torch.no_grad()
    def predict_proba(self, x: Tensor, chunk_size: int = PREDICT_CHUNK) -> Tensor:
        """p(y = 1 | x) for raw inputs ``x`` (``n x d``), on the model's device.

        The Bernoulli-probit predictive integrated over the latent posterior in closed form:
        E[Phi(f)] = Phi(mu / sqrt(1 + var)) for f ~ N(mu, var). Evaluated in chunks of
        ``chunk_size`` rows to bound memory; on the CPU a row's result does not depend on the
        chunk size or on the other rows in the call (see ``_latent_padded``).
        """
        n = x.shape[0]
        mu, var = self._latent_padded(x, chunk_size)
        return torch.special.ndtr(mu / torch.sqrt(1.0 + var))[:n]

    def _latent_padded(self, x: Tensor, chunk_size: int) -> tuple[Tensor, Tensor]:
        """Latent mean/variance for ``x`` padded to a multiple of ``_PAD`` rows.

        Vectorised CPU kernels (exp, erfc) and BLAS round a short remainder differently from
        full SIMD blocks, so without padding the last rows of a call would change in the last
        bit with the chunk size. Padding every chunk to a multiple of ``_PAD`` rows (repeating
        the last row) keeps each row on the same code path; the padded rows are cut off later.
        """
        if chunk_size < 1:
            raise ValueError(f"chunk_size must be >= 1, got {chunk_size}")
        self.model.eval()
        self.likelihood.eval()
        x = x.to(device=self.device, dtype=self.dtype)
        n = x.shape[0]
        if n == 0:
            empty = x.new_empty(0)
            return empty, empty.clone()
        chunk_size = max(_PAD, chunk_size - chunk_size % _PAD)
        n_pad = -n % _PAD
        if n_pad:
            x = torch.cat([x, x[-1:].expand(n_pad, -1)])
        means, variances = [], []
        with gpytorch.settings.fast_pred_var():
            for start in range(0, x.shape[0], chunk_size):
                f = self.model(self.normaliser.transform(x[start : start + chunk_size]))
                means.append(f.mean)
                variances.append(f.variance)
        return torch.cat(means), torch.cat(variances)

    def to_state(self) -> dict[str, Any]:
        """Tensors and plain Python values only, loadable with ``torch.load(weights_only=True)``."""
        return {
            "settings": self.settings.to_dict(),
            "normaliser": self.normaliser.state_dict(),
            "model": {k: v.detach().cpu().clone() for k, v in self.model.state_dict().items()},
            "likelihood": {
                k: v.detach().cpu().clone() for k, v in self.likelihood.state_dict().items()
            },
            "history": [float(v) for v in self.history],
            "validation": copy.deepcopy(self.validation),
            "own_rows": copy.deepcopy(self.own_rows),
            "n_train": int(self.n_train),
            "n_val": int(self.n_val),
            "train_seconds": float(self.train_seconds),
        }

    @classmethod
    def from_state(
        cls, state: Mapping[str, Any], device: torch.device | str = "cpu"
    ) -> FittedClassifier:
        """Rebuild the model from :meth:`to_state` output; predictions are reproduced exactly."""
        settings = GPSettings.from_config(state["settings"])
        model_state = state["model"]
        inducing = model_state["variational_strategy.inducing_points"]
        model = psi_gp(inducing.clone(), settings)
        model.load_state_dict(model_state, strict=True)
        likelihood = gpytorch.likelihoods.BernoulliLikelihood()
        likelihood.load_state_dict(state["likelihood"], strict=True)
        fitted = cls(
            model=model,
            likelihood=likelihood,
            normaliser=Normalizer.from_state_dict(state["normaliser"]),
            settings=settings,
            history=list(state.get("history", [])),
            validation=copy.deepcopy(state.get("validation")),
            own_rows=copy.deepcopy(state.get("own_rows")),
            n_train=int(state.get("n_train", 0)),
            n_val=int(state.get("n_val", 0)),
            train_seconds=float(state.get("train_seconds", 0.0)),
        )
        fitted.to(device)
        fitted.model.eval()
        fitted.likelihood.eval()
        return fitted


__all__ = ["PREDICT_CHUNK", "FittedClassifier", "Normalizer"]
