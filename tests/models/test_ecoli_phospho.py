"""The shipped E. coli CheY phosphorylation network: file, calibration, propensities."""

from __future__ import annotations

import math

import pytest
import torch

from surrogate.models.ecoli_phospho import (
    NETWORK_PATH,
    calibrated,
    cw_bias,
    load_network,
    mean_field_steady_state,
    network_sbml,
)


def test_shipped_file_matches_the_constants():
    assert NETWORK_PATH.read_text() == network_sbml(), (
        "network.xml is stale: python -c 'from surrogate.models.ecoli_phospho import main; main()'"
    )


def test_calibration_hits_the_adapted_cheyp():
    c = calibrated()
    ap, yp = mean_field_steady_state(c, c.adapted_activity)
    assert yp == pytest.approx(2.7, rel=1e-12)
    # the three fluxes of the mean-field steady state agree (uM/s)
    flux = (c.k_z_cheZ + c.gamma_y) * yp
    assert c.k_a * c.adapted_activity * (c.cheA_total - ap) == pytest.approx(flux, rel=1e-12)
    assert c.k_y * ap * (c.cheY_total - yp) == pytest.approx(flux, rel=1e-12)
    assert cw_bias(2.7, c) == pytest.approx(1 / (1 + math.exp(2 * (10 - 20 * 2.7 / 5.76))))


def test_network_reads_with_activity_input_and_balanced_fluxes():
    model = load_network()
    assert model.input_names == ("activity",)
    assert model.fixed_species == ("CheZ",)
    c = calibrated()
    a = model.propensities(model.initial_state.unsqueeze(0), torch.tensor([c.adapted_activity]))
    a = dict(zip(model.reaction_names, a[0].tolist(), strict=True))
    flux = (c.k_z_cheZ + c.gamma_y) * 2.7 * c.n_per_um  # events/s at the steady state
    for name in ("autophosphorylation", "phosphotransfer", "dephosphorylation"):
        # initial counts are the steady state rounded to whole molecules: < 0.6 % off
        assert a[name] == pytest.approx(flux, rel=6e-3)
    kp = c.omega * math.exp(10 - 20 * 2.7 / 5.76)
    assert a["C_to_N"] == pytest.approx(kp * 1, rel=1e-3)  # C = 1, Yp = 2268 / 840 = 2.7


def test_amounts_variant_has_the_same_propensities():
    from surrogate.models.ecoli_phospho import NETWORK_AMOUNTS_PATH

    assert NETWORK_AMOUNTS_PATH.read_text() == network_sbml(amounts=True)
    conc, amounts = load_network(), load_network(NETWORK_AMOUNTS_PATH)
    assert conc.species == amounts.species and conc.reaction_names == amounts.reaction_names
    assert torch.equal(conc.initial_state, amounts.initial_state)
    gen = torch.Generator().manual_seed(0)
    state = conc.initial_states(50) + torch.randint(-90, 90, (50, 8), generator=gen).clamp_min(0)
    state[:, :3] = torch.tensor([1, 1, 2])
    activity = torch.rand((50, 1), generator=gen, dtype=torch.float64)
    torch.testing.assert_close(
        conc.propensities(state, activity),
        amounts.propensities(state, activity),
        rtol=1e-12,
        atol=0,
    )
