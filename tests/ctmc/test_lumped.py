"""The exact lumped psi: state-space enumeration, generator, stationary law, exp(Q dt) lumped.

References computed independently: the four motors as an 81-state chain of DISTINGUISHABLE
motors (Kronecker sum of the one-motor generator, scipy's expm), the stationary law as a
multinomial of the one-motor law, and long full-model runs at fixed inputs (binomial bounds).
"""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
import scipy.linalg
import torch

from surrogate.ctmc import ReactionNetwork
from surrogate.ctmc.lumped import StateSpace, lumped_psi, stationary_distribution
from surrogate.models.ecoli import EcoliParameters, is_run
from surrogate.models.ecoli.internal import MotorInternalModel
from surrogate.models.ecoli.motors import (
    FLAGELLA_NETWORK,
    exact_run_probability,
    population_space,
    rate_constants,
)

P = EcoliParameters()
DT = 0.05
# (k+, k-): adapted (CW bias ~0.22), CW-biased, CCW-saturated (k+ ~ 3e4, stiff), balanced
RATES = [(2.43, 0.695), (0.5, 3.38), (3.0e4, 1.69 / 3.0e4), (1.3, 1.3)]


def test_enumerates_the_motor_population() -> None:
    space = population_space(4)
    assert space.n_states == 15
    states = {tuple(s) for s in space.states.tolist()}
    assert states == {s for s in itertools.product(range(5), repeat=3) if sum(s) == 4}
    assert space.states[0].tolist() == [0, 0, 4]


def test_too_large_a_state_space_is_refused() -> None:
    birth = ReactionNetwork.from_reactions(["A"], [("birth", {}, {"A": 1})])
    with pytest.raises(ValueError, match="max_states=50"):
        StateSpace.enumerate(birth, torch.tensor([0]), max_states=50)


def _one_motor_generator(kp: float, km: float) -> np.ndarray:
    mu = P.mu
    return np.array([[-(mu + kp), mu, kp], [0.0, -kp, kp], [km, 0.0, -km]])  # S, C, N


def _distinguishable(kp: float, km: float) -> tuple[np.ndarray, np.ndarray]:
    """81-state generator of 4 distinguishable motors and each state's RUN flag."""
    q1 = _one_motor_generator(kp, km)
    eye = np.eye(3)
    q = np.zeros((81, 81))
    for i in range(4):
        mats = [eye] * 4
        mats[i] = q1
        term = mats[0]
        for m in mats[1:]:
            term = np.kron(term, m)
        q += term
    run = []
    for states in itertools.product(range(3), repeat=4):
        n_ccw = sum(s == 2 for s in states)
        run.append(n_ccw >= 2 and all(s != 0 for s in states))
    return q, np.array(run)


@pytest.mark.parametrize(("kp", "km"), RATES)
def test_stationary_law_is_the_multinomial_of_the_one_motor_law(kp: float, km: float) -> None:
    space = population_space(4)
    f64 = torch.float64
    q = space.generator(
        rate_constants(torch.tensor([kp], dtype=f64), torch.tensor([km], dtype=f64), P)
    )
    pi = stationary_distribution(q)[0].numpy()
    w = np.array([1.0, P.mu / kp, (P.mu + kp) / km])
    p1 = w / w.sum()
    expected = [
        math.factorial(4) / math.prod(math.factorial(c) for c in s) * np.prod(p1 ** np.array(s))
        for s in space.states.tolist()
    ]
    np.testing.assert_allclose(pi, expected, rtol=1e-9, atol=1e-15)


@pytest.mark.parametrize(("kp", "km"), RATES)
def test_lumped_psi_matches_distinguishable_motors(kp: float, km: float) -> None:
    q, run = _distinguishable(kp, km)
    # stationary law of the 81-state chain: the product of one-motor laws
    w = np.array([1.0, P.mu / kp, (P.mu + kp) / km])
    p1 = w / w.sum()
    pi = np.array(
        [np.prod([p1[s] for s in states]) for states in itertools.product(range(3), repeat=4)]
    )
    transition = scipy.linalg.expm(q * DT)
    to_run = transition[:, run].sum(1)
    expected = [
        float((pi * (run == phi) * to_run).sum() / (pi * (run == phi)).sum()) for phi in (0, 1)
    ]
    f64 = torch.float64
    got = exact_run_probability(torch.tensor([kp], dtype=f64), torch.tensor([km], dtype=f64), DT, P)
    got = got[0].numpy()
    np.testing.assert_allclose(got, expected, rtol=1e-8, atol=1e-12)


@pytest.mark.parametrize(("m", "L"), [(2.2, 0.0), (2.15, 0.0), (2.25, 0.0), (2.9, 0.05)])
def test_lumped_psi_matches_long_full_model_runs_at_fixed_inputs(m: float, L: float) -> None:
    """Full-model cells started far from stationarity (every motor CCW) and run 5 s (> 10
    relaxation times) at fixed inputs, then one more window each: the frequency of phi' = 1
    among cells in lump phi is the exact psi, within 5 binomial standard errors (100,000
    independent cells)."""
    torch.manual_seed(11)
    internal = MotorInternalModel(P)
    n = 100_000
    x = torch.tensor([[m, L]]).expand(n, 2).contiguous()
    counts = torch.zeros(n, 3, dtype=torch.int64)
    counts[:, 2] = P.n_motors
    state = internal.state_from_counts(counts)
    for _ in range(100):
        state = internal.advance(state, x, DT)
    phi = internal.phi(state)
    nxt = internal.phi(internal.advance(state, x, DT))
    exact = internal.exact_psi(internal.features(x[:1], ("dG",)).double(), DT)[0].numpy()
    checked = 0
    for a in (0, 1):
        sel = phi == a
        total = int(sel.sum())
        if total < 2000:  # the lump is (almost) never occupied at these inputs
            continue
        freq = float(nxt[sel].mean())
        se = math.sqrt(max(exact[a] * (1 - exact[a]), 1e-6) / total)
        assert abs(freq - exact[a]) < 5 * se, (a, freq, exact[a], se)
        checked += 1
    assert checked >= 1


def test_lumped_psi_of_a_dimerisation_network() -> None:
    """A closed non-first-order network (2A <-> B, 6 A-equivalents): the lumped psi from the
    enumerated generator equals a direct computation on the 4 states."""
    net = ReactionNetwork.from_reactions(
        ["A", "B"], [("dimerise", {"A": 2}, {"B": 1}), ("split", {"B": 1}, {"A": 2})]
    )
    space = StateSpace.enumerate(net, torch.tensor([6, 0]))
    assert {tuple(s) for s in space.states.tolist()} == {(6, 0), (4, 1), (2, 2), (0, 3)}
    c = torch.tensor([[0.7, 1.3]], dtype=torch.float64)
    q = space.generator(c)[0].numpy()
    # a_dimerise = c1 A (A - 1) / 2, a_split = c2 B
    for i, (a, b) in enumerate(space.states.tolist()):
        out = {}
        if a >= 2:
            out[(a - 2, b + 1)] = 0.7 * a * (a - 1) / 2
        if b >= 1:
            out[(a + 2, b - 1)] = 1.3 * b
        for j, s in enumerate(space.states.tolist()):
            assert q[i, j] == pytest.approx(
                out.get(tuple(s), 0.0) if i != j else -sum(out.values())
            )
    on = space.states[:, 1] >= 2  # "ON": at least two dimers
    psi = lumped_psi(torch.as_tensor(q)[None], on, 0.3)[0].numpy()
    pi = stationary_distribution(torch.as_tensor(q)[None])[0].numpy()
    p = scipy.linalg.expm(q * 0.3)
    lump = on.numpy()
    for phi in (0, 1):
        w = pi * (lump == phi)
        assert psi[phi] == pytest.approx(float((w @ p[:, lump].sum(1)) / w.sum()), rel=1e-9)


def test_exact_psi_is_batched_and_run_property_consistent() -> None:
    space = population_space(4)
    assert torch.equal(is_run(space.states), torch.tensor(
        [s[1 - 1 + 2] >= 2 and s[0] == 0 for s in space.states.tolist()]))  # fmt: skip
    kp = torch.tensor([r[0] for r in RATES], dtype=torch.float64)
    km = torch.tensor([r[1] for r in RATES], dtype=torch.float64)
    batched = exact_run_probability(kp, km, DT, P)
    single = torch.cat(
        [exact_run_probability(kp[i : i + 1], km[i : i + 1], DT, P) for i in range(4)]
    )
    torch.testing.assert_close(batched, single, rtol=1e-12, atol=0)
    assert batched.shape == (4, 2) and bool(((batched >= 0) & (batched <= 1)).all())
    assert FLAGELLA_NETWORK.n_species == 3


@pytest.mark.parametrize(("kp", "km"), RATES)
def test_the_class_step_lumps_back_to_the_two_state_law(kp: float, km: float) -> None:
    """lumped_class_step on the motors' 7 classes (phi x number of CCW motors): rows are laws,
    and summing destination classes into phi, origin classes weighted by their stationary
    mass, gives lumped_psi (the two-state law) to round-off."""
    from surrogate.ctmc.lumped import lumped_class_step
    from surrogate.models.ecoli.motors import N, class_index

    space = population_space(4)
    f64 = torch.float64
    q = space.generator(
        rate_constants(torch.tensor([kp], dtype=f64), torch.tensor([km], dtype=f64), P)
    )
    internal = MotorInternalModel(P)
    states = space.states
    classes = class_index(4)[is_run(states).long(), states[:, N]]
    c = len(internal.class_names)
    step = lumped_class_step(q, classes, c, DT)[0]  # (C, C)
    assert step.shape == (7, 7) and c == 7
    torch.testing.assert_close(step.sum(-1), torch.ones(c, dtype=f64), rtol=0, atol=1e-12)
    assert bool((step >= 0).all())
    lumps = torch.tensor(internal.class_lumps)
    assert torch.equal(lumps[classes], is_run(states).long())  # each class inside its lump
    pi = stationary_distribution(q)[0]
    mass = torch.zeros(c, dtype=f64).index_add_(0, classes, pi)
    to_run = step[:, lumps == 1].sum(-1)  # (C,)
    expected = lumped_psi(q, is_run(states), DT)[0]
    for phi in (0, 1):
        w = mass * (lumps == phi)
        got = float((w * to_run).sum() / w.sum())
        assert got == pytest.approx(float(expected[phi]), abs=1e-9)


def test_the_class_step_with_one_state_per_class_is_the_matrix_exponential() -> None:
    """Classes that are the states themselves (in a shuffled order): the class law is exp(Q dt),
    rows and columns permuted."""
    from surrogate.ctmc.lumped import lumped_class_step

    space = population_space(4)
    f64 = torch.float64
    q = space.generator(
        rate_constants(torch.tensor([2.43, 0.5], dtype=f64), torch.tensor([0.695, 3.38],
                       dtype=f64), P)
    )  # fmt: skip
    k = space.n_states
    order = torch.randperm(k, generator=torch.Generator().manual_seed(0))
    step = lumped_class_step(q, order, k, DT)  # state s is class order[s]
    expected = torch.from_numpy(np.stack([scipy.linalg.expm(qi.numpy() * DT) for qi in q]))
    back = step[:, order][:, :, order]  # [s, t] = step[order[s], order[t]]
    torch.testing.assert_close(back, expected, rtol=0, atol=1e-12)
    torch.testing.assert_close(step.sum(-1), torch.ones(2, k, dtype=f64), rtol=0, atol=1e-12)


def test_the_stationary_law_of_large_generators_with_threads_set_does_not_hang() -> None:
    """With torch's threads set explicitly to 2 (a job's ``threads=2``), torch 2.13's oneMKL
    hung in a batched LU of 151 x 151 systems (the textbook's dimerisation's collect, forever,
    "Parameter 6 was incorrect on entry to DLASWP"); those solves now run on one thread. In a
    subprocess with a deadline, so a regression fails instead of hanging the suite. The law
    is checked against a birth-death chain's closed form (Poisson(20) truncated at 150)."""
    import subprocess
    import sys

    code = (
        "import math, torch\n"
        "from surrogate.ctmc.lumped import stationary_distribution\n"
        "torch.set_num_threads(2)\n"
        "k = 151\n"
        "q = torch.zeros(2, k, k, dtype=torch.float64)\n"
        "i = torch.arange(k - 1)\n"
        "q[:, i, i + 1] = 2.0\n"
        "q[:, i + 1, i] = 0.1 * (i + 1).double()\n"
        "q -= torch.diag_embed(q.sum(-1))\n"
        "pi = stationary_distribution(q)\n"
        "n = torch.arange(k).double()\n"
        "want = torch.exp(n * math.log(20.0) - torch.lgamma(n + 1))\n"
        "want /= want.sum()\n"
        "assert torch.allclose(pi, want.expand(2, -1), atol=1e-12), float((pi - want).abs().max())\n"
        "assert torch.get_num_threads() == 2\n"
        "print('ok')\n"
    )  # fmt: skip
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                            timeout=120)  # fmt: skip
    assert result.returncode == 0 and "ok" in result.stdout, result.stderr[-2000:]
