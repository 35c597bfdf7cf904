"""Settings, input normalisation and the training loop for one psi classifier.

Numerical guard (a deliberate choice): when the training loss becomes NaN/inf, or a Cholesky
factorisation fails, training stops, the model is restored to the last state known to be good
(the start of the last epoch whose losses were all finite: the parameters after an epoch's last
step are never evaluated by a loss), and :class:`~surrogate.errors.NumericalError` is raised. The restored model is
attached to the exception as ``exc.partial`` (a :class:`FittedClassifier` without validation
metrics) for inspection, but it is never returned silently: a half-trained surrogate must not
flow into the downstream simulations unnoticed. The message says which epoch failed and which
settings to lower.
"""

from __future__ import annotations

import copy
import logging
import math
import time
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, field, fields
from typing import Any

import gpytorch
import torch
from linear_operator.utils.errors import NanError, NotPSDError
from torch import Tensor
from tqdm.auto import tqdm

from surrogate.errors import ConfigError, NumericalError
from surrogate.gp.metrics import classification_metrics
from surrogate.gp.model import DEFAULT_MEAN, KERNELS, MEANS, PsiGP
from surrogate.validation import known_keys

PREDICT_CHUNK = 65_536
#: classifiers are trained side by side (one batched GP) up to this many occupied bins each:
#: where a step's fixed cost dominates. Measured: 200 bins, 50 inducing points 2.5x faster than
#: one by one; 500 bins (1-D), 100 inducing 1.15x; ~1e5 bins (2-D, 500 per axis) 0.54x
BATCH_MAX_BINS = 4096
_PAD = 64  # rows; a multiple of every SIMD width, see FittedClassifier._latent_padded

log = logging.getLogger(__name__)


# ----------------------------------------------------------------------------------------------
# settings


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
        """Plain dict of the settings (JSON-able and ``weights_only``-loadable)."""
        return asdict(self)


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


def _psi_gp(inducing: Tensor, settings: GPSettings) -> PsiGP:
    """The untrained :class:`PsiGP` over ``inducing`` points (``(M, d)``, or ``(B, M, d)``
    batched) that ``settings`` describes: the one place the gp group's model keys (kernel, ard,
    learn_inducing, natural_gradient, mean) reach the model, so a fit and its reload agree."""
    return PsiGP(inducing, kernel=settings.kernel, ard=settings.ard,
                 learn_inducing=settings.learn_inducing, natural=settings.natural_gradient,
                 mean=settings.mean)  # fmt: skip


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
        model = _psi_gp(inducing.clone(), settings)
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
            n_train=int(state.get("n_train", 0)),
            n_val=int(state.get("n_val", 0)),
            train_seconds=float(state.get("train_seconds", 0.0)),
        )
        fitted.to(device)
        fitted.model.eval()
        fitted.likelihood.eval()
        return fitted


# ----------------------------------------------------------------------------------------------
# training


def _check_data(x: Tensor, y: Tensor) -> tuple[Tensor, Tensor]:
    if not isinstance(x, Tensor) or not isinstance(y, Tensor):
        raise TypeError("fit_classifier expects torch tensors x (n x d) and y (n,)")
    if x.dim() != 2 or x.shape[1] < 1:
        raise ValueError(f"x must have shape (n, d) (one column per input), got {tuple(x.shape)}")
    y = y.reshape(-1)
    if y.shape[0] != x.shape[0]:
        raise ValueError(f"x and y differ in length: {x.shape[0]} vs {y.shape[0]}")
    x = x.to(torch.float32)
    y = y.to(torch.float32)
    if not bool(torch.isfinite(x).all()):
        bad = int((~torch.isfinite(x)).any(dim=1).sum())
        raise NumericalError(f"training inputs contain NaN or inf in {bad} row(s)")
    if not bool(torch.isfinite(y).all()) or not bool(((y >= 0) & (y <= 1)).all()):
        raise NumericalError(
            "training labels must be 0/1 outcomes or probabilities in [0, 1] (no NaN/inf)"
        )
    return x, y


@dataclass
class _Prepared:
    """One classifier's data as its training loop sees it (see :func:`_prepare`)."""

    n_train: int
    n_val: int
    gen: torch.Generator
    normaliser: Normalizer
    z_train: Tensor
    y_train: Tensor
    val_idx: Tensor
    inducing: Tensor
    x: Tensor
    outcomes: Tensor


def _prepare(
    x: Tensor,
    y: Tensor,
    settings: GPSettings,
    device: torch.device,
    outcomes: Tensor | None = None,
) -> _Prepared:
    """The validation split (fixed by ``settings.seed``), the normaliser and the inducing points
    (a random subset of training inputs), both from the training part only. Seeds torch's
    global generator with ``settings.seed`` first (the variational mean's initial noise).
    ``outcomes``: the 0/1 outcomes the held-out metrics score (default ``y``, which must then
    be 0/1)."""
    x, y = _check_data(x, y)
    if not settings.bins and not bool(((y == 0) | (y == 1)).all()):
        # gpytorch's Bernoulli likelihood reads labels as signs: a fraction would be misread
        raise ConfigError("expected (fractional) labels need binned training (gp.bins > 0)")
    outcomes = y if outcomes is None else outcomes.reshape(-1).to(torch.float32)
    if outcomes.shape != y.shape or not bool(((outcomes == 0) | (outcomes == 1)).all()):
        raise NumericalError(
            "held-out metrics need 0/1 outcomes (one per row); pass them as `outcomes` when "
            "training on expected labels"
        )
    n = x.shape[0]
    n_val = round(settings.validation_fraction * n)
    n_train = n - n_val
    if n_train < 2:
        raise ConfigError(
            f"gp.validation_fraction={settings.validation_fraction} leaves {n_train} training "
            f"point(s) of {n}; need at least 2"
        )
    if settings.n_inducing > n_train:
        raise ConfigError(
            f"gp.n_inducing={settings.n_inducing} exceeds the {n_train} training points"
        )

    torch.manual_seed(settings.seed)
    # Index generation on the CPU with its own generator: same split and batches on any device.
    gen = torch.Generator().manual_seed(settings.seed)
    perm = torch.randperm(n, generator=gen)
    train_idx, val_idx = perm[:n_train], perm[n_train:]
    x_train, y_train = x[train_idx].to(device), y[train_idx].to(device)

    normaliser = Normalizer.fit(x_train)
    z_train = normaliser.transform(x_train)
    inducing = z_train[torch.randperm(n_train, generator=gen)[: settings.n_inducing].to(device)]
    return _Prepared(n_train, n_val, gen, normaliser, z_train, y_train, val_idx, inducing, x,
                     outcomes)  # fmt: skip


def fit_classifier(
    x: Tensor,
    y: Tensor,
    settings: GPSettings | None = None,
    progress: bool = True,
    device: torch.device | str = "cpu",
    desc: str = "GP",
    outcomes: Tensor | None = None,
    weight: float = 1.0,
) -> FittedClassifier:
    """Train a sparse variational GP probit classifier on inputs ``x`` (``n x d``), labels ``y``
    (``n``: 0/1 outcomes, or expected labels in [0, 1], whose binned likelihood counts each row
    as ``y`` of a success; then ``outcomes``, the rows' 0/1 outcomes, score the held-out part).

    A random validation split (fixed by ``settings.seed``) is held out; the normaliser and the
    inducing points (a random subset of training inputs) come from the training part only. The
    negative ELBO is minimised with minibatch Adam (plus NGD on the variational parameters when
    ``settings.natural_gradient``). See the module docstring for the numerical guard.
    ``weight``: each row counts as this many draws in the binned likelihood (expected labels'
    :func:`label_weight`; binned training only).
    """
    settings = settings or GPSettings()
    device = torch.device(device)
    _check_weight(weight, settings)
    prep = _prepare(x, y, settings, device, outcomes)
    n_train, n_val, gen, z_train, y_train, inducing = (
        prep.n_train,
        prep.n_val,
        prep.gen,
        prep.z_train,
        prep.y_train,
        prep.inducing,
    )
    normaliser = prep.normaliser
    model = _psi_gp(inducing.clone(), settings).to(device)
    likelihood = gpytorch.likelihoods.BernoulliLikelihood().to(device)
    mll = gpytorch.mlls.VariationalELBO(likelihood, model, num_data=n_train)

    if settings.natural_gradient:
        optimizers: list[torch.optim.Optimizer] = [
            gpytorch.optim.NGD(
                model.variational_parameters(), num_data=n_train, lr=settings.natural_lr
            ),
            torch.optim.Adam([*model.hyperparameters(), *likelihood.parameters()], lr=settings.lr),
        ]
    else:
        optimizers = [
            torch.optim.Adam([*model.parameters(), *likelihood.parameters()], lr=settings.lr)
        ]

    fitted = FittedClassifier(
        model=model,
        likelihood=likelihood,
        normaliser=normaliser,
        settings=settings,
        n_train=n_train,
        n_val=n_val,
    )
    model.train()
    likelihood.train()
    binned = (
        _weighted(bin_inputs(z_train, y_train, settings.bins), weight) if settings.bins else None
    )
    good_state = _snapshot(fitted)
    t0 = time.perf_counter()
    bar = tqdm(range(settings.epochs), desc=desc, disable=not progress, leave=False)
    for epoch in bar:
        # The parameters after an epoch's last step are never evaluated by a loss, so the last
        # state known to be good is the one an epoch started from once all its losses are finite.
        epoch_start = _snapshot(fitted)
        # Accumulate on the device; one host sync per epoch, not per minibatch.
        total = torch.zeros((), device=device)
        try:
            if binned is not None:  # one full-batch step on the binned data
                for opt in optimizers:
                    opt.zero_grad(set_to_none=True)
                loss = _binned_loss(model, likelihood, *binned)
                loss.backward()
                for opt in optimizers:
                    opt.step()
                total = loss.detach() * n_train
            for idx in () if binned is not None else _batches(n_train, settings, gen, device):
                for opt in optimizers:
                    opt.zero_grad(set_to_none=True)
                loss = -mll(model(z_train[idx]), y_train[idx])
                loss.backward()
                for opt in optimizers:
                    opt.step()
                total = total + loss.detach() * idx.shape[0]
        except (NotPSDError, NanError) as exc:
            bar.close()
            raise _numerical_failure(fitted, good_state, epoch, str(exc)) from exc
        epoch_loss = float(total) / n_train
        if not math.isfinite(epoch_loss):
            bar.close()
            raise _numerical_failure(fitted, good_state, epoch, f"loss became {epoch_loss}")
        fitted.history.append(epoch_loss)
        good_state = epoch_start
        bar.set_postfix(loss=f"{epoch_loss:.4f}")
    bar.close()
    fitted.train_seconds = time.perf_counter() - t0

    model.eval()
    likelihood.eval()
    _validate(fitted, prep)
    return fitted


def _validate(fitted: FittedClassifier, prep: _Prepared) -> None:
    """Held-out metrics of a trained classifier (none without a validation split)."""
    if prep.n_val > 0:
        p_val = fitted.predict_proba(prep.x[prep.val_idx])
        fitted.validation = classification_metrics(p_val, prep.outcomes[prep.val_idx])


def fit_classifiers(
    data: Sequence[tuple[Tensor, ...]],
    settings: GPSettings | None = None,
    progress: bool = True,
    device: torch.device | str = "cpu",
    desc: str = "GP",
    weights: Sequence[float] | None = None,
) -> list[FittedClassifier]:
    """:func:`fit_classifier` for several data sets (``(x, y)`` or ``(x, y, outcomes)``),
    trained side by side.

    With binned training (``settings.bins > 0``) on at most :data:`BATCH_MAX_BINS` occupied
    bins each, and Adam alone, the classifiers are one batched GP (independent
    hyperparameters, inducing points and variational parameters per classifier) whose loss is
    the sum of theirs: Adam's update is elementwise, so each follows the steps its own
    :func:`fit_classifier` would take (the same split, inducing points and initial noise), at
    about the per-step cost of one. ``train_seconds`` is the shared loop's. Otherwise
    (minibatches, natural gradients, many bins) they are fitted one after the other.
    ``weights``: one per data set, as :func:`fit_classifier`'s ``weight`` (default 1).
    """
    settings = settings or GPSettings()
    device = torch.device(device)
    weights = [1.0] * len(data) if weights is None else [float(w) for w in weights]
    if len(weights) != len(data):
        raise ValueError(f"{len(weights)} weights for {len(data)} data sets")
    for w in weights:
        _check_weight(w, settings)
    if not progress:  # no bar to watch: say what runs (a K-lumps fit takes minutes)
        log.info("%s: fitting %d classifier(s), %d steps each", desc, len(data), settings.epochs)

    def one_by_one() -> list[FittedClassifier]:
        return [fit_classifier(d[0], d[1], settings, progress=progress, device=device,
                               desc=f"{desc} {i}", outcomes=d[2] if len(d) > 2 else None,
                               weight=w)
                for i, (d, w) in enumerate(zip(data, weights, strict=True))]  # fmt: skip

    if not settings.bins or settings.natural_gradient or len(data) < 2:
        return one_by_one()
    preps = [_prepare(d[0], d[1], settings, device, d[2] if len(d) > 2 else None) for d in data]
    binned = [_weighted(bin_inputs(p.z_train, p.y_train, settings.bins), w)
              for p, w in zip(preps, weights, strict=True)]  # fmt: skip
    if max(z.shape[0] for z, _, _ in binned) > BATCH_MAX_BINS:
        return one_by_one()
    model = _psi_gp(torch.stack([p.inducing for p in preps]).clone(), settings).to(device)
    # the initial variational mean of each separate fit: 1e-3 N(0, I) drawn right after seeding
    # (gpytorch's CholeskyVariationalDistribution initialisation from the whitened prior)
    strategy = model.variational_strategy
    torch.manual_seed(settings.seed)
    noise = torch.randn(settings.n_inducing, device=device)
    with torch.no_grad():
        dist = strategy._variational_distribution
        dist.variational_mean.copy_(torch.zeros_like(noise).add_(noise, alpha=dist.mean_init_std))
        dist.chol_variational_covar.copy_(torch.eye(settings.n_inducing, device=device))
        strategy.variational_params_initialized.fill_(1)
    likelihood = gpytorch.likelihoods.BernoulliLikelihood().to(device)
    optimizer = torch.optim.Adam([*model.parameters(), *likelihood.parameters()], lr=settings.lr)
    z_b, n_b, k_b = _padded_bins(binned)
    histories: list[list[float]] = [[] for _ in preps]
    model.train()
    likelihood.train()
    good_state = _model_state(model)
    t0 = time.perf_counter()
    bar = tqdm(range(settings.epochs), desc=desc, disable=not progress, leave=False)
    for epoch in bar:
        epoch_start = _model_state(model)
        try:
            optimizer.zero_grad(set_to_none=True)
            losses = _binned_loss(model, likelihood, z_b, n_b, k_b)  # (b,)
            losses.sum().backward()
            optimizer.step()
        except (NotPSDError, NanError) as exc:
            bar.close()
            raise _batch_failure(
                model, good_state, preps, settings, histories, epoch, str(exc)
            ) from exc
        values = losses.detach().cpu().tolist()
        if not all(math.isfinite(v) for v in values):
            bar.close()
            raise _batch_failure(model, good_state, preps, settings, histories, epoch,
                                 f"loss became {values}")  # fmt: skip
        for h, v in zip(histories, values, strict=True):
            h.append(v)
        good_state = epoch_start
        bar.set_postfix(loss=" ".join(f"{v:.4f}" for v in values))
    bar.close()
    seconds = time.perf_counter() - t0
    out = _split(model, preps, settings, histories)
    for fitted, prep in zip(out, preps, strict=True):
        fitted.train_seconds = seconds
        _validate(fitted, prep)
    return out


def _check_weight(weight: float, settings: GPSettings) -> None:
    """A likelihood weight is finite and positive, and other than 1 only for binned training."""
    if not (math.isfinite(weight) and weight > 0):
        raise ValueError(f"a likelihood weight must be finite and > 0, got {weight!r}")
    if weight != 1.0 and not settings.bins:
        raise ConfigError("weighted rows (expected labels' dispersion) need gp.bins > 0")


def _weighted(
    binned: tuple[Tensor, Tensor, Tensor], weight: float
) -> tuple[Tensor, Tensor, Tensor]:
    """Bins whose rows count ``weight`` draws each (``weight == 1``: the same tensors)."""
    if weight == 1.0:
        return binned
    z_b, n_b, k_b = binned
    return z_b, n_b * weight, k_b * weight


def _padded_bins(binned: Sequence[tuple[Tensor, Tensor, Tensor]]) -> tuple[Tensor, Tensor, Tensor]:
    """Stack several classifiers' bins (``b x L x d``, ``b x L``, ``b x L``), padding with
    empty bins (no points: they add nothing to the ELBO) at the first bin's input."""
    size = max(z.shape[0] for z, _, _ in binned)

    def pad(t: Tensor, like: Tensor) -> Tensor:
        extra = size - t.shape[0]
        return torch.cat([t, like.expand(extra, *t.shape[1:])]) if extra else t

    z = torch.stack([pad(z, z[:1]) for z, _, _ in binned])
    n = torch.stack([pad(n, n.new_zeros(1)) for _, n, _ in binned])
    k = torch.stack([pad(k, k.new_zeros(1)) for _, _, k in binned])
    return z, n, k


def _model_state(model: PsiGP) -> dict[str, Tensor]:
    return {k: v.detach().clone() for k, v in model.state_dict().items()}


def _split(
    model: PsiGP,
    preps: Sequence[_Prepared],
    settings: GPSettings,
    histories: Sequence[list[float]],
) -> list[FittedClassifier]:
    """The batched GP as one :class:`FittedClassifier` per batch entry (its slice of every
    batched tensor), each saved and loaded exactly as a separately fitted one."""
    state = model.state_dict()
    out = []
    for i, prep in enumerate(preps):
        single = _psi_gp(state["variational_strategy.inducing_points"][i].clone(),
                        settings).to(prep.z_train.device)  # fmt: skip
        target = single.state_dict()
        part = {}
        for k, ref in target.items():
            v = state[k]
            part[k] = v.clone() if v.shape == ref.shape else v[i].clone()
            if part[k].shape != ref.shape:
                raise RuntimeError(f"batched GP state {k}: {tuple(v.shape)} vs {tuple(ref.shape)}")
        single.load_state_dict(part, strict=True)
        single.eval()
        likelihood = gpytorch.likelihoods.BernoulliLikelihood().to(prep.z_train.device)
        likelihood.eval()
        out.append(FittedClassifier(model=single, likelihood=likelihood,
                                    normaliser=prep.normaliser, settings=settings,
                                    history=list(histories[i]), n_train=prep.n_train,
                                    n_val=prep.n_val))  # fmt: skip
    return out


def _batch_failure(
    model: PsiGP,
    good_state: dict[str, Tensor],
    preps: Sequence[_Prepared],
    settings: GPSettings,
    histories: Sequence[list[float]],
    epoch: int,
    what: str,
) -> NumericalError:
    """Restore the batch to its last good state; the error of its first classifier."""
    model.load_state_dict(good_state)
    fitted = _split(model, preps, settings, histories)[0]
    return _numerical_failure(fitted, _snapshot(fitted), epoch, what)


_State = tuple[dict[str, Tensor], dict[str, Tensor]]


def _batches(n: int, settings: GPSettings, gen: torch.Generator, device: torch.device) -> Any:
    return torch.randperm(n, generator=gen).to(device).split(settings.batch_size)


def _bin_index(z: Tensor, bins: int | Sequence[int]) -> tuple[Tensor, int]:
    """Each point's equal-width bin (``bins`` per column, or ``bins[j]`` for column ``j``)
    and the number of bins."""
    d = z.shape[1]
    per_axis = [bins] * d if isinstance(bins, int) else list(bins)
    if len(per_axis) != d:
        raise ConfigError(f"gp.bins has {len(per_axis)} counts for {d} input(s): give one or {d}")
    index = torch.zeros(z.shape[0], dtype=torch.int64, device=z.device)
    for j, n in enumerate(per_axis):
        col = z[:, j].contiguous()  # bucketize copies (and warns) otherwise
        edges = torch.linspace(float(col.min()), float(col.max()), n + 1, device=z.device)
        index = index * n + torch.bucketize(col, edges[1:-1])
    return index, math.prod(per_axis)


def bin_inputs(z: Tensor, y: Tensor, bins: int | Sequence[int]) -> tuple[Tensor, Tensor, Tensor]:
    """Aggregate points into equal-width bins of every (normalised) input column: ``bins`` per
    column, or ``bins[j]`` for column ``j``.

    Returns the occupied bins' mean inputs ``b x d``, point counts ``n_b`` and counts of y = 1
    ``k_b``. With one input and hundreds of bins the bins are far narrower than any lengthscale
    psi varies on, so placing a bin's points at their mean changes the fit negligibly, while a
    full-batch step on ~``bins`` rows is cheap enough to converge (minibatch training on the
    points left the fit measurably off; see docs/fidelity.md).
    """
    d = z.shape[1]
    index, size = _bin_index(z, bins)
    n_b = torch.bincount(index, minlength=size).to(z.dtype)
    k_b = torch.bincount(index, weights=y.to(z.dtype), minlength=size)
    sums = torch.stack(
        [torch.bincount(index, weights=z[:, j], minlength=size) for j in range(d)], 1
    )
    keep = n_b > 0
    return sums[keep] / n_b[keep].unsqueeze(1), n_b[keep], k_b[keep]


def label_weight(z: Tensor, y: Tensor, bins: int | Sequence[int], cap: float) -> float:
    """How many Bernoulli draws one expected label is worth: the inverse of the quasi-binomial
    dispersion, Pearson's pooled estimate within equal-width bins of ``z`` (``n x d``),
    ``sum_b (n_b - 1) p_b (1 - p_b) / sum_i (y_i - p_b(i))^2`` over bins with two rows or more
    (``p_b`` the bin's mean label; ``n_b - 1``: the bin's mean uses up one degree of freedom),
    clipped to ``[1, cap]``.

    A 0/1 outcome has the binomial variance p (1 - p); an expected label, the window's law given
    the internal state, varies only as much as that state does among cells at the same input
    (not at all where the class pins the state). The binned likelihood counts a row as one draw,
    so without this weight a GP trusts noise-free labels as little as coin flips and bends
    where they are sparse (E. coli, run with 2 CCW motors leaving at the top of the occupied
    band: +28 % at 90 rows; docs/fidelity.md, "Memory"). Weighting the likelihood by it is the
    quasi-likelihood fit of a GLM with estimated dispersion. The bins span ``z``'s own range,
    as the training's bins span its (normalised) training split's: the same equal-width bins up
    to the held-out rows.

    One weight for all of a GP's rows, pooled over the bins: a per-bin estimate would be noise
    where rows are sparse (90 rows in 100 bins), which is where the weight matters. Pooling is
    right when the rows share one dispersion: labels of one kind from one collection (collect
    writes expected labels for every row or for none, so each GP of the pipeline gets one
    kind). Where it varies, rows with dispersions ``1/w_k`` in shares ``f_k`` get the inverse
    of the mean dispersion, ``1 / sum_k f_k / w_k``: the noisier rows are over-weighted and the
    quieter under-weighted. E.g. a table mixing noise-free expected labels with 0/1 outcomes
    copied into the expected column, half each, gets ~2: the outcomes count ~2x what they are
    worth. So do not mix label sources in one table; within one source the dispersion still
    varies with ``z`` where the class pins the internal state in places and not in others
    (E. coli's hidden S/C split), and the weight is then that average.
    """
    if not cap >= 1.0:
        raise ValueError(f"label_weight: cap must be >= 1, got {cap!r}")
    if not (bool(torch.isfinite(z).all()) and bool(torch.isfinite(y).all())):
        raise NumericalError("label_weight: inputs and labels must be finite")
    index, size = _bin_index(z, bins)
    y = y.to(torch.float64)
    n_b = torch.bincount(index, minlength=size).to(torch.float64)
    p_b = torch.bincount(index, weights=y, minlength=size) / n_b.clamp(min=1)
    pooled = n_b >= 2  # a bin of one row says nothing about the spread around its mean
    binomial = float(((n_b - 1) * p_b * (1 - p_b))[pooled].sum())
    residual = float(((y - p_b[index]) ** 2)[pooled[index]].sum())
    if binomial <= 0.0:  # every pooled bin all 0 or all 1: nothing to weigh
        return 1.0
    return float(min(cap, max(1.0, binomial / residual))) if residual > 0 else float(cap)


def binned_expected_log_likelihood(
    likelihood: gpytorch.likelihoods.BernoulliLikelihood,
    f: gpytorch.distributions.MultivariateNormal,
    n_b: Tensor,
    k_b: Tensor,
) -> Tensor:
    """Each bin's expected log-likelihood under q(f) (``... x L``): ``k`` successes and
    ``n - k`` failures of the probit likelihood, E_q[k log Phi(f) + (n - k) log Phi(-f)], in
    one pass of the likelihood's Gauss-Hermite quadrature.

    What ``BernoulliLikelihood.expected_log_prob`` computes for each label (with its
    ``log_normal_cdf``), summed, in one quadrature instead of two (a training step at the
    paper's size ~25 % cheaper). Not ``torch.special.log_ndtr``, though it is closer to the
    exact integral: the objective would change, and the fitted psi with it (measured: up to
    2 % more bias where cells live after the default 1,000 steps on the same data).
    """
    from gpytorch.functions import log_normal_cdf

    return likelihood.quadrature(
        lambda s: k_b * log_normal_cdf(s) + (n_b - k_b) * log_normal_cdf(-s), f
    )


def _binned_loss(
    model: PsiGP,
    likelihood: gpytorch.likelihoods.BernoulliLikelihood,
    z_b: Tensor,
    n_b: Tensor,
    k_b: Tensor,
) -> Tensor:
    """Negative ELBO per point on binned data (``...``: one per GP of a batch): the expected
    log-likelihood of k_b successes and n_b - k_b failures at each bin's mean input, minus the
    KL term."""
    ell = binned_expected_log_likelihood(likelihood, model(z_b), n_b, k_b)
    return -(ell.sum(-1) - model.variational_strategy.kl_divergence()) / n_b.sum(-1)


def _snapshot(fitted: FittedClassifier) -> _State:
    return (
        {k: v.detach().clone() for k, v in fitted.model.state_dict().items()},
        {k: v.detach().clone() for k, v in fitted.likelihood.state_dict().items()},
    )


def _numerical_failure(
    fitted: FittedClassifier, good_state: _State, epoch: int, what: str
) -> NumericalError:
    """Restore the last good state and build the error (with the restored model attached)."""
    fitted.model.load_state_dict(good_state[0])
    fitted.likelihood.load_state_dict(good_state[1])
    fitted.model.eval()
    fitted.likelihood.eval()
    s = fitted.settings
    finished = len(fitted.history)
    restored = f"the start of epoch {finished}" if finished else "its initial state"
    err = NumericalError(
        f"GP training diverged in epoch {epoch + 1}/{s.epochs} ({what}). The model was "
        f"restored to {restored} (the last state whose losses were all finite) and is attached "
        f"as `exc.partial`. "
        f"Try a smaller gp.lr (now {s.lr})"
        + (f" or gp.natural_lr (now {s.natural_lr})" if s.natural_gradient else "")
        + f", or fewer gp.n_inducing (now {s.n_inducing})."
    )
    err.partial = fitted  # type: ignore[attr-defined]
    return err


__all__ = [
    "FittedClassifier",
    "GPSettings",
    "Normalizer",
    "fit_classifier",
    "fit_classifiers",
    "label_weight",
]
