"""The run-and-tumble chemotaxis body (the E. coli body) with its adaptation, for any network.

The body of ``model=ecoli`` (:class:`~surrogate.models.ecoli.body.ChemotacticBody`): a swimmer
in a 2-D ligand field that runs at ``speed`` while phi = 1 and tumbles by Gamma angles while
phi = 0, with an Ornstein-Uhlenbeck methylation ``m`` (its adaptation, time scale ``tau``). It
hands its internal model ``x = (m, L)`` and derives from them the receptor cluster's free energy
``F(m, L)`` and activity ``activity = 1 / (1 + exp(F))`` (MWC), the input of a CheY
phosphorylation network. Parameters: every constant of
:class:`~surrogate.models.ecoli.parameters.EcoliParameters` (``conf/model/base/ecoli_cell.yaml``
lists them with their sources; the motor constants are unused here), plus ``perturbation`` (collect's
jumps into a disc around the peak: ``radius`` mm, ``sampling`` radius|area).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from torch import Tensor

from surrogate.errors import ConfigError, KernelUnsupported
from surrogate.fields import Field
from surrogate.models.base import CellKernel, check_options
from surrogate.models.ecoli.body import ChemotacticBody
from surrogate.models.ecoli.formulas import activity
from surrogate.models.ecoli.parameters import EcoliParameters
from surrogate.models.ecoli.signalling import free_energy
from surrogate.models.packed import PackedDecision
from surrogate.models.perturbation import PERTURBATION_DEFAULTS, DiscJump, disc_jump, disc_options

#: the derived variables the compiled kernel transcribes (models/ecoli/kernel.py FEATURE_CODES)
KERNEL_VARIABLES = ("m", "L", "F", "activity")
#: features the kernel computes with the E. coli formulas (FEATURE_CODES' other names): an
#: internal model's input mapped under one of these names would be read as the kernel's
KERNEL_COMPUTED = ("cheyp", "dG")


class RunAndTumbleBody(ChemotacticBody):
    """The E. coli body as a library body (see the module docstring).

    Args:
        options: constants of :class:`EcoliParameters` and ``perturbation``.
        where: the setting's name in messages (e.g. ``"model.body"``).

    Example:
        >>> body = RunAndTumbleBody({"tau": 20.0})
        >>> x = torch.tensor([[2.0, 0.0]])
        >>> float(body.derived["activity"](x))  # the MWC activity at m = 2, L = 0
        0.45...
    """

    variable_names = ("m", "L")

    def __init__(self, options: Mapping[str, Any] | None = None, where: str = "model.body") -> None:
        options = dict(options or {})
        perturbation = options.pop("perturbation", None)
        try:
            params = EcoliParameters.from_config(options)
        except ConfigError as error:  # its messages name model.<constant>
            text = str(error).replace("model.", f"{where}.")
            raise ConfigError(
                text.replace("unknown model setting", f"unknown {where} setting")
            ) from None
        super().__init__(params)
        self.where = where
        self.perturbation_options = check_options(
            {} if perturbation is None else perturbation, PERTURBATION_DEFAULTS,
            f"{where}.perturbation",
        )  # fmt: skip
        disc_options(self.perturbation_options, f"{where}.perturbation")
        self.derived = {"F": self._energy, "activity": self._activity}

    def _energy(self, x: Tensor) -> Tensor:
        return free_energy(x[:, 0], x[:, 1], self.params)

    def _activity(self, x: Tensor) -> Tensor:
        return activity(self._energy(x))

    def validate(self, dt: float) -> None:
        """The OU is stepped by Euler-Maruyama: dt must be well below tau."""
        if dt >= self.params.tau:
            raise ConfigError(
                f"dt={dt:g} s must be smaller than {self.where}.tau={self.params.tau:g} s (the "
                "adaptation time, stepped by Euler-Maruyama)"
            )

    def perturbation(self, field: Field, options: Mapping[str, Any]) -> DiscJump:
        """Jumps into a disc around the field's peak."""
        return disc_jump(field, options, f"{self.where}.perturbation")

    def observable_label(self, name: str) -> str:
        """Figure label of an observable."""
        return {"distance": "distance from the peak (mm)"}.get(name, name)

    def cell_kernel(
        self, internal: Any, decision: PackedDecision, field: Field, dt: float
    ) -> CellKernel:
        """The E. coli compiled per-cell step for a two-state chain over a lookup table of
        :data:`KERNEL_VARIABLES` (the internal model's columns of those names must be this
        body's, which the model that asks vouches for)."""
        # the SBML agent's inputs mapped by formula (not derived here) must not take the names
        # of features the kernel computes with the body's own formulas
        mapped = set(internal.feature_names) - set(self.derived)
        if mapped & set(KERNEL_COMPUTED):
            raise KernelUnsupported(f"inputs {sorted(mapped)} named like the kernel's features")
        if tuple(internal.input_names) != self.variable_names:
            raise KernelUnsupported("an internal model with other inputs than the body's (m, L)")
        from surrogate.models.ecoli.kernel import EcoliKernel  # numba: imported on demand

        return EcoliKernel(self.params, internal, decision, field, dt)

    def kernel_precompiler(self) -> str | None:
        """The E. coli kernel's precompile while numba's cache lacks it."""
        from surrogate.models.ecoli import kernel  # numba: imported on demand

        return None if kernel.is_compiled_on_disk() else f"{kernel.__name__}:precompile"
