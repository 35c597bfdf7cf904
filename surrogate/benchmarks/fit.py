"""Faster GP fits, measured: the default recipe's K-lumps fit (E. coli: 45 one-input GPs side
by side, 32 inducing points, 100 bins) with other optimisers and fewer steps, against the
default (Adam, 1,000 full-batch steps).

One run (``python scripts/bench_fit.py``) reads the quick start's collection (collect it first
with ``python scripts/collect.py``) and builds the class chain's binary problems exactly as train
does (:func:`surrogate.gp.classes.class_problems`); :func:`run_bench` fits them once per method
in this process, one after the other on ``threads`` torch threads, timing wall and CPU seconds.
Each fit is scored against the reference (the first method): its final negative ELBO per point
(mean and max over the GPs of its excess over the reference's) and its psi where each GP's
data live (the occupied bins' mean inputs): ``|Δpsi|`` against the reference's own posterior
sd of psi there. A method is *equal* where ``|Δpsi| < 1`` sd at every such point of every GP.
The same scores against a fit converged further (Adam, 2,000 steps) say how far the reference
itself is from the optimum in those units.

Methods: ``adam`` (:func:`~surrogate.gp.training.fit_classifiers`' default loop), ``newton``
(``gp.optimizer=newton`` through that function: q(u) by Newton's method, the hyperparameters by
Adam; :mod:`surrogate.gp.newton`), ``ngd`` and ``lbfgs`` (:mod:`surrogate.gp.optimizers`),
and ``adam+ngd``: hyperparameters from a short
Adam fit, then natural-gradient steps on the variational parameters alone with the
hyperparameters frozen (at ``natural_lr = 1`` each step is the closed-form update of the
Gaussian fit to the current likelihood's local quadratic: a Newton step on q(u)).
"""

from __future__ import annotations

import dataclasses
import os
import sys
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import gpytorch
import numpy as np
import torch
from linear_operator.utils.errors import NanError, NotPSDError
from torch import Tensor

from surrogate.errors import NumericalError
from surrogate.gp.binned import bin_inputs, binned_loss, padded_bins, weighted_bins
from surrogate.gp.fitted import FittedClassifier
from surrogate.gp.model import PsiGP
from surrogate.gp.optimizers import fit_lbfgs, fit_ngd, natural_step
from surrogate.gp.settings import GPSettings, psi_gp
from surrogate.gp.training import _prepare, _Prepared, _split, fit_classifiers
from surrogate.io import write_json

__all__ = ["DEFAULT_METHODS", "Method", "fit_problems", "psi_sd", "run_bench", "score"]

Problems = list[tuple[Tensor, Tensor, Tensor]]


@dataclasses.dataclass(frozen=True)
class Method:
    """One fit to time: ``optimizer`` for ``steps`` iterations (``natural_lr`` for NGD);
    ``refine``: NGD steps on the variational parameters after (``adam+ngd``)."""

    optimizer: str
    steps: int
    natural_lr: float = 0.1
    refine: int = 0

    @property
    def name(self) -> str:
        """A short label: ``adam 1000``, ``ngd 50 lr=0.5``, ``adam 100 + ngd 10``."""
        if self.refine:
            return f"{self.optimizer} {self.steps} + ngd {self.refine}"
        lr = f" lr={self.natural_lr:g}" if self.optimizer == "ngd" else ""
        return f"{self.optimizer} {self.steps}{lr}"


#: the reference first, then the brief's grid (issue 52)
DEFAULT_METHODS: tuple[Method, ...] = (
    Method("adam", 1000),
    *(Method("adam", n) for n in (100, 200, 400)),
    *(Method("ngd", n, lr) for lr in (0.1, 0.5, 1.0) for n in (25, 50, 100, 200)),
    *(Method("lbfgs", n) for n in (20, 50, 100, 200)),
    Method("adam", 100, 1.0, 10),
    *(Method("newton", n) for n in (20, 50, 100, 200)),
)
#: a fit converged further than the reference (twice its steps): every method's distance to
#: it against the reference's own says whether the reference is within its sd of the optimum
CONVERGED = Method("adam", 2000)


def fit_problems(
    problems: Problems, weights: Sequence[float], settings: GPSettings, method: Method
) -> tuple[list[FittedClassifier], float, float]:
    """Fit ``problems`` with ``method``: the classifiers, wall and CPU seconds. Adam runs
    :func:`~surrogate.gp.training.fit_classifiers` itself (the default fit's code path)."""
    wall, cpu = time.perf_counter(), time.process_time()
    if method.optimizer in ("adam", "newton"):  # the stage's own fit
        own = dataclasses.replace(settings, epochs=method.steps, optimizer=method.optimizer)
        fitted = fit_classifiers(problems, own, progress=False, weights=weights)
        if method.refine:
            fitted = _refine(fitted, problems, weights, settings, method)
    else:
        fitted = _fit_other(problems, weights, settings, method)
    return fitted, time.perf_counter() - wall, time.process_time() - cpu


def _batched(
    problems: Problems, weights: Sequence[float], settings: GPSettings
) -> tuple[PsiGP, list[_Prepared], tuple[Tensor, Tensor, Tensor]]:
    """The untrained batched GP of ``problems`` as :func:`fit_classifiers` builds it (the same
    splits, normalisers, inducing points and bins; ``settings.natural_gradient``: a natural
    variational distribution, which starts from the prior), its preparations and padded bins."""
    cpu = torch.device("cpu")
    preps = [_prepare(x, y, settings, cpu, o) for x, y, o in problems]
    binned = [weighted_bins(bin_inputs(p.z_train, p.y_train, settings.bins), w)
              for p, w in zip(preps, weights, strict=True)]  # fmt: skip
    model = psi_gp(torch.stack([p.inducing for p in preps]).clone(), settings)
    if not settings.natural_gradient:  # fit_classifiers' initial variational mean
        torch.manual_seed(settings.seed)
        noise = torch.randn(settings.n_inducing)
        with torch.no_grad():
            dist = model.variational_strategy._variational_distribution
            dist.variational_mean.copy_(noise * dist.mean_init_std)
            dist.chol_variational_covar.copy_(torch.eye(settings.n_inducing))
            model.variational_strategy.variational_params_initialized.fill_(1)
    return model, preps, padded_bins(binned)


def _fit_other(
    problems: Problems, weights: Sequence[float], settings: GPSettings, method: Method
) -> list[FittedClassifier]:
    """``problems`` fitted as one batched GP by :mod:`surrogate.gp.optimizers`' ``method``."""
    s = dataclasses.replace(settings, epochs=method.steps, natural_lr=method.natural_lr,
                            natural_gradient=method.optimizer == "ngd")  # fmt: skip
    model, preps, (z_b, n_b, k_b) = _batched(problems, weights, s)
    likelihood = gpytorch.likelihoods.BernoulliLikelihood()
    histories: list[list[float]] = [[] for _ in problems]
    model.train()

    def loss_fn() -> Tensor:
        return binned_loss(model, likelihood, z_b, n_b, k_b)

    try:
        if method.optimizer == "ngd":
            fit_ngd(model, likelihood, loss_fn, n_b.sum(-1), s.epochs, s.lr, s.natural_lr,
                    histories)  # fmt: skip
        elif method.optimizer == "lbfgs":
            fit_lbfgs(list(model.parameters()), loss_fn, s.epochs, histories)
        else:
            raise ValueError(f"bench_fit: unknown optimizer {method.optimizer!r}")
        with torch.no_grad():  # the state after the last step, which no step evaluated
            _record_final(loss_fn())
    except (NotPSDError, NanError, FloatingPointError) as exc:
        raise NumericalError(f"{method.name} diverged ({exc})") from exc
    return _split(model, preps, s, histories)


def _record_final(losses: Tensor) -> None:
    if not bool(torch.isfinite(losses).all()):
        raise FloatingPointError(f"final loss {losses.tolist()}")


def _refine(
    fitted: list[FittedClassifier],
    problems: Problems,
    weights: Sequence[float],
    settings: GPSettings,
    method: Method,
) -> list[FittedClassifier]:
    """``method.refine`` natural steps on q(u) of ``fitted`` with their hyperparameters frozen
    (a batched natural-parameter model carrying the fits' hyperparameters)."""
    natural = dataclasses.replace(settings, natural_gradient=True, epochs=method.refine)
    model, preps, (z_b, n_b, k_b) = _batched(problems, weights, natural)
    states = [f.model.state_dict() for f in fitted]
    target = model.state_dict()
    hyper = {k: torch.stack([s[k] for s in states])
             if target[k].shape == (len(states), *states[0][k].shape) else states[0][k]
             for k in states[0] if "_variational_distribution" not in k}  # fmt: skip
    model.load_state_dict(hyper, strict=False)
    likelihood = fitted[0].likelihood
    model.train()
    params = list(model.variational_parameters())
    try:
        for _ in range(method.refine):
            for p in params:
                p.grad = None
            binned_loss(model, likelihood, z_b, n_b, k_b).sum().backward()
            natural_step(params, n_b.sum(-1), method.natural_lr)
        with torch.no_grad():
            _record_final(binned_loss(model, likelihood, z_b, n_b, k_b))
    except (NotPSDError, NanError, FloatingPointError) as exc:
        raise NumericalError(f"the natural refinement diverged ({exc})") from exc
    return _split(model, preps, natural, [f.history for f in fitted])


def _bins(x: Tensor, y: Tensor, outcomes: Tensor, weight: float, settings: GPSettings) -> Any:
    """One problem's training bins as the fit sees them (normalised inputs, weighted counts)."""
    prep = _prepare(x, y, settings, torch.device("cpu"), outcomes)
    return weighted_bins(bin_inputs(prep.z_train, prep.y_train, settings.bins), weight)


def psi_sd(mu: Tensor, var: Tensor, nodes: int = 32) -> Tensor:
    """The sd of psi = Phi(f) for f ~ N(``mu``, ``var``) (Gauss-Hermite quadrature)."""
    t, w = np.polynomial.hermite_e.hermegauss(nodes)
    t_, w_ = torch.tensor(t, dtype=torch.float64), torch.tensor(w / w.sum(), dtype=torch.float64)
    f = mu.double().unsqueeze(-1) + var.double().clamp(min=0).sqrt().unsqueeze(-1) * t_
    p = torch.special.ndtr(f)
    m1 = (p * w_).sum(-1)
    return ((p * p * w_).sum(-1) - m1 * m1).clamp(min=0).sqrt()


def score(
    fitted: Sequence[FittedClassifier],
    reference: Sequence[FittedClassifier],
    problems: Problems,
    weights: Sequence[float],
    settings: GPSettings,
) -> dict[str, Any]:
    """``fitted`` against ``reference`` per GP: final negative ELBO per point (its excess over
    the reference's) and ``|Δpsi|`` where the GP's data live, in the reference's posterior sd."""
    excess, d_max, d_sum, d_n, ratio, unequal = [], 0.0, 0.0, 0, 0.0, 0
    rows_off, rows_all = 0.0, 0.0
    for f, r, (x, y, o), w in zip(fitted, reference, problems, weights, strict=True):
        binned = _bins(x, y, o, w, settings)
        with torch.no_grad():
            losses = [float(binned_loss(c.model, c.likelihood, *binned)) for c in (f, r)]
        excess.append(losses[0] - losses[1])
        points, counts, _ = bin_inputs(x.float(), y.float(), settings.bins)  # where data live
        mu, var = r.latent(points)
        delta = (f.predict_proba(points) - r.predict_proba(points)).abs().double()
        sd = psi_sd(mu, var)
        d_max = max(d_max, float(delta.max()))
        d_sum, d_n = d_sum + float(delta.sum()), d_n + delta.numel()
        over = delta / sd.clamp(min=1e-12)
        rows_off += float(counts[over >= 1.0].sum())
        rows_all += float(counts.sum())
        worst = float(over.max())
        ratio = max(ratio, worst)
        unequal += worst >= 1.0
    return {"elbo_excess_mean": float(np.mean(excess)), "elbo_excess_max": float(np.max(excess)),
            "dpsi_max": d_max, "dpsi_mean": d_sum / d_n, "dpsi_over_sd_max": ratio,
            "gps_unequal": unequal, "rows_unequal": rows_off / rows_all,
            "equal": unequal == 0}  # fmt: skip


def run_bench(
    problems: Problems,
    weights: Sequence[float],
    settings: GPSettings,
    methods: Sequence[Method] = DEFAULT_METHODS,
    converged: Method | None = CONVERGED,
    threads: int = 1,
    output: Path | None = None,
) -> dict[str, Any]:
    """Time and score ``methods`` (the first is the reference) on ``problems`` (each
    ``(x, y, outcomes)``, with its likelihood weight; e.g. the K-lumps chain's,
    :func:`~surrogate.gp.classes.class_problems`) fitted with ``settings``, against the
    reference and (``conv_*`` keys) against the fit of ``converged`` (fitted first, timed too);
    print the table, write JSON to ``output`` when given."""
    torch.set_num_threads(threads)
    rows: list[dict[str, Any]] = []
    reference: list[FittedClassifier] | None = None
    load = [os.getloadavg()[0]]
    best = None
    if converged is not None:
        best, wall, cpu = fit_problems(problems, weights, settings, converged)
        print(f"{converged.name}: {wall:.1f} s wall, {cpu:.1f} s CPU", file=sys.stderr)
    for method in methods:
        row: dict[str, Any] = {"method": method.name, "steps": method.steps + method.refine}
        try:
            fitted, wall, cpu = fit_problems(problems, weights, settings, method)
        except NumericalError as exc:  # a diverging method is a result too
            rows.append({**row, "failed": str(exc).split(". ")[0]})
            print(f"{method.name:>20s} failed: {rows[-1]['failed']}", file=sys.stderr, flush=True)
            continue
        reference = reference or fitted
        row.update(wall_s=wall, cpu_s=cpu,
                   **score(fitted, reference, problems, weights, settings))  # fmt: skip
        if best is not None:
            conv = score(fitted, best, problems, weights, settings)
            row.update({f"conv_{k}": v for k, v in conv.items()})
        rows.append(row)
        load.append(os.getloadavg()[0])
        print(format_row(row, rows[0]), file=sys.stderr, flush=True)
    result = {"machine": {"cores": os.cpu_count(), "load_avg_1": load, "threads": threads,
                          "python": sys.version.split()[0], "torch": torch.__version__},
              "gps": len(problems), "settings": settings.to_dict(),
              "converged": converged.name if converged else None, "rows": rows}  # fmt: skip
    print(format_table(result))
    if output is not None:
        write_json(output, result)
    return result


HEADER = (f"{'method':>20s} {'steps':>5s} {'wall s':>7s} {'cpu s':>7s} {'cpu/ref':>7s} "
          f"{'dELBO mean':>10s} {'dELBO max':>9s} {'|dpsi| max':>10s} {'|dpsi| mean':>11s} "
          f"{'max/sd':>8s} {'GPs off':>7s} {'rows off':>8s} | {'conv dELBO':>10s} "
          f"{'|dpsi| max':>10s} {'max/sd':>8s} {'GPs off':>7s} {'rows off':>8s}")  # fmt: skip


def format_row(row: Mapping[str, Any], ref: Mapping[str, Any]) -> str:
    """One line of the table (``ref``: the reference's row)."""
    if "failed" in row:
        return f"{row['method']:>20s} {row['steps']:5d} failed: {row['failed']}"
    return (f"{row['method']:>20s} {row['steps']:5d} {row['wall_s']:7.1f} {row['cpu_s']:7.1f} "
            f"{row['cpu_s'] / ref['cpu_s']:7.2f} {row['elbo_excess_mean']:10.2e} "
            f"{row['elbo_excess_max']:9.2e} {row['dpsi_max']:10.2e} {row['dpsi_mean']:11.2e} "
            f"{row['dpsi_over_sd_max']:8.2f} {row['gps_unequal']:7d} "
            f"{row['rows_unequal']:8.1%}"
            + (f" | {row['conv_elbo_excess_mean']:10.2e} {row['conv_dpsi_max']:10.2e} "
               f"{row['conv_dpsi_over_sd_max']:8.2f} {row['conv_gps_unequal']:7d} "
               f"{row['conv_rows_unequal']:8.1%}" if "conv_dpsi_max" in row else ""))  # fmt: skip


def format_table(result: Mapping[str, Any]) -> str:
    """The plain-text table of a :func:`run_bench` result."""
    rows = result["rows"]
    return "\n".join([HEADER, *(format_row(r, rows[0]) for r in rows)])
