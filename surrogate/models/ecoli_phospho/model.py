"""The E. coli model with the stochastic CheY phosphorylation network read from SBML
(``model=ecoli_phospho``): the first model's cell, fields and methylation, but CheY-P is a
molecule count of an SBML network driven by the receptor activity a(m, L).

The internal model simulates the SBML network exactly, window by window: on the CPU with the
compiled per-cell Gillespie direct method (:class:`~surrogate.ctmc.CompiledSSA`, numba, one
random stream per cell), on CUDA with the batched event-round SSA. Its inputs are the body's
(m, L); the network sees them only through the activity a = 1 / (1 + exp(F(m, L))), which is
therefore the *signal* (the default input of the abstraction). There is no exact lumped psi (the
state space is large), so the abstraction's diagnostic uses the full model's binned switching
frequencies.

Unlike the first model, the internal state carries memory across windows beyond phi: CheY-P
(relaxation ~33 ms, autocorrelation ~0.22 across one dt = 50 ms) and the motors' configuration
within a lump. A two-state chain cannot carry it: that, not the learning, bounds how close the
abstraction can get (measured in docs/fidelity.md).
"""

from __future__ import annotations

import dataclasses
import hashlib
from collections.abc import Mapping, Sequence
from functools import partial
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from surrogate.errors import ConfigError, KernelUnsupported
from surrogate.fields import Field
from surrogate.models.base import (
    COLLECT_PERTURBATION,
    CellKernel,
    InternalState,
    Model,
    burn_in_seconds,
    check_options,
)
from surrogate.models.ecoli import formulas
from surrogate.models.ecoli.body import ChemotacticBody
from surrogate.models.ecoli.motors import run_probability_after, states_from_counts
from surrogate.models.ecoli.parameters import EcoliParameters
from surrogate.models.ecoli.signalling import free_energy
from surrogate.models.ecoli_phospho.constants import PhosphoConstants, calibrated
from surrogate.models.ecoli_phospho.sbml_writer import NETWORK_PATH, network_sbml
from surrogate.models.network import SSA_BACKENDS, NetworkInternalModel
from surrogate.models.packed import PackedDecision
from surrogate.models.perturbation import PERTURBATION_DEFAULTS
from surrogate.sbml import SbmlModel, read_sbml, read_sbml_string

__all__ = ["SSA_BACKENDS", "EcoliPhosphoModel", "PhosphoInternalModel"]
#: constants of the phospho network (beyond the first model's), with their config names
PHOSPHO_KEYS = ("cheA_total", "cheY_total", "cheZ", "k_y", "k_z_cheZ", "gamma_y", "n_per_um")


class PhosphoInternalModel(NetworkInternalModel):
    """The SBML phosphorylation network with the motors, driven by the MWC activity: the
    generic network model (:class:`~surrogate.models.network.NetworkInternalModel`) over the
    SBML file, with the first model's signalling as its features and the motors' expected
    labels.

    Args:
        params: the first model's constants (MWC receptor terms give the activity).
        network: the SBML model (input ``activity``; motor species ``S``, ``C``, ``N``).
        ssa: ``compiled`` (CPU, numba), ``batched`` (torch, any device) or ``auto``.
        burn_in: seconds of SSA at each cell's activity from the file's initial state, standing
            in for the network's stationary law (its CheY-P relaxes in ~33 ms, its motors in ~1 s).
    """

    lump_names = ("tumble", "run")
    network: SbmlModel
    #: sub-windows of the CheY-P path in expected_phi_next (its only approximation)
    expected_substeps = 10

    def __init__(
        self, params: EcoliParameters, network: SbmlModel, ssa: str = "auto", burn_in: float = 2.0
    ) -> None:
        self.params = params
        species = network.species
        missing = [s for s in ("S", "C", "N") if s not in species]
        if missing or network.input_names != ("activity",):
            raise ConfigError(
                f"model.network: the SBML model needs motor species S, C, N and the one input "
                f"parameter 'activity'; it has species {list(species)} (missing {missing}) and "
                f"inputs {list(network.input_names)}"
            )
        super().__init__(
            network, ("m", "L"), "N >= 2 && S == 0", lump_names=self.lump_names,
            features={"F": partial(receptor_energy, params=params),
                      "activity": partial(receptor_activity, params=params)},
            ssa=ssa, burn_in=burn_in_seconds(burn_in), signal_bounds={"activity": (0.0, 1.0)},
        )  # fmt: skip
        self._motor_columns = [species.index(m) for m in ("S", "C", "N")]
        self._motor_moves = _motor_moves(network, self._motor_columns)

    @property
    def state_space(self) -> None:
        """None: the network's state space is far too large to enumerate (so no exact psi)."""
        return None

    def expected_phi_next(self, state: InternalState, x: Tensor, dt: float) -> Tensor:
        """P(RUN after a window ``dt`` | the motors now, a CheY-P path) ``(n,)`` float64: the
        window's expected label, with the motors' randomness integrated out exactly.

        The motors do not act on CheY-P, so given the CheY-P path over the window the motors
        are a time-inhomogeneous chain whose exact transition is a product of exp(Q(CheY-P) h)
        over the path. The path is a second ("ghost") SSA run of the window from the same
        state on a copy of the cell's random stream, in ``expected_substeps`` sub-windows: a
        draw from the path's law given the state now, so its label's mean given the state is
        the outcome's, whatever the ghost's correlation with the real window; the real window
        is untouched (same random numbers). Per sub-window the motor rates are the mean of the
        network's own per-motor propensities at its two ends (CheY-P relaxes in ~33 ms; dt is
        50 ms). :func:`~surrogate.models.ecoli.motors.run_probability_after` then gives P(RUN).
        """
        counts, streams = state
        activity = self.features(x, ("activity",)).to(torch.float64).to(counts.device)
        h = dt / self.expected_substeps
        ghost: InternalState = (counts.clone(), streams.clone())
        rates = self._motor_generator(ghost[0], activity)
        transition = torch.eye(3, dtype=torch.float64, device=counts.device).expand(
            counts.shape[0], 3, 3
        )
        for _ in range(self.expected_substeps):
            ghost = self.advance(ghost, x, h)
            after = self._motor_generator(ghost[0], activity)
            transition = transition @ torch.linalg.matrix_exp(0.5 * (rates + after) * h)
            rates = after
        motors = states_from_counts(counts[:, self._motor_columns], self.params.n_motors)
        return run_probability_after(motors, transition)

    def _motor_generator(self, counts: Tensor, activity: Tensor) -> Tensor:
        """One motor's generator ``n x 3 x 3`` (S, C, N) at each cell's counts: the network's
        own motor propensities with one motor in each state (first order: the rate per motor)."""
        probe = counts.clone()
        probe[:, self._motor_columns] = 1
        rates = self.network.propensities(probe, activity)
        generator = rates.new_zeros(counts.shape[0], 3, 3)
        for reaction, source, target in self._motor_moves:
            generator[:, source, target] += rates[:, reaction]
        return generator - torch.diag_embed(generator.sum(-1))


def receptor_energy(x: Tensor, params: EcoliParameters) -> Tensor:
    """F(m, L) at inputs ``x = (m, L)`` (``n x 2``): the MWC free energy."""
    return free_energy(x[:, 0], x[:, 1], params)


def receptor_activity(x: Tensor, params: EcoliParameters) -> Tensor:
    """The receptor activity 1 / (1 + exp(F(m, L))): the network's input."""
    return formulas.activity(receptor_energy(x, params))


def _motor_moves(network: SbmlModel, columns: Sequence[int]) -> list[tuple[int, int, int]]:
    """(reaction, from, to) of the reactions that move one motor between S, C, N (indices
    into ``columns``): one motor species consumed, another produced, first order in it."""
    reactants, products = network.network.reactants, network.network.products
    moves = []
    for r in range(reactants.shape[0]):
        used = reactants[r, columns].tolist()
        made = products[r, columns].tolist()
        if sum(used) == 0 and sum(made) == 0:
            continue
        if sorted(used) != [0, 0, 1] or sorted(made) != [0, 0, 1] or used == made:
            raise ConfigError(
                f"model.network: reaction {network.reaction_names[r]!r} does not move one "
                f"motor between S, C and N (first order); the expected labels need that"
            )
        moves.append((r, used.index(1), made.index(1)))
    return moves


class EcoliPhosphoModel(Model):
    """E. coli with the CheY phosphorylation network (see the module docstring).

    Args:
        network: an SBML file with the input ``activity`` and motor species S, C, N; None: the
            shipped ``network.xml`` (generated anew from the constants when they differ from
            the defaults).
        ssa: ``auto`` (compiled on the CPU, batched on CUDA), ``compiled`` or ``batched``.
        burn_in: seconds of network dynamics at each cell's activity before the run's own
            equilibration (see :class:`PhosphoInternalModel`).
        perturbation: collect's perturbation (as the first model's).
        **constants: the first model's constants (:class:`EcoliParameters`) and the network's
            (``cheA_total``, ``cheY_total``, ``cheZ``, ``k_y``, ``k_z_cheZ``, ``gamma_y``,
            ``n_per_um``).
    """

    name = "ecoli_phospho"
    internal: PhosphoInternalModel
    body: ChemotacticBody

    def __init__(
        self,
        network: str | None = None,
        ssa: str = "auto",
        burn_in: float = 2.0,
        perturbation: Mapping[str, Any] | None = None,
        **constants: Any,
    ) -> None:
        phospho = {k: constants.pop(k) for k in list(constants) if k in PHOSPHO_KEYS}
        self.params = EcoliParameters.from_config(constants)
        p = self.params
        self.constants = calibrated(dataclasses.replace(
            PhosphoConstants(), **phospho, adapted_activity=p.yp_adapted / p.alpha,
            adapted_cheyp=p.yp_adapted, n_motors=int(p.n_motors), mu=p.mu, omega=p.omega,
            g0=p.g0, g1=p.g1, k_d=p.k_d,
        ))  # fmt: skip
        sbml = _network(network, self.constants)
        self._network_given = network is not None
        self.internal = PhosphoInternalModel(p, sbml, ssa, burn_in)
        self.body = ChemotacticBody(p)
        self.perturbation_options = check_options(
            {} if perturbation is None else perturbation, PERTURBATION_DEFAULTS,
            "model.perturbation",
        )  # fmt: skip

    def validate(self, dt: float) -> None:
        """The OU is stepped by Euler-Maruyama: dt must be well below tau."""
        if dt >= self.params.tau:
            raise ConfigError(f"dt={dt:g} s must be smaller than model.tau={self.params.tau:g} s")

    def collect_defaults(self, dt: float) -> dict[str, float]:
        """10,000 transitions per origin from 500 cells, every 5th window (experiment=phospho's
        recipe, the figures of docs/fidelity.md): ~10,000 SSA events per cell-step make the first
        model's 100,000 from 2,000 cells hours of work."""
        return {"n_per_state": 10_000, "n_cells": 500, "record_every": 5, **COLLECT_PERTURBATION}

    def sources(self) -> dict[str, str]:
        """The digest of a network file given by ``model.network`` (the shipped one is
        defined by the package)."""
        source = self.internal.network.source
        if self._network_given and source is not None:
            return {"network": hashlib.sha256(Path(source).read_bytes()).hexdigest()}
        return {}

    def cell_kernel(self, decision: PackedDecision, field: Field, dt: float) -> CellKernel:
        """The first model's compiled per-cell step
        (:class:`~surrogate.models.ecoli.kernel.EcoliKernel`; the same body and signalling) for
        a two-state chain over a lookup table of m, L, F or the activity, in a built-in field.
        The full model (the SSA network) has no kernel: the kernel refuses it, and the
        simulator keeps the torch step (whose window is the compiled SSA on the CPU)."""
        if type(self.internal) is not PhosphoInternalModel:  # its features are the kernel's
            raise KernelUnsupported(f"internal model {type(self.internal).__name__}")
        from surrogate.models.ecoli.kernel import EcoliKernel  # numba: imported on demand

        return EcoliKernel(self.params, self.internal, decision, field, dt)

    def kernel_precompiler(self) -> str | None:
        """:func:`surrogate.models.ecoli.kernel.precompile` while numba's cache lacks the
        kernel (the first model's: one signature serves both models)."""
        from surrogate.models.ecoli import kernel  # numba: imported on demand

        return None if kernel.is_compiled_on_disk() else f"{kernel.__name__}:precompile"

    def observable_label(self, name: str) -> str:
        """Figure labels."""
        return {"distance": "distance from the peak (mm)"}.get(name, name)

    def describe(self) -> str:
        """One line for reports."""
        c = self.constants
        return (
            f"E. coli with stochastic CheY phosphorylation (SBML): {c.n_motors} motors, CheA "
            f"{c.cheA_total:g} uM, CheY {c.cheY_total:g} uM, kA {c.k_a:.3g}/s (calibrated), "
            f"SSA {self.internal.ssa}"
        )


def _network(path: str | None, constants: PhosphoConstants) -> SbmlModel:
    if path is not None:
        p = Path(path).expanduser()
        if not p.is_file():
            raise ConfigError(f"model.network={path}: no such SBML file")
        return read_sbml(p, inputs=["activity"])
    shipped = calibrated(PhosphoConstants(n_motors=constants.n_motors))
    if constants == shipped:
        return read_sbml(NETWORK_PATH, inputs=["activity"])
    return read_sbml_string(network_sbml(constants), inputs=["activity"])
