"""The training loop for psi classifiers: one at a time (:func:`fit_classifier`) or side by
side as one batched GP (:func:`fit_classifiers`). The settings live in
:mod:`surrogate.gp.settings`, the trained classifier in :mod:`surrogate.gp.fitted` and the binned
likelihood in :mod:`surrogate.gp.binned`; :class:`GPSettings` stays importable from here.

Numerical guard (a deliberate choice): when the training loss becomes NaN/inf, or a Cholesky
factorisation fails, training stops, the model is restored to the last state known to be good (the
start of the last epoch whose losses were all finite: the parameters after an epoch's last step are
never evaluated by a loss), and :class:`~surrogate.errors.NumericalError` is raised. The restored
model is attached to the exception as ``exc.partial`` (a :class:`FittedClassifier` without
validation metrics) for inspection, but it is never returned silently: a half-trained surrogate must
not flow into the downstream simulations unnoticed. The message says which epoch failed and which
settings to lower.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import gpytorch
import torch
from linear_operator.utils.errors import NanError, NotPSDError
from torch import Tensor
from tqdm.auto import tqdm

from surrogate.errors import ConfigError, NumericalError
from surrogate.gp.binned import bin_inputs, binned_loss, padded_bins, weighted_bins
from surrogate.gp.fitted import FittedClassifier, Normalizer
from surrogate.gp.metrics import classification_metrics
from surrogate.gp.model import PsiGP
from surrogate.gp.newton import fit_newton
from surrogate.gp.optimizers import fit_lbfgs
from surrogate.gp.own_rows import own_rows_check
from surrogate.gp.settings import GPSettings, psi_gp
from surrogate.processes import spawned_pool

#: classifiers are trained side by side (one batched GP) up to this many occupied bins each:
#: where a step's fixed cost dominates. Measured: 200 bins, 50 inducing points 2.5x faster than
#: one by one; 500 bins (1-D), 100 inducing 1.15x; ~1e5 bins (2-D, 500 per axis) 0.54x
BATCH_MAX_BINS = 4096
#: bins per input of an unbinned fit's own-rows check (a binned one reads its own bins), at
#: most OWN_ROWS_MAX_BINS in all: the bins are counted densely, and 50 per input on 5 inputs
#: made 3e8 of them (a 5-input test fit went from under a second to 50 s)
OWN_ROWS_BINS = 50
OWN_ROWS_MAX_BINS = 2**16

log = logging.getLogger(__name__)


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
    #: the windows each row stands for (None: one each), all rows and the training split's
    rows: Tensor | None = None
    rows_train: Tensor | None = None


def _prepare(
    x: Tensor,
    y: Tensor,
    settings: GPSettings,
    device: torch.device,
    outcomes: Tensor | None = None,
    rows: Tensor | None = None,
) -> _Prepared:
    """The validation split (fixed by ``settings.seed``), the normaliser and the inducing points
    (a random subset of training inputs), both from the training part only. Seeds torch's
    global generator with ``settings.seed`` first (the variational mean's initial noise).
    ``outcomes``: the 0/1 outcomes the held-out metrics score (default ``y``, which must then
    be 0/1). ``rows``: the windows each row stands for (a collection that keeps every switch;
    None: one each), which only binned training reads."""
    x, y = _check_data(x, y)
    if rows is not None:
        rows = rows.reshape(-1).to(torch.float32)
        if rows.shape != y.shape or not bool((torch.isfinite(rows) & (rows > 0)).all()):
            raise NumericalError("each row's windows must be one positive number per row")
        if not settings.bins:
            raise ConfigError(
                "rows that stand for several windows each (a collection with "
                "collect.keep_switches=true) need binned training (gp.bins > 0): the "
                "unbinned ELBO counts each row once"
            )
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
    rows_train = None if rows is None else rows[train_idx].to(device)
    return _Prepared(n_train, n_val, gen, normaliser, z_train, y_train, val_idx, inducing, x,
                     outcomes, rows, rows_train)  # fmt: skip


def fit_classifier(  # noqa: PLR0913  # rows: a table's per-row windows, beside its weight
    x: Tensor,
    y: Tensor,
    settings: GPSettings | None = None,
    progress: bool = True,
    device: torch.device | str = "cpu",
    desc: str = "GP",
    outcomes: Tensor | None = None,
    weight: float = 1.0,
    rows: Tensor | None = None,
) -> FittedClassifier:
    """Train a sparse variational GP probit classifier on inputs ``x`` (``n x d``), labels ``y``
    (``n``: 0/1 outcomes, or expected labels in [0, 1], whose binned likelihood counts each row
    as ``y`` of a success; then ``outcomes``, the rows' 0/1 outcomes, score the held-out part).

    A random validation split (fixed by ``settings.seed``) is held out; the normaliser and the
    inducing points (a random subset of training inputs) come from the training part only. The
    negative ELBO is minimised with minibatch Adam (plus NGD on the variational parameters when
    ``settings.natural_gradient``). See the module docstring for the numerical guard.
    ``weight``: each row counts as this many draws in the binned likelihood (expected labels'
    :func:`label_weight`; binned training only). ``rows`` (``n``): the windows each row
    stands for (a collection that keeps every switch; binned training only), in the bins and
    the held-out metrics.
    """
    settings = settings or GPSettings()
    if settings.optimizer != "adam":  # L-BFGS and Newton fits are the batched one's (of one)
        data: tuple[Tensor, ...] = (x, y, y if outcomes is None else outcomes)
        data = data if rows is None else (*data, rows)
        return fit_classifiers([data], settings, progress, device, desc, [weight])[0]
    device = torch.device(device)
    _check_weight(weight, settings)
    prep = _prepare(x, y, settings, device, outcomes, rows)
    n_train, n_val, gen, z_train, y_train, inducing = (
        prep.n_train,
        prep.n_val,
        prep.gen,
        prep.z_train,
        prep.y_train,
        prep.inducing,
    )
    normaliser = prep.normaliser
    model = psi_gp(inducing.clone(), settings).to(device)
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
        weighted_bins(bin_inputs(z_train, y_train, settings.bins, prep.rows_train), weight)
        if settings.bins
        else None
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
                loss = binned_loss(model, likelihood, *binned)
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
    _validate(fitted, prep, weight)
    return fitted


def _validate(fitted: FittedClassifier, prep: _Prepared, weight: float = 1.0) -> None:
    """Held-out metrics of a trained classifier (none without a validation split), and the
    fit against its own training rows, binned as it was trained (:mod:`surrogate.gp.own_rows`;
    an unbinned fit's rows in :data:`OWN_ROWS_BINS` bins per input, fewer where that would
    pass :data:`OWN_ROWS_MAX_BINS` in all), each row counting
    ``weight`` draws as in its likelihood (expected labels' dispersion: their SE)."""
    if prep.n_val > 0:
        p_val = fitted.predict_proba(prep.x[prep.val_idx])
        rows = None if prep.rows is None else prep.rows[prep.val_idx]
        fitted.validation = classification_metrics(p_val, prep.outcomes[prep.val_idx],
                                                   weights=rows)  # fmt: skip
    d = prep.z_train.shape[1]
    per_axis = min(OWN_ROWS_BINS, max(2, int(OWN_ROWS_MAX_BINS ** (1 / d) + 1e-9)))
    z_b, n_b, k_b = bin_inputs(prep.z_train, prep.y_train, fitted.settings.bins or per_axis,
                               prep.rows_train)  # fmt: skip
    x_b = z_b * prep.normaliser.std + prep.normaliser.mean  # the fit's input space
    p_b = fitted.predict_proba(x_b)
    p, x, n, k = (t.detach().cpu().numpy() for t in (p_b, x_b, n_b * weight, k_b * weight))
    fitted.own_rows = own_rows_check(p, x, n, k)


def fit_classifiers(
    data: Sequence[tuple[Tensor, ...]],
    settings: GPSettings | None = None,
    progress: bool = True,
    device: torch.device | str = "cpu",
    desc: str = "GP",
    weights: Sequence[float] | None = None,
    processes: int = 1,
) -> list[FittedClassifier]:
    """:func:`fit_classifier` for several data sets (``(x, y)``, ``(x, y, outcomes)`` or
    ``(x, y, outcomes, rows)``: ``rows`` the windows each row stands for), trained
    side by side.

    With binned training (``settings.bins > 0``) on at most :data:`BATCH_MAX_BINS` occupied
    bins each, and Adam alone, the classifiers are one batched GP (independent
    hyperparameters, inducing points and variational parameters per classifier) whose loss is
    the sum of theirs: Adam's update is elementwise, so each follows the steps its own
    :func:`fit_classifier` would take (the same split, inducing points and initial noise), at
    about the per-step cost of one. ``train_seconds`` is the shared loop's. Otherwise
    (minibatches, natural gradients, many bins) they are fitted one after the other, or, with
    ``processes > 1`` on the CPU, in that many spawned processes on this process's torch
    threads each (:func:`_in_processes`): each fit seeds itself and sees its own data only, so
    it is the fit made here, bit for bit.
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
        if processes > 1 and len(data) > 1 and device.type == "cpu":
            return _in_processes(data, weights, settings, min(processes, len(data)), desc)
        return [fit_classifier(d[0], d[1], settings, progress=progress, device=device,
                               desc=f"{desc} {i}", outcomes=_part(d, 2), weight=w,
                               rows=_part(d, 3))
                for i, (d, w) in enumerate(zip(data, weights, strict=True))]  # fmt: skip

    batched_only = settings.optimizer != "adam"  # whatever the count (settings check bins)
    natural = settings.natural_gradient and settings.optimizer == "adam"
    if not settings.bins or natural or (len(data) < 2 and not batched_only):
        return one_by_one()
    preps = [_prepare(d[0], d[1], settings, device, _part(d, 2), _part(d, 3)) for d in data]
    binned = [weighted_bins(bin_inputs(p.z_train, p.y_train, settings.bins, p.rows_train), w)
              for p, w in zip(preps, weights, strict=True)]  # fmt: skip
    if max(z.shape[0] for z, _, _ in binned) > BATCH_MAX_BINS and not batched_only:
        return one_by_one()
    model = psi_gp(torch.stack([p.inducing for p in preps]).clone(), settings).to(device)
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
    z_b, n_b, k_b = padded_bins(binned)
    histories: list[list[float]] = [[] for _ in preps]
    model.train()
    likelihood.train()
    good_state = _model_state(model)
    t0 = time.perf_counter()
    if batched_only:
        try:
            if settings.optimizer == "newton":
                fit_newton(model, z_b, n_b, k_b, settings.epochs, settings.lr, histories)
            else:
                fit_lbfgs([*model.parameters(), *likelihood.parameters()],
                          lambda: binned_loss(model, likelihood, z_b, n_b, k_b),
                          settings.epochs, histories)  # fmt: skip
        except (NotPSDError, NanError, FloatingPointError, torch.linalg.LinAlgError) as exc:
            raise _batch_failure(model, good_state, preps, settings, histories, 0,
                                 str(exc)) from exc  # fmt: skip
        return _finish(model, preps, settings, histories, time.perf_counter() - t0, weights)
    bar = tqdm(range(settings.epochs), desc=desc, disable=not progress, leave=False)
    for epoch in bar:
        epoch_start = _model_state(model)
        try:
            optimizer.zero_grad(set_to_none=True)
            losses = binned_loss(model, likelihood, z_b, n_b, k_b)  # (b,)
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
    return _finish(model, preps, settings, histories, time.perf_counter() - t0, weights)


def _in_processes(
    data: Sequence[tuple[Tensor, ...]],
    weights: Sequence[float],
    settings: GPSettings,
    processes: int,
    desc: str,
) -> list[FittedClassifier]:
    """:func:`fit_classifier` of each data set in ``processes`` spawned processes of this
    process's torch threads, in their order; the first fit that failed numerically (in the
    data sets' order, as one by one would have stopped) is raised here, its restored model
    attached as ``exc.partial``."""
    threads = torch.get_num_threads()
    log.info("%s: fitting %d classifier(s) in %d processes of %d thread(s), %d steps each",
             desc, len(data), processes, threads, settings.epochs)  # fmt: skip
    with spawned_pool(processes, threads=threads) as pool:
        futures = [pool.submit(_fit_state, d, settings, f"{desc} {i}", w)
                   for i, (d, w) in enumerate(zip(data, weights, strict=True))]  # fmt: skip
        states = [f.result() for f in futures]
    for error, state in states:
        if error is not None:
            err = NumericalError(error)
            if state is not None:
                err.partial = FittedClassifier.from_state(state)  # type: ignore[attr-defined]
            raise err
    return [FittedClassifier.from_state(state) for _, state in states if state is not None]


def _fit_state(
    data: tuple[Tensor, ...], settings: GPSettings, desc: str, weight: float
) -> tuple[str | None, dict[str, Any] | None]:
    """A worker's task: :func:`fit_classifier` of ``data`` as (None, its state), or (the
    error's message, the restored model's state if it has one) where it raised a
    :class:`NumericalError` (an exception's attributes do not cross processes)."""
    try:
        fitted = fit_classifier(data[0], data[1], settings, progress=False, desc=desc,
                                outcomes=_part(data, 2), weight=weight,
                                rows=_part(data, 3))  # fmt: skip
    except NumericalError as exc:
        partial = getattr(exc, "partial", None)
        return str(exc), partial.to_state() if partial is not None else None
    return None, fitted.to_state()


def _part(data: Sequence[Tensor], i: int) -> Tensor | None:
    """A data set's ``i``-th part (outcomes 2, rows' windows 3), None where it has none."""
    return data[i] if len(data) > i else None


def _finish(
    model: PsiGP,
    preps: Sequence[_Prepared],
    settings: GPSettings,
    histories: Sequence[list[float]],
    seconds: float,
    weights: Sequence[float],
) -> list[FittedClassifier]:
    """The batch's classifiers, each validated (its rows counting its ``weights`` entry),
    with the shared loop's ``seconds``."""
    out = _split(model, preps, settings, histories)
    for fitted, prep, weight in zip(out, preps, weights, strict=True):
        fitted.train_seconds = seconds
        _validate(fitted, prep, weight)
    return out


def _check_weight(weight: float, settings: GPSettings) -> None:
    """A likelihood weight is finite and positive, and other than 1 only for binned training."""
    if not (math.isfinite(weight) and weight > 0):
        raise ValueError(f"a likelihood weight must be finite and > 0, got {weight!r}")
    if weight != 1.0 and not settings.bins:
        raise ConfigError("weighted rows (expected labels' dispersion) need gp.bins > 0")


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
        single = psi_gp(state["variational_strategy.inducing_points"][i].clone(),
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
        + (
            "Try gp.optimizer=adam (L-BFGS's line search left the region where the "
            "covariances are positive definite)"
            if s.optimizer == "lbfgs"
            else f"Try a smaller gp.lr (now {s.lr})"
            + (f" or gp.natural_lr (now {s.natural_lr})" if s.natural_gradient else "")
        )
        + f", or fewer gp.n_inducing (now {s.n_inducing})."
    )
    err.partial = fitted  # type: ignore[attr-defined]
    return err


__all__ = [
    "BATCH_MAX_BINS",
    "GPSettings",
    "fit_classifier",
    "fit_classifiers",
]
