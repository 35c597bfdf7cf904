"""The E. coli chemotaxis model (paper, Section 2): motors as the internal model, a run-and-tumble
swimmer with OU methylation as the body. Selected by ``conf/model/ecoli.yaml``."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from surrogate.errors import ConfigError, KernelUnsupported
from surrogate.fields import Field
from surrogate.models.base import CellKernel, Model, check_options
from surrogate.models.ecoli.body import ChemotacticBody
from surrogate.models.ecoli.internal import MotorInternalModel
from surrogate.models.ecoli.parameters import EcoliParameters
from surrogate.models.ecoli.reference import PAPER_TABLE1
from surrogate.models.packed import PackedDecision
from surrogate.models.perturbation import PERTURBATION_DEFAULTS


class EcoliModel(Model):
    """E. coli chemotaxis after Sneddon, Pontius & Emonet (2012) and the paper.

    Args:
        perturbation: collect's perturbation (``radius`` mm, ``sampling`` radius|area).
        **constants: any field of :class:`EcoliParameters` (unknown names are refused).

    Example:
        >>> model = EcoliModel(n_motors=4, tau=15.0)
        >>> model.internal.input_names, model.internal.lump_names
        (('m', 'L'), ('tumble', 'run'))
    """

    name = "ecoli"
    internal: MotorInternalModel
    body: ChemotacticBody

    perturbation_key = "model.perturbation"

    def __init__(self, perturbation: Mapping[str, Any] | None = None, **constants: Any) -> None:
        self.params = EcoliParameters.from_config(constants)
        self.internal = MotorInternalModel(self.params)
        self.body = ChemotacticBody(self.params)
        self.perturbation_options = check_options(
            {} if perturbation is None else perturbation, PERTURBATION_DEFAULTS,
            "model.perturbation",
        )  # fmt: skip

    def validate(self, dt: float) -> None:
        """The OU is stepped by Euler-Maruyama: dt must be well below tau."""
        if dt >= self.params.tau:
            raise ConfigError(
                f"dt={dt:g} s must be smaller than model.tau={self.params.tau:g} s (the "
                f"adaptation time, stepped by Euler-Maruyama); the paper uses dt=0.05"
            )

    def cell_kernel(self, decision: PackedDecision, field: Field, dt: float) -> CellKernel:
        """The compiled per-cell E. coli step (:class:`~surrogate.models.ecoli.kernel.EcoliKernel`)
        for the full model or a two-state chain over a lookup table, in a built-in field."""
        if type(self.internal) is not MotorInternalModel:  # the kernel transcribes the motors
            raise KernelUnsupported("an internal model other than the model's motors")
        from surrogate.models.ecoli.kernel import EcoliKernel  # numba: imported on demand

        return EcoliKernel(self.params, self.internal, decision, field, dt)

    def kernel_precompiler(self) -> str | None:
        """:func:`surrogate.models.ecoli.kernel.precompile` while numba's cache lacks the
        kernel (one signature serves every decision layer and field)."""
        from surrogate.models.ecoli import kernel  # numba: imported on demand

        return None if kernel.is_compiled_on_disk() else f"{kernel.__name__}:precompile"

    def observable_label(self, name: str) -> str:
        """Figure labels."""
        return {"distance": "distance from the peak (mm)"}.get(name, name)

    def reference_table(self) -> dict[str, dict[str, Any]]:
        """The paper's Table 1 (KS distances, p-values, speed-up) per field."""
        return PAPER_TABLE1

    def describe(self) -> str:
        """One line for reports."""
        p = self.params
        return (
            f"E. coli chemotaxis: {p.n_motors} motors ({p.motor_sampler}), tau {p.tau:g} s, "
            f"tumble angles {p.tumble_mode}"
        )

    def to_config(self) -> dict[str, Any]:
        """Constants and perturbation (for manifests)."""
        return {
            "name": self.name,
            **self.params.to_dict(),
            "perturbation": dict(self.perturbation_options),
        }
