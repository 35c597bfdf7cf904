"""Population continuous-time Markov chains given as mass-action reaction networks.

A network over species ``S_1..S_S`` is a list of reactions ``sum_s r_rs S_s -> sum_s p_rs S_s``.
In state ``x`` (integer counts) reaction ``r`` fires at the mass-action propensity

    a_r(x) = c_r * prod_s binom(x_s, r_rs),

so a first-order reaction ``A -> B`` fires at ``c x_A`` and a dimerisation ``2A -> B`` at
``c x_A (x_A - 1) / 2``. Rate constants ``c`` are supplied per cell by the caller: in the
multi-scale model they are functions of the cell's inputs and are held fixed over one window.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass

import torch
from torch import Tensor

__all__ = ["ReactionNetwork", "make_propensity_fn"]

PropensityFn = Callable[[Tensor, Tensor], Tensor]


def _is_integer_dtype(dtype: torch.dtype) -> bool:
    return not (dtype.is_floating_point or dtype.is_complex or dtype == torch.bool)


def _as_coefficients(value: Tensor, name: str) -> Tensor:
    tensor = torch.as_tensor(value)
    if not _is_integer_dtype(tensor.dtype):
        raise ValueError(f"{name} must hold integer coefficients, got dtype {tensor.dtype}")
    if tensor.dim() != 2:
        raise ValueError(f"{name} must have shape (R, S), got {tuple(tensor.shape)}")
    if (tensor < 0).any():
        raise ValueError(f"{name} must be non-negative, got a minimum of {int(tensor.min())}")
    # Clone so later in-place edits of the caller's tensor cannot change a frozen network.
    return tensor.detach().to(device="cpu", dtype=torch.int64).clone()


def make_propensity_fn(reactants: Tensor, device: torch.device | str) -> PropensityFn:
    """Return ``f(state, rate_constants) -> (n, R) float64`` mass-action propensities.

    ``reactants`` is the ``(R, S)`` coefficient tensor (inspected on the CPU, so building the
    function costs no device sync). The returned function performs no validation; it is the hot
    path of the SSA. Its ``state`` is ``(n, S)`` integer and ``rate_constants`` ``(n, R)``
    float, both on ``device``. The result is float64 whatever the rate dtype, because reaction
    selection in the SSA must resolve propensity ratios far below float32 resolution.
    """
    reactants = reactants.cpu()
    orders = reactants.sum(dim=1)
    if bool((orders <= 1).all()):
        # Every reaction has at most one reactant molecule: a_r = c_r x_{s(r)} (or c_r if
        # zero-order), a single gather instead of the general product over species.
        source = reactants.argmax(dim=1).to(device)
        zero_order = (orders == 0).to(device)

        def first_order(state: Tensor, rates: Tensor) -> Tensor:
            x = state.to(torch.float64).index_select(1, source)
            return rates.to(torch.float64) * torch.where(zero_order, 1.0, x)

        return first_order

    max_coeff = int(reactants.max())
    # binom(x, r) = prod_{k<r} (x - k) / (k + 1); masks[k] selects the (reaction, species)
    # pairs whose coefficient exceeds k.
    masks = [(reactants > k).to(device) for k in range(max_coeff)]

    def mass_action(state: Tensor, rates: Tensor) -> Tensor:
        x = state.to(torch.float64).unsqueeze(1)  # (n, 1, S)
        comb = torch.ones(rates.shape, dtype=torch.float64, device=rates.device)
        for k, mask in enumerate(masks):
            comb = comb * torch.where(mask, (x - k) / (k + 1), 1.0).prod(dim=-1)
        # For x_s < r_rs the product passes through the factor (x_s - x_s) = 0; clamping
        # turns a possible -0.0 into +0.0.
        return rates.to(torch.float64) * comb.clamp_min(0.0)

    return mass_action


@dataclass(frozen=True, eq=False)
class ReactionNetwork:
    """A mass-action reaction network over a fixed list of species.

    Attributes:
        species: Species names, in column order of every state tensor.
        reactants: ``(R, S)`` int64, molecules of each species consumed by each reaction.
        products: ``(R, S)`` int64, molecules of each species produced by each reaction.
        reaction_names: Reaction names, in column order of every rate-constant tensor.

    The coefficient tensors are stored on the CPU; methods move them to the device of their
    inputs. Equality is identity (tensors have no single truth value).
    """

    species: tuple[str, ...]
    reactants: Tensor
    products: Tensor
    reaction_names: tuple[str, ...]

    def __post_init__(self) -> None:
        species = tuple(self.species)
        names = tuple(self.reaction_names)
        if not species:
            raise ValueError("a reaction network needs at least one species")
        if len(set(species)) != len(species):
            raise ValueError(f"species names must be unique, got {species}")
        if not names:
            raise ValueError("a reaction network needs at least one reaction")
        if len(set(names)) != len(names):
            raise ValueError(f"reaction names must be unique, got {names}")
        reactants = _as_coefficients(self.reactants, "reactants")
        products = _as_coefficients(self.products, "products")
        expected = (len(names), len(species))
        for name, tensor in (("reactants", reactants), ("products", products)):
            if tuple(tensor.shape) != expected:
                raise ValueError(
                    f"{name} must have shape (R, S) = {expected} for {len(names)} reactions "
                    f"and {len(species)} species, got {tuple(tensor.shape)}"
                )
        object.__setattr__(self, "species", species)
        object.__setattr__(self, "reaction_names", names)
        object.__setattr__(self, "reactants", reactants)
        object.__setattr__(self, "products", products)

    @classmethod
    def from_reactions(
        cls,
        species: Sequence[str],
        reactions: Sequence[tuple[str, Mapping[str, int], Mapping[str, int]]],
    ) -> ReactionNetwork:
        """Build a network from readable ``(name, {species: coeff}, {species: coeff})`` triples.

        Example: ``("dimerise", {"A": 2}, {"B": 1})`` is ``2A -> B``; ``("decay", {"A": 1}, {})``
        is ``A -> 0``. Species missing from a mapping have coefficient 0.
        """
        species = tuple(species)
        column = {name: s for s, name in enumerate(species)}
        reactants = torch.zeros((len(reactions), len(species)), dtype=torch.int64)
        products = torch.zeros_like(reactants)
        names = []
        for r, reaction in enumerate(reactions):
            if len(reaction) != 3:
                raise ValueError(
                    f"reaction {r} must be (name, reactants, products), got {reaction!r}"
                )
            name, consumed, produced = reaction
            names.append(name)
            for side, target in ((consumed, reactants), (produced, products)):
                for sp, coeff in side.items():
                    if sp not in column:
                        raise ValueError(
                            f"reaction {name!r} uses unknown species {sp!r}; known: {species}"
                        )
                    if isinstance(coeff, bool) or not isinstance(coeff, int) or coeff < 0:
                        raise ValueError(
                            f"reaction {name!r}: coefficient of {sp!r} must be a non-negative "
                            f"int, got {coeff!r}"
                        )
                    target[r, column[sp]] = coeff
        return cls(
            species=species, reactants=reactants, products=products, reaction_names=tuple(names)
        )

    @property
    def n_species(self) -> int:
        """Number of species ``S``."""
        return len(self.species)

    @property
    def n_reactions(self) -> int:
        """Number of reactions ``R``."""
        return len(self.reaction_names)

    @property
    def stoichiometry(self) -> Tensor:
        """``(R, S)`` int64 net change of the state when each reaction fires."""
        return self.products - self.reactants

    def check_inputs(self, state: Tensor, rate_constants: Tensor) -> tuple[Tensor, Tensor]:
        """Validate a ``(n, S)`` state and ``(n, R)`` (or ``(R,)``) rate constants.

        Returns the state as int64 and the rate constants expanded to ``(n, R)``. Raises
        ``ValueError`` on wrong shape, dtype, device, negative counts or negative / non-finite
        rate constants.
        """
        if not isinstance(state, Tensor) or not isinstance(rate_constants, Tensor):
            raise ValueError("state and rate_constants must be torch tensors")
        if state.dim() != 2 or state.shape[1] != self.n_species:
            raise ValueError(
                f"state must have shape (n, S) with S = {self.n_species} species "
                f"{self.species}, got {tuple(state.shape)}"
            )
        if not _is_integer_dtype(state.dtype):
            raise ValueError(f"state must hold integer counts, got dtype {state.dtype}")
        n = state.shape[0]
        if rate_constants.dim() == 1:
            rate_constants = rate_constants.unsqueeze(0).expand(n, -1)
        if rate_constants.dim() != 2 or tuple(rate_constants.shape) != (n, self.n_reactions):
            raise ValueError(
                f"rate_constants must have shape (n, R) = ({n}, {self.n_reactions}) or (R,), "
                f"got {tuple(rate_constants.shape)}"
            )
        if not rate_constants.dtype.is_floating_point:
            raise ValueError(
                f"rate_constants must be floating point, got dtype {rate_constants.dtype}"
            )
        if rate_constants.device != state.device:
            raise ValueError(
                f"state is on {state.device} but rate_constants on {rate_constants.device}"
            )
        # One host sync for all checks together: these run once per call, not per event.
        bad = torch.stack(
            [
                (state < 0).any(),
                ~torch.isfinite(rate_constants).all(),
                (rate_constants < 0).any(),
            ]
        ).tolist()
        if bad[0]:
            raise ValueError("state must hold non-negative counts")
        if bad[1]:
            raise ValueError("rate_constants must be finite")
        if bad[2]:
            raise ValueError("rate_constants must be non-negative")
        return state.to(torch.int64), rate_constants

    def propensities(self, state: Tensor, rate_constants: Tensor) -> Tensor:
        """Mass-action propensities ``a_r(x) = c_r prod_s binom(x_s, r_rs)``.

        Args:
            state: ``(n, S)`` integer counts.
            rate_constants: ``(n, R)`` (or ``(R,)``, shared by all cells) float rate constants.

        Returns:
            ``(n, R)`` propensities in the dtype of ``rate_constants`` (computed in float64).
        """
        state, rate_constants = self.check_inputs(state, rate_constants)
        fn = make_propensity_fn(self.reactants, state.device)
        return fn(state, rate_constants).to(rate_constants.dtype)
