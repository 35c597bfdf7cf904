"""The SVGP classifiers' predictive in closed form with cached factors, for per-step simulation.

``PsiClassifier.__call__`` goes through gpytorch (lazy operators, a triangular solve per call and
one host sync to split the rows by origin state): ~40 ms per step even for 100 cells.
:class:`CachedPsi` evaluates the same predictive with everything that does not depend on the
query precomputed once, as a handful of plain tensor ops with no host sync (so it fuses into a
compiled simulation step and runs on any device).

Whitened variational strategy (gpytorch ``VariationalStrategy``), for one classifier with inducing
points Z (M), K_zz + jitter I = L L^T, variational q(u) = N(m_u, S) in whitened coordinates and a
prior mean c (gp.mean=constant) or c + s^T x (gp.mean=linear; s the slopes on the raw inputs,
:func:`_prior_mean`):

    a(x)   = L^{-1} k_Z(x)                                   (M,)
    mean   = c [+ s^T x] + a^T m_u
    var    = k(x, x) + jitter + a^T (S - I) a
    p(RUN) = Phi(mean / sqrt(1 + var))                        (Bernoulli-probit predictive)

With S - I = V diag(d) V^T (eigendecomposition, float64) and G = [L^{-T} V | L^{-T} m_u]
(M x (M + 1)) cached, one matmul k_Z(x)^T G gives y = V^T a and a^T m_u together, and
a^T (S - I) a = sum_j d_j y_j^2 (as accurate as gpytorch's a^T (S - I) a; the tempting
k^T [L^{-T} (S - I) L^{-1}] k is not, in float32). The kernel row k_Z(x) (scaled RBF or Matern
with per-input lengthscales) is exp of a small matmul of augmented inputs, centred on the
inducing points. The factors come from the model's own kernel module, jitter and Cholesky
routine, so they are those gpytorch uses.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable
from typing import Any, Protocol

import gpytorch
import torch
from linear_operator.utils.cholesky import psd_safe_cholesky
from torch import Tensor

from surrogate.errors import NumericalError
from surrogate.gp.fitted import FittedClassifier
from surrogate.threads import one_thread

# base kernel name -> Matern smoothness (None = RBF)
_NU = {"rbf": None, "matern12": 0.5, "matern32": 1.5, "matern52": 2.5}

#: rows per chunk of :meth:`CachedPsi.tabulate`: its (rows, M) temporaries stay in cache
TABULATE_ROWS = 4096


class ClassifierPair(Protocol):
    """What :class:`CachedPsi` reads of a :class:`~surrogate.gp.predictor.PsiClassifier` (a
    structural type: the predictor module tabulates through this one, so this one does not
    import it)."""

    @property
    def psi_0(self) -> FittedClassifier: ...  # origin phi = 0

    @property
    def psi_1(self) -> FittedClassifier: ...  # origin phi = 1

    @property
    def input_names(self) -> tuple[str, ...]: ...

    @property
    def domain(self) -> dict[str, tuple[float, float]]: ...

    @property
    def device(self) -> torch.device: ...

    def __call__(self, phi: Tensor, z: Tensor) -> Tensor: ...


def _base_kernel(fitted: FittedClassifier) -> tuple[float | None, Tensor, float]:
    """(Matern nu or None for RBF, lengthscales (d,), outputscale) of a fitted classifier."""
    covar = fitted.model.covar_module
    if not isinstance(covar, gpytorch.kernels.ScaleKernel):
        raise TypeError(f"CachedPsi needs a ScaleKernel, got {type(covar).__name__}")
    base = covar.base_kernel
    if isinstance(base, gpytorch.kernels.RBFKernel):
        nu = None
    elif isinstance(base, gpytorch.kernels.MaternKernel):
        nu = float(base.nu)
    else:
        raise TypeError(f"CachedPsi supports RBF and Matern kernels, got {type(base).__name__}")
    d = fitted.model.variational_strategy.inducing_points.shape[-1]
    lengthscale = base.lengthscale.detach().reshape(-1).expand(d)
    return nu, lengthscale, float(covar.outputscale.detach())


@torch.no_grad()
def _factors(fitted: FittedClassifier) -> dict[str, Any]:
    """Everything of one classifier's predictive that does not depend on the query point."""
    fitted.model.eval()
    fitted.likelihood.eval()
    strategy = fitted.model.variational_strategy
    if not isinstance(strategy, gpytorch.variational.VariationalStrategy):
        raise TypeError(f"CachedPsi needs a (whitened) VariationalStrategy, got {type(strategy)}")
    nu, lengthscale, outputscale = _base_kernel(fitted)
    z = strategy.inducing_points.detach()
    jitter = float(strategy.jitter_val)
    # K_zz exactly as gpytorch forms it (model dtype, + jitter), factorised in float64 by the same
    # routine (psd_safe_cholesky adds more jitter only if the factorisation fails)
    k_zz = fitted.model.covar_module(z).to_dense() + jitter * torch.eye(
        z.shape[0], dtype=z.dtype, device=z.device
    )
    chol = psd_safe_cholesky(k_zz.to(torch.float64))
    q_u = strategy.variational_distribution  # N(m_u, S), whitened
    m_u = q_u.mean.detach().to(torch.float64)
    s = q_u.covariance_matrix.detach().to(torch.float64)
    eye = torch.eye(z.shape[0], dtype=torch.float64, device=z.device)
    # S - I = V diag(d) V^T: a^T (S - I) a = sum_j d_j (v_j^T a)^2
    d, v = torch.linalg.eigh(0.5 * (s + s.mT) - eye)
    inv_t = torch.linalg.solve_triangular(chol, eye, upper=False).mT  # L^{-T}
    g = torch.cat([inv_t @ v, (inv_t @ m_u).unsqueeze(-1)], dim=1)
    return {
        "nu": nu,
        "shift": fitted.normaliser.mean.detach(),  # normalised x = (x - shift) / std
        "scale": fitted.normaliser.std.detach() * lengthscale,  # ... / lengthscale
        "z": z,  # inducing points, normalised space
        "lengthscale": lengthscale,
        "g": g,
        "d": d,
        **_prior_mean(fitted),
        "prior_var": outputscale + jitter,
        "outputscale": outputscale,
    }


def _prior_mean(fitted: FittedClassifier) -> dict[str, Any]:
    """The prior mean c + w^T x_normalised as raw-input terms: ``mean`` (c less the shift's
    share) and ``slope`` (``d``; None for a constant mean)."""
    module = fitted.model.mean_module
    if isinstance(module, gpytorch.means.ConstantMean):
        return {"mean": float(module.constant.detach()), "slope": None}
    weights = module.weights.detach().reshape(-1).to(torch.float64)  # normalised-input slopes
    norm = fitted.normaliser
    slope = weights / norm.std.detach().to(torch.float64)
    bias = float(module.bias.detach()) - float((slope * norm.mean.detach()).sum())
    return {"mean": bias, "slope": slope}


class CachedPsi:
    """psi_phi(z) = p(phi' = 1 | phi, z) of a :class:`PsiClassifier`, in closed form.

    Build with :meth:`from_classifier`; call like the classifier: ``psi(phi, z)`` (``z``:
    ``n x d``) -> float32 probabilities on the inputs' device. Agrees with
    ``PsiClassifier.__call__`` to ~2e-5 (the size of gpytorch's own float32 round-off; see the
    tests).

    Per query the work is one small matmul for the exponents (inputs augmented as
    [u, |u|^2, 1] against [2w; -1; -|w|^2], so -|u - w|^2 comes out of the matmul, centred on
    the inducing points to keep the float32 cancellation small), one ``exp`` over (rows, M) and
    one (rows, M) x (M, M + 1) matmul (S - I = V diag(d) V^T is folded into the cache, so
    a^T (S - I) a = sum_j d_j (v_j^T a)^2). On the CPU, calls with at least ``split_rows`` rows
    evaluate each classifier only on its own rows (one host sync for the row split, half the
    flops; run eagerly even inside ``torch.compile``); otherwise (small calls, CUDA) both
    classifiers are evaluated on every row and each row selects its own, with no sync.
    """

    def __init__(
        self,
        factors: tuple[dict[str, Any], dict[str, Any]],
        input_names: tuple[str, ...] | list[str],
        domain: dict[str, tuple[float, float]] | None = None,
        dtype: torch.dtype = torch.float32,
        split_rows: int = 4096,
        warps: dict[str, float] | None = None,
    ) -> None:
        phi0, phi1 = factors  # the classifiers of origin phi = 0 and phi = 1
        if phi0["nu"] != phi1["nu"] or phi0["z"].shape != phi1["z"].shape:
            raise ValueError("CachedPsi: both classifiers must share the kernel and inducing count")
        self.nu: float | None = phi0["nu"]
        self.input_names = tuple(input_names)
        self.domain = dict(domain) if domain else {}
        self.dtype = dtype
        self.split_rows = int(split_rows)
        # like PsiClassifier: refuse NaN/inf inputs on direct calls (a host sync per call; the
        # simulation loop turns it off and checks its state at record times instead)
        self.check_finite = True
        self.n_inducing = int(phi0["z"].shape[0])
        # inputs the classifiers read on a log axis (PsiClassifier.warps): raw values come in
        self.warps = dict(warps or {})
        self.warp_knees = torch.tensor([self.warps.get(n, 1.0) for n in self.input_names],
                                       dtype=dtype)  # fmt: skip
        self.warped = torch.tensor([n in self.warps for n in self.input_names])
        # RBF: k = exp(-|x - z|^2 / 2) in lengthscale units, so work with u = x / sqrt(2) and
        # get -|u - w|^2 = -r^2 / 2; Matern needs r itself: u = x, r = sqrt(|u - w|^2).
        half = 1.0 / math.sqrt(2.0) if self.nu is None else 1.0
        x_gain, x_bias, w_aug, g, d = [], [], [], [], []
        for f in (phi0, phi1):
            f64 = {k: v.to(torch.float64) for k, v in f.items() if isinstance(v, Tensor)}
            w = f64["z"] / f64["lengthscale"] * half  # inducing points in u units (M, d)
            centre = w.mean(0)
            w = w - centre
            gain = half / f64["scale"]  # u = (x - shift) * gain - centre
            x_gain.append(gain)
            x_bias.append(-f64["shift"] * gain - centre)
            ones = torch.ones_like(w[:, 0])
            w_aug.append(torch.cat([2.0 * w.mT, -ones[None], -(w * w).sum(1)[None]], 0))
            g.append(f64["g"] * f["outputscale"])
            d.append(f64["d"])
        # (2, ...) tensors, index = origin phi
        self.x_gain = torch.stack(x_gain).to(dtype)  # (2, d)
        self.x_bias = torch.stack(x_bias).to(dtype)  # (2, d)
        self.w_aug = torch.stack(w_aug).to(dtype)  # (2, d + 2, M)
        self.g = torch.stack(g).to(dtype)  # (2, M, M + 1), outputscale folded in
        self.d = torch.stack(d).to(dtype)  # (2, M) eigenvalues of S - I
        self.mean = torch.tensor([phi0["mean"], phi1["mean"]], dtype=dtype)
        # a linear prior mean: (2, d) slopes on the raw inputs (None: constant, no extra op);
        # both classifiers share one GP setting, so both or neither have one
        self.mean_slope: Tensor | None = (
            None if phi0.get("slope") is None
            else torch.stack([phi0["slope"].cpu(), phi1["slope"].cpu()]).to(dtype)
        )  # fmt: skip
        self.prior_var = torch.tensor([phi0["prior_var"], phi1["prior_var"]], dtype=dtype)
        self.to(phi0["z"].device)

    @classmethod
    def from_classifier(
        cls, psi: ClassifierPair, dtype: torch.dtype = torch.float32, split_rows: int = 4096
    ) -> CachedPsi:
        """Cache the factors of both classifiers of ``psi`` (on its device)."""
        # M x M factorisations (M ~ 200): a second CPU thread only slows them, and on a busy
        # box the threaded eigh took 0.3-3 s where one thread takes 0.015 s (measured)
        with one_thread(psi.device.type == "cpu"):
            factors = (_factors(psi.psi_0), _factors(psi.psi_1))
        return cls(factors, psi.input_names, psi.domain, dtype, split_rows,
                   getattr(psi, "warps", None))  # fmt: skip

    @property
    def device(self) -> torch.device:
        """Device of the cached factors."""
        return self.g.device

    def to(self, device: torch.device | str) -> CachedPsi:
        """Move the cached factors to ``device`` in place; return self."""
        for name in ("x_gain", "x_bias", "w_aug", "g", "d", "mean", "prior_var", "warp_knees",
                     "warped"):  # fmt: skip
            setattr(self, name, getattr(self, name).to(device))
        if self.mean_slope is not None:
            self.mean_slope = self.mean_slope.to(device)
        return self

    def _kernel(self, e: Tensor) -> Tensor:
        """Unit-variance kernel from e = -|u - w|^2 (RBF: exp(e); Matern: r = sqrt(-e))."""
        if self.nu is None:
            return torch.exp(e)
        r = torch.sqrt(torch.clamp(-e, min=0.0))
        if self.nu == 0.5:
            return torch.exp(-r)
        s = math.sqrt(2.0 * self.nu) * r
        if self.nu == 1.5:
            return (1.0 + s) * torch.exp(-s)
        return (1.0 + s + s * s / 3.0) * torch.exp(-s)

    def _kernel_(self, e: Tensor) -> Tensor:
        """:meth:`_kernel` computed in ``e``'s memory (``e`` a temporary): fewer passes and
        allocations, for large evaluations; the same function, rounded in another order."""
        if self.nu is None:
            return e.exp_()
        r = e.neg_().clamp_min_(0.0).sqrt_()
        if self.nu == 0.5:
            return r.neg_().exp_()
        s = r.mul_(math.sqrt(2.0 * self.nu))
        decay = s.neg().exp_()
        if self.nu == 2.5:
            s.addcmul_(s, s, value=1.0 / 3.0)  # s + s^2 / 3
        return s.add_(1.0).mul_(decay)

    def _latent(self, x: Tensor, c: int | None, inplace: bool = False) -> tuple[Tensor, Tensor]:
        """Latent mean and variance at raw inputs ``x`` (n, d): of classifier ``c``, or of both
        ((2, n) each) when ``c`` is None; ``inplace``: the kernel by :meth:`_kernel_` (eager
        evaluations only: a compiled step fuses :meth:`_kernel` anyway)."""
        sel = slice(None) if c is None else c
        if c is None:  # (2, n, d)
            u = x.unsqueeze(0) * self.x_gain.unsqueeze(1) + self.x_bias.unsqueeze(1)
        else:
            u = x * self.x_gain[c] + self.x_bias[c]
        u_aug = torch.cat([u, (u * u).sum(-1, keepdim=True), torch.ones_like(u[..., :1])], -1)
        e = torch.matmul(u_aug, self.w_aug[sel])  # -|u - w|^2, (.., n, M)
        k = self._kernel_(e) if inplace else self._kernel(e)
        out = torch.matmul(k, self.g[sel])  # (.., n, M + 1)
        n_ind = self.n_inducing
        y = out[..., :n_ind]  # V^T a
        mean = out[..., n_ind] + (self.mean[sel, None] if c is None else self.mean[c])
        if self.mean_slope is not None:  # a linear prior mean: each classifier's slope on x
            trend = torch.matmul(x, self.mean_slope.mT).mT if c is None else x @ self.mean_slope[c]
            mean = mean + trend
        var = torch.matmul(y * y, self.d[sel].unsqueeze(-1)).squeeze(-1)  # a^T (S - I) a
        return mean, var + (self.prior_var[sel, None] if c is None else self.prior_var[c])

    def latent(self, z: Tensor) -> tuple[Tensor, Tensor]:
        """Latent mean and variance (``2 x n``) of both classifiers at raw inputs ``z``."""
        return self._latent(self._inputs(z), None)

    def spread(self, phi: Tensor, z: Tensor) -> tuple[Tensor, Tensor]:
        """psi at ``z`` (``n x d``) for origins ``phi`` (``(n,)``) and its posterior standard
        deviation, ``phi(mu) sigma`` (the probit link's delta method: psi = Phi(f), f ~ N(mu,
        sigma^2) under the variational posterior); both float32 on ``z``'s device."""
        mean, var = self._latent(self._inputs(z), None)  # (2, n)
        one = phi.to(self.device).reshape(-1).to(mean.dtype) > 0
        mu, v = torch.where(one, mean[1], mean[0]), torch.where(one, var[1], var[0])
        p = torch.special.ndtr(mu * torch.rsqrt(1.0 + v))
        sd = torch.exp(-0.5 * mu * mu) / math.sqrt(2.0 * math.pi) * torch.sqrt(v.clamp_min(0.0))
        return p.to(z.device, torch.float32), sd.to(z.device, torch.float32)

    def _inputs(self, z: Tensor) -> Tensor:
        """``z`` as ``n x d`` on the cache's device and dtype (a 1-D ``z`` for one input)."""
        d = len(self.input_names)
        z = z.reshape(-1, 1) if z.dim() == 1 and d == 1 else z
        if z.dim() != 2 or z.shape[1] != d:
            raise ValueError(
                f"psi takes {d} input column(s) {self.input_names}, got {tuple(z.shape)}"
            )
        z = z.to(self.device, self.dtype)
        if self.warps:  # log(1 + z / knee) on the warped columns (PsiClassifier.warps)
            z = torch.where(self.warped, torch.log1p(z.clamp(min=0.0) / self.warp_knees), z)
        return z

    def __call__(self, phi: Tensor, z: Tensor) -> Tensor:
        """p(phi' = 1) (float32, on ``z``'s device); refuses NaN/inf inputs while
        ``check_finite`` is true (a host sync per call)."""
        if self.check_finite and not bool(torch.isfinite(z).all()):
            raise NumericalError(f"CachedPsi got NaN or infinite inputs {self.input_names}")
        return self.evaluate(phi, z)

    def evaluate(self, phi: Tensor, z: Tensor) -> Tensor:
        """Pure form of :meth:`__call__` (no checks; no host sync unless rows are split)."""
        out_device = z.device
        x = self._inputs(z)
        one = phi.to(self.device).reshape(-1)
        if one.shape[0] != x.shape[0]:
            raise ValueError(f"phi has {one.shape[0]} rows but the inputs have {x.shape[0]}")
        if self.device.type == "cpu" and x.shape[0] >= self.split_rows:
            out = self._split_rows(one, x)
        else:
            mean, var = self._latent(x, None)
            p = torch.special.ndtr(mean * torch.rsqrt(1.0 + var))  # (2, n)
            out = torch.where(one.to(p.dtype) > 0, p[1], p[0])
        return out.to(out_device, torch.float32)

    def _split_rows_impl(
        self, phi: Tensor, x: Tensor, chunk: int | None = None, inplace: bool = False
    ) -> Tensor:
        """Each classifier on its own rows only (one host sync for the split), ``chunk`` rows
        at a time (None: all at once), the kernel in place where ``inplace``."""
        one = phi.bool()
        out = torch.empty(x.shape[0], dtype=self.dtype, device=self.device)
        for c, rows in ((0, (~one).nonzero().squeeze(1)), (1, one.nonzero().squeeze(1))):
            step = chunk or max(1, rows.numel())
            for start in range(0, rows.numel(), step):
                part = rows[start : start + step]
                mean, var = self._latent(x.index_select(0, part), c, inplace=inplace)
                out[part] = torch.special.ndtr(mean * torch.rsqrt(1.0 + var))
        return out

    @torch.no_grad()
    def tabulate(self, phi: Tensor, z: Tensor) -> Tensor:
        """:meth:`evaluate` for many rows at once, e.g. every node of a lookup table's grid
        (:meth:`PsiClassifier.tabulator <surrogate.gp.predictor.PsiClassifier.tabulator>`):
        each classifier on its own rows only (one host sync, on any device), in chunks of
        ``TABULATE_ROWS`` rows so that the working set (a few ``TABULATE_ROWS x M`` floats)
        stays in cache, the kernel computed in place. The same values as :meth:`evaluate` up to
        float32 rounding; eager only (not for a compiled step).

        Args:
            phi: ``(n,)`` origins 0/1.
            z: ``n x d`` raw inputs.

        Returns:
            ``(n,)`` float32 p(phi' = 1) on ``z``'s device.
        """
        x = self._inputs(z)
        one = phi.to(self.device).reshape(-1)
        if one.shape[0] != x.shape[0]:
            raise ValueError(f"phi has {one.shape[0]} rows but the inputs have {x.shape[0]}")
        out = self._split_rows_impl(one, x, chunk=TABULATE_ROWS, inplace=True)
        return out.to(z.device, torch.float32)

    def _split_rows(self, phi: Tensor, x: Tensor) -> Tensor:
        """:meth:`_split_rows_impl`, eagerly even inside a compiled simulation step (a graph
        break there: data-dependent row counts), since halving the matmul outweighs the break
        at these sizes."""
        if torch.compiler.is_compiling():
            return _eager_split_rows()(self, phi, x)
        return self._split_rows_impl(phi, x)

    @torch.no_grad()
    def max_deviation(self, psi: ClassifierPair, n_check: int = 4096, seed: int = 0) -> float:
        """Max |cached - psi| over ``n_check`` random (phi, z) points in ``psi.domain`` (widened
        by 10 % on each side; the unit box for an input without a known range)."""
        gen = torch.Generator().manual_seed(seed)
        cols = []
        for key in self.input_names:
            lo, hi = self.domain.get(key, (0.0, 1.0))
            pad = 0.1 * (hi - lo)
            cols.append(lo - pad + (hi - lo + 2 * pad) * torch.rand(n_check, generator=gen))
        z = torch.stack(cols, -1)
        phi = torch.randint(0, 2, (n_check,), generator=gen)
        dev = psi.device
        exact = psi(phi.to(dev), z.to(dev)).to("cpu", torch.float64)
        approx = self(phi.to(self.device), z.to(self.device))
        return float((approx.to("cpu", torch.float64) - exact).abs().max())


@functools.cache
def _eager_split_rows() -> Callable[[CachedPsi, Tensor, Tensor], Tensor]:
    """``CachedPsi._split_rows_impl`` wrapped by ``torch.compiler.disable`` at first use under
    ``torch.compile``, not at import: the wrapper imports ``torch._dynamo`` (~1.5-2 s), which
    a process that never compiles need not pay."""
    return torch.compiler.disable(CachedPsi._split_rows_impl)


__all__ = ["CachedPsi", "ClassifierPair"]
