"""E. coli with a stochastic CheY phosphorylation network (``model=ecoli_phospho``): the
expensive inner model.

* :mod:`~surrogate.models.ecoli_phospho.constants`: the network's constants, their sources and
  the calibration of the autophosphorylation rate;
* :mod:`~surrogate.models.ecoli_phospho.sbml_writer`: the network as SBML (``network.xml``);
* :mod:`~surrogate.models.ecoli_phospho.model`: the plug-in (:class:`EcoliPhosphoModel`).

Every public name is re-exported here.
"""

from surrogate.models.ecoli_phospho.constants import (
    N_PER_UM,
    PhosphoConstants,
    calibrate_k_autophosphorylation,
    calibrated,
    cw_bias,
    mean_field_steady_state,
    relaxation_rates,
)
from surrogate.models.ecoli_phospho.model import EcoliPhosphoModel, PhosphoInternalModel
from surrogate.models.ecoli_phospho.sbml_writer import (
    NETWORK_AMOUNTS_PATH,
    NETWORK_PATH,
    load_network,
    main,
    network_sbml,
)

__all__ = [
    "NETWORK_AMOUNTS_PATH",
    "NETWORK_PATH",
    "N_PER_UM",
    "EcoliPhosphoModel",
    "PhosphoConstants",
    "PhosphoInternalModel",
    "calibrate_k_autophosphorylation",
    "calibrated",
    "cw_bias",
    "load_network",
    "main",
    "mean_field_steady_state",
    "network_sbml",
    "relaxation_rates",
]
