"""The E. coli body's scalar formulas, each written once for both loops.

Receptor signal, CheY-P and dG, motor rates, the OU methylation step, movement and tumble
angles, and one motor's exact window. Each function is a scalar formula of
:mod:`surrogate.scalar`: called directly it computes over tensors (the torch step, through the
wrappers of ``signalling``, ``motors`` and ``body``), and :func:`numba_formulas` compiles the
same code per cell for the kernel (:mod:`surrogate.models.ecoli.kernel`), in the same
operations and precision (float32 signalling, OU and movement; float64 motor rates and
transition terms). Formulas: ``ecoli-parameters.md`` (Sneddon et al. 2012); the paper's Yp
formula has a typo in the TSR factor, corrected here (K_TSR_on in the TSR denominator).

Constants come as ``c``, a row in :data:`CONSTANTS` order (index names below): Python floats
from :func:`constants` on the torch path, the same values rounded to float32 in the kernel
(torch rounds a Python float to the tensor's dtype, so both compute with the same numbers).
"""

from __future__ import annotations

import math
from types import ModuleType
from typing import Any

from surrogate.scalar import (
    choose,
    clamp,
    clamp_min,
    complement_product,
    cos,
    exp,
    expm1,
    f32,
    flag,
    log,
    log1p,
    maximum,
    minimum,
    numba_formulas,
    remainder,
    sigmoid,
    sin,
    to64,
    where,
)

#: a motor's states (float 0., 1., 2.): semicoiled, curly (both CW) and normal (CCW)
S, C, N = 0, 1, 2

#: the body's constants, as :func:`constants` computes them (the kernel's float32 row)
CONSTANTS = (
    "n_tar", "k_tar_off", "k_tar_on", "n_tsr", "k_tsr_off", "k_tsr_on", "eps0", "eps1", "alpha",
    "g0_4", "g1_2", "k_d", "m0_offset", "dt_tau", "ou_scale", "m_min", "m_max", "step_len",
    "tumble_scale", "two_pi",
)  # fmt: skip
(N_TAR, K_TAR_OFF, K_TAR_ON, N_TSR, K_TSR_OFF, K_TSR_ON, EPS0, EPS1, ALPHA, G0_4, G1_2, K_D,
 M0_OFFSET, DT_TAU, OU_SCALE, M_MIN, M_MAX, STEP_LEN, TUMBLE_SCALE, TWO_PI) = range(len(CONSTANTS))  # fmt: skip


def constants(p: Any, dt: float = 0.0) -> tuple[float, ...]:
    """The constants of :data:`CONSTANTS` for parameters ``p`` (``EcoliParameters``) and time
    step ``dt`` (s; the OU and movement entries; 0 where only the signal is needed), each
    computed in double (as Python floats)."""
    return (
        float(p.n_tar), p.k_tar_off, p.k_tar_on, float(p.n_tsr), p.k_tsr_off, p.k_tsr_on,
        p.eps0, p.eps1, p.alpha, p.g0 / 4.0, p.g1 / 2.0, p.k_d,
        math.log(p.alpha / p.yp_adapted - 1.0) - p.eps0,
        dt / p.tau, p.sigma_m * math.sqrt(2.0 * dt / p.tau), p.m_min, p.m_max, p.speed * dt,
        math.radians(p.tumble_scale_deg), 2 * math.pi,
    )  # fmt: skip


# -- signalling (float32) ------------------------------------------------------------------
def log_receptor_terms(ligand, c):
    """ln(TarTerm(L)) + ln(TsrTerm(L)), with TarTerm = ((1 + L/K_off) / (1 + L/K_on))^n_TAR."""
    tar = c[N_TAR] * (log1p(ligand / c[K_TAR_OFF]) - log1p(ligand / c[K_TAR_ON]))
    tsr = c[N_TSR] * (log1p(ligand / c[K_TSR_OFF]) - log1p(ligand / c[K_TSR_ON]))
    return tar + tsr


def free_energy(methylation, receptor_terms, c):
    """Receptor-cluster free energy F(m, L) = eps0 + eps1 m + ln TarTerm + ln TsrTerm (kT)."""
    return c[EPS0] + c[EPS1] * methylation + receptor_terms


def activity(energy):
    """The MWC cluster activity a = 1 / (1 + exp(F)) (as sigmoid(-F): stable for large |F|)."""
    return sigmoid(-energy)


def cheyp(act, c):
    """CheY-P Yp = alpha a (uM) at activity ``act``."""
    return c[ALPHA] * act


def delta_g(yp, c):
    """dG = g0/4 - (g1/2) Yp / (Yp + K_D) (kT): the motor's CW/CCW free-energy difference."""
    return c[G0_4] - c[G1_2] * yp / (yp + c[K_D])


def signal(methylation, receptor_terms, c):
    """(F, activity, CheY-P, dG) from m and the receptor terms, each computed once."""
    energy = free_energy(methylation, receptor_terms, c)
    act = activity(energy)
    yp = cheyp(act, c)
    return energy, act, yp, delta_g(yp, c)


def rates(dg, omega):
    """(k+, k-) = omega exp(+-dG) in 1/s, float64 (k+ reaches ~3e4/s at Yp = 0)."""
    dg = to64(dg)
    return omega * exp(dg), omega * exp(-dg)


# -- adaptation: the OU methylation step (float32) --------------------------------------------
def adapted_methylation(receptor_terms, c):
    """m0(L) = [ln(alpha/Yp* - 1) - eps0 - ln TarTerm(L) - ln TsrTerm(L)] / eps1: Yp(m0, L) = Yp*."""
    return (c[M0_OFFSET] - receptor_terms) / c[EPS1]


def ou_step(methylation, receptor_terms, noise, c):
    """One Euler-Maruyama step of the methylation OU process, clamped to [m_min, m_max]:
    m + (m0(L) - m) dt / tau + sigma_m sqrt(2 dt / tau) ``noise`` (~ N(0, 1))."""
    drift = (adapted_methylation(receptor_terms, c) - methylation) * c[DT_TAU]
    return clamp(methylation + drift + c[OU_SCALE] * noise, c[M_MIN], c[M_MAX])


# -- movement (float32) -----------------------------------------------------------------------
def run_step(x, y, heading, phi_after, c):
    """The position after a step: ``speed * dt`` along the heading when running (``phi_after``
    1), else where it was."""
    step_len = phi_after * c[STEP_LEN]
    return x + cos(heading) * step_len, y + sin(heading) * step_len


def turning(phi_before, phi_after, per_tumble):
    """Whether the cell turns this step (> 0): at every step spent tumbling, or only at the
    start of a tumble (``per_tumble``)."""
    return phi_before * (f32(1.0) - phi_after) if per_tumble else f32(1.0) - phi_after


def tumble_angle(u, first, k, scale):
    """A Gamma(k, scale) angle from ``u[first]`` ... ``u[first + k - 1]`` (uniforms in [0, 1),
    k >= 1): scale * (sum of k Exp(1)) = -scale ln(prod of (1 - u)), the products in groups of
    4 (1 - u lies in (0, 1], and a product of <= 4 of them stays a normal float32)."""
    total = log(complement_product(u, first, first + min(4, k)))
    for i in range(4, k, 4):
        total = total + log(complement_product(u, first + i, first + min(i + 4, k)))
    return total * (-scale)


def turn(heading, angle, sign_u, c):
    """The heading turned by ``angle`` with a random sign (- when ``sign_u`` < 0.5), in
    [0, 2 pi)."""
    return remainder(heading + where(sign_u < 0.5, -angle, angle), c[TWO_PI])


# -- one motor's exact window (float64) ------------------------------------------------------
def _h(x):
    """(1 - e^{-x}) / x for x >= 0 (1 at x = 0), to full relative precision."""
    return where(x > 0, -expm1(-x) / x, 1.0)


def motor_transition_terms(k_plus, k_minus, dt, mu):
    """The six independent entries of one motor's exp(Q dt), in float64:
    (P_SS, P_CS, P_NS, P_SN = P_CN, P_NN, 1 - P_NN); P_xC = 1 - P_xS - P_xN (derivation:
    :mod:`surrogate.models.ecoli.motors`; accurate to ~1e-16 absolute for any rates)."""
    kp = to64(k_plus)
    km = to64(k_minus)
    a = mu + kp
    b = kp + km
    em1_a = expm1(-a * dt)  # e^{-A dt} - 1, in [-1, 0]
    em1_b = expm1(-b * dt)
    g = -em1_a / a  # (1 - e^{-A dt}) / A
    lo = 1.0 + maximum(em1_a, em1_b)  # e^{-min(A, B) dt}
    f = lo * dt * _h(abs(a - b) * dt)  # (e^{-B dt} - e^{-A dt}) / (A - B)
    relax = -em1_b / b  # (1 - e^{-B dt}) / B
    to_n = kp * relax  # P_SN = P_CN
    from_n = km * relax  # 1 - P_NN = P_NS + P_NC
    cross = kp * km / b
    p_cs = cross * clamp_min(g - f, 0.0)
    p_ss = (1.0 + em1_a) + p_cs
    p_ns = cross * g + (km * km / b) * f
    return p_ss, p_cs, p_ns, to_n, 1.0 - from_n, from_n


def motor_thresholds(k_plus, k_minus, dt, mu):
    """Cumulative thresholds (t1_S, t1_C, t1_N, t2_CW, t2_N) for one motor's next state from
    one uniform u: S if u < t1[s], C if t1[s] <= u < t2[s], else N (t1 = P_sS, t2 = 1 - P_sN;
    1 - P_SN = 1 - P_CN for both CW states)."""
    p_ss, p_cs, p_ns, to_n, _, from_n = motor_transition_terms(k_plus, k_minus, dt, mu)
    return p_ss, p_cs, minimum(p_ns, from_n), 1.0 - to_n, from_n


def next_motor_state(state, u, t1_s, t1_c, t1_n, t2_cw, t2_n):
    """A motor's next state (float 0., 1., 2.) from its ``state`` and uniform ``u``."""
    t1 = choose(state, t1_s, t1_c, t1_n)  # states S, C, N
    t2 = choose(state, t2_cw, t2_cw, t2_n)
    return flag(u >= t1) + flag(u >= t2)


def ccw(state):
    """1 for a motor in N (CCW), else 0: summed over a cell's motors, its N count."""
    return clamp_min(state - f32(1.0), f32(0.0))


def run_flag(n_ccw, lowest):
    """phi_RUN = (N >= 2) and (S == 0) as float 0/1, from the N count and the lowest state."""
    return flag(n_ccw >= 2) * flag(lowest > S)


FORMULAS = (log_receptor_terms, free_energy, activity, cheyp, delta_g, signal, rates,
            adapted_methylation, ou_step, run_step, turning, tumble_angle, turn, _h,
            motor_transition_terms, motor_thresholds, next_motor_state, ccw, run_flag)  # fmt: skip


def compiled() -> ModuleType:
    """The formulas compiled for numba kernels (:func:`surrogate.scalar.numba_formulas`)."""
    names = {"S": S, "C": C, "N": N} | {name.upper(): k for k, name in enumerate(CONSTANTS)}
    return numba_formulas(FORMULAS, names)
