"""E. coli with a stochastic CheY phosphorylation network: the expensive inner model.

Same cell as ``models/ecoli`` (4 motors S, C, N with S -> C at mu, C -> N and S -> N at k+,
N -> S at k-, k+- = omega exp(+-dG), dG = g0/4 - g1/2 Yp / (Yp + K_D)), but CheY-P is a molecule
count driven by a phosphorylation network whose input is the receptor activity a(m, L) of the
MWC model, supplied per cell:

    CheA  -> CheAp                at kA a [CheA]          (autophosphorylation, receptor-driven)
    CheAp + CheY -> CheA + CheYp  at kY [CheAp][CheY]     (phosphotransfer)
    CheYp -> CheY                 at (kZ [CheZ] + gY) [CheYp]  (CheZ phosphatase + autohydrolysis)

Concentrations are in uM; propensities (events/s) are rates in uM/s times ``N_PER_UM`` = 840
molecules per uM (cell volume ~1.4 fL: 1.4e-15 L x 6.022e23 / 1e6 = 843). In the SBML file
(``network.xml``) the compartment ``cell`` has size 840 in units of the volume where one molecule
is 1 uM, so a protein symbol in a kinetic law is its concentration in uM.

Constants and sources (the primary papers' tables could not be opened in this session; the values
are the ones those papers are cited for in later models (Vladimirov et al. 2008, PLoS Comput Biol
4:e1000242; Tu, Shimizu & Berg 2008, PNAS 105:14855) and should be re-checked against them):

* Totals (Li & Hazelbauer 2004, J Bacteriol 186:3687, strain RP437 in tryptone broth):
  CheA 5.3 uM (monomers), CheY 9.7 uM, CheZ 3.8 uM.
* kY = 100 uM^-1 s^-1: CheA-P -> CheY phosphotransfer (Stewart et al. 2000, Biochemistry
  39:13157; used by Kollmann et al. 2005, Nature 438:504).
* kZ [CheZ] = 30 s^-1: CheZ-mediated CheY-P dephosphorylation, gY = 0.1 s^-1 CheZ-independent
  hydrolysis (Kollmann et al. 2005; Vladimirov et al. 2008).
* mu, omega, g0, g1, K_D, 4 motors: as models/ecoli (Sneddon, Pontius & Emonet 2012).

Calibration (:func:`calibrate_k_autophosphorylation`): kA is the one constant solved for, as the
least constrained in vivo (it lumps receptor-coupled CheA activity). At the adapted activity
a* = Yp*/alpha = 2.7/6 = 0.45 the mean-field steady state must have Yp = Yp* = 2.7 uM, the first
model's adapted CheY-P (CW bias 1 / (1 + exp(2 dG)) = 0.2227). With Y = Y_T - Yp*, steady state of
CheY-P gives the flux J = (kZ [CheZ] + gY) Yp*, steady state of CheA-P gives
Ap = J / (kY Y), and autophosphorylation must carry the same flux: kA = J / (a* (A_T - Ap)).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

N_PER_UM = 840.0  # molecules per uM in a 1.4 fL cell


@dataclass(frozen=True)
class PhosphoConstants:
    """Constants of the phospho network (concentrations in uM, rates in 1/s or 1/(uM s)).

    Attributes: see the module docstring for sources. ``k_a`` is None until calibrated.
    """

    cheA_total: float = 5.3
    cheY_total: float = 9.7
    cheZ: float = 3.8
    k_y: float = 100.0
    k_z_cheZ: float = 30.0  # kZ [CheZ], 1/s
    gamma_y: float = 0.1
    k_a: float | None = None
    adapted_activity: float = 0.45  # a* = Yp* / alpha
    adapted_cheyp: float = 2.7  # Yp*, uM
    n_motors: int = 4
    mu: float = 5.0
    omega: float = 1.3
    g0: float = 40.0
    g1: float = 40.0
    k_d: float = 3.06
    n_per_um: float = N_PER_UM

    @property
    def k_z(self) -> float:
        """CheZ phosphatase constant per uM CheZ (1/(uM s))."""
        return self.k_z_cheZ / self.cheZ


def calibrate_k_autophosphorylation(c: PhosphoConstants) -> float:
    """kA (1/s) such that the mean-field steady state at ``adapted_activity`` has
    CheY-P = ``adapted_cheyp`` (see the module docstring for the equations)."""
    y_free = c.cheY_total - c.adapted_cheyp
    if y_free <= 0:
        raise ValueError(f"adapted_cheyp {c.adapted_cheyp} must be below cheY_total {c.cheY_total}")
    flux = (c.k_z_cheZ + c.gamma_y) * c.adapted_cheyp
    ap = flux / (c.k_y * y_free)
    if ap >= c.cheA_total:
        raise ValueError("no steady state: the phosphotransfer cannot carry the required flux")
    return flux / (c.adapted_activity * (c.cheA_total - ap))


def calibrated(c: PhosphoConstants | None = None) -> PhosphoConstants:
    """The constants with kA solved by :func:`calibrate_k_autophosphorylation`."""
    c = c or PhosphoConstants()
    return replace(c, k_a=calibrate_k_autophosphorylation(c))


def mean_field_steady_state(c: PhosphoConstants, activity: float) -> tuple[float, float]:
    """(CheA-P, CheY-P) in uM at the deterministic steady state for a given activity.

    From kA a (A_T - Ap) = kY Ap (Y_T - Yp) = d Yp with d = kZ [CheZ] + gY: Ap = d Yp /
    (kY (Y_T - Yp)) and kA a (A_T - Ap) = d Yp, a quadratic in Yp solved for its root in
    (0, Y_T).
    """
    if c.k_a is None:
        raise ValueError("k_a is not set: use calibrated(constants)")
    d, ka = c.k_z_cheZ + c.gamma_y, c.k_a * activity

    def balance(yp: float) -> float:
        ap = d * yp / (c.k_y * (c.cheY_total - yp))
        return ka * (c.cheA_total - ap) - d * yp

    lo, hi = 0.0, c.cheY_total * (1 - 1e-15)
    for _ in range(200):  # bisection: balance is decreasing on (0, Y_T)
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if balance(mid) > 0 else (lo, mid)
    yp = 0.5 * (lo + hi)
    return d * yp / (c.k_y * (c.cheY_total - yp)), yp


def relaxation_rates(c: PhosphoConstants, activity: float) -> tuple[float, float]:
    """Decay rates (1/s) of the linearised (CheA-P, CheY-P) dynamics at the steady state."""
    ap, yp = mean_field_steady_state(c, activity)
    assert c.k_a is not None
    d = c.k_z_cheZ + c.gamma_y
    jacobian = np.array(
        [
            [-(c.k_a * activity + c.k_y * (c.cheY_total - yp)), c.k_y * ap],
            [c.k_y * (c.cheY_total - yp), -(c.k_y * ap + d)],
        ]
    )
    rates = sorted(-np.linalg.eigvals(jacobian).real)
    return float(rates[0]), float(rates[1])


def cw_bias(cheyp: float, c: PhosphoConstants) -> float:
    """Stationary CW bias k- / (k+ + k-) = 1 / (1 + exp(2 dG)) at a CheY-P level (uM)."""
    dg = c.g0 / 4 - c.g1 / 2 * cheyp / (cheyp + c.k_d)
    return 1.0 / (1.0 + math.exp(2 * dg))


__all__ = [
    "N_PER_UM",
    "PhosphoConstants",
    "calibrate_k_autophosphorylation",
    "calibrated",
    "cw_bias",
    "mean_field_steady_state",
    "relaxation_rates",
]
