"""The benchmarks' decision layers: the lookup bench's chains come from the kind registry."""

from __future__ import annotations

from surrogate.benchmarks.layers import history_chains
from surrogate.kinds import SWITCH_CLOCK, TWO_STATE, chain_kind


def test_history_chains_are_the_registered_kinds_it_can_tabulate() -> None:
    """Each ``histories`` word is the config string of a registered kind, in the order the
    settings list them; the hidden-phase chain, which needs a fit, is left out."""
    chains = history_chains()
    shipped = [w for w in chains if w in ("none", "age", "classes")]
    assert shipped == ["none", "age", "classes"]
    assert chains["none"] is TWO_STATE and chains["age"] is SWITCH_CLOCK
    assert chains["classes"] is chain_kind("classes")
    assert "phases" not in chains and "phi" not in chains
