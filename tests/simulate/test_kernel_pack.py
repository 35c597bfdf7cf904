"""The engine's packing of decision layers for a model's compiled kernel (plain arrays)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from surrogate.gp import PsiLookupTable, StackedPsiLookup
from surrogate.models.ecoli import EcoliModel
from surrogate.models.packed import CHAIN, EXACT, FULL, UNSUPPORTED
from surrogate.simulate import AbstractDecision, ExactDecision, FullDecision
from surrogate.simulate.batch import DecisionBatch
from surrogate.simulate.kernel_pack import pack_decision
from surrogate.simulate.memory import AGE, MemoryDecision, tabulate_with_clock

DT = 0.05


def _psi(phi: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
    return torch.sigmoid(z.sum(1) - phi.float())


def test_a_chain_packs_its_table_box_and_features() -> None:
    """The flat table, each axis's box (low end, nodes per unit), shape, strides and layer
    are the lookup table's own, read through its public accessors."""
    model = EcoliModel()
    table = PsiLookupTable.from_function(_psi, [(1.0, 3.5), (0.0, 0.12)], ("m", "L"), (8, 6))
    block = pack_decision(AbstractDecision(table, model.internal, model.featurizer(["m", "L"])),
                          DT).blocks[0]  # fmt: skip
    t = block.tables
    assert (block.kind, block.features, block.features_of) == (CHAIN, ("m", "L"), model.internal)
    assert block.why is None and block.decision_row == 0 and block.count is None
    assert np.array_equal(t.table, table.table.reshape(-1).numpy())
    assert t.origin.tolist() == [[1.0, 0.0]] and t.layer == 48 == table.layer_size
    assert np.allclose(t.scale, [[7 / 2.5, 5 / 0.12]])
    assert t.shape.tolist() == [8, 6] and t.strides.tolist() == [6, 1] == list(table.strides)
    assert t.table_of_cell(5).tolist() == [0] * 5  # one table serves any population
    # the accessors hand out copies: packing never writes into a table
    table.affine[0, 0] = 99.0
    assert table.affine[0, 0] == 1.0


def test_kinds_rows_and_what_cannot_be_packed() -> None:
    model = EcoliModel()
    internal = model.internal
    table = PsiLookupTable.from_function(_psi, [(-3.0, 3.0)], ("dG",), (16,))

    class Tempered(AbstractDecision):
        pass

    full = pack_decision(FullDecision(internal), DT)
    assert full.blocks[0].kind == FULL and full.blocks[0].motor_row == 0
    assert full.randoms == FullDecision(internal).randoms and full.total is None
    assert pack_decision(ExactDecision(internal, DT, table), DT).blocks[0].kind == EXACT
    odd = pack_decision(Tempered(table, internal), DT).blocks[0]
    assert odd.kind == UNSUPPORTED and odd.why == "decision layer Tempered"
    direct = pack_decision(ExactDecision(internal, DT), DT).blocks[0]  # the exact psi itself
    assert direct.tables is None and "run probability ExactPsi" in direct.why


def test_a_batch_packs_one_block_per_member_with_stacked_tables() -> None:
    model = EcoliModel()
    internal, dg = model.internal, model.featurizer(["dG"])
    a = PsiLookupTable.from_function(_psi, [(-3.0, 3.0)], ("dG",), (16,))
    b = PsiLookupTable.from_function(_psi, [(-2.0, 4.0)], ("dG",), (16,))
    stacked = AbstractDecision(StackedPsiLookup([a, b], [3, 4]), internal, dg)
    packed = pack_decision(DecisionBatch([FullDecision(internal), stacked], [5, 7]), DT)
    full, chain = packed.blocks
    assert packed.total == 12 and (full.start, full.count, chain.start, chain.count) == (0, 5, 5, 7)
    assert chain.tables.table_of_cell(7).tolist() == [0, 0, 0, 1, 1, 1, 1]
    assert chain.tables.origin[:, 0].tolist() == [-3.0, -2.0]
    # the decision's rows: each member's right-aligned (the full model's float64 uniforms)
    assert full.motor_row == packed.randoms.uniform64 - FullDecision(internal).randoms.uniform64
    assert chain.decision_row == packed.randoms.uniform - 1
    with pytest.raises(ValueError, match="cover 7 cells, not 8"):
        chain.tables.table_of_cell(8)
    with pytest.raises(ValueError, match="cover 7 cells, the block 6"):
        pack_decision(DecisionBatch([FullDecision(internal), stacked], [5, 6]), DT)


def test_a_clock_in_seconds_or_on_its_nodes_and_the_state_copied_once() -> None:
    """The clock is psi's last input in seconds (unit dt, cap max_age), or, for a table with
    a node per step, in steps on a unit axis; its state is the layer's own copy, made once."""
    model = EcoliModel()
    internal, dg = model.internal, model.featurizer(["dG"])
    seconds = PsiLookupTable.from_function(_psi, [(-3.0, 3.0), (0.0, 2.0)], ("dG", AGE), (16, 9))
    block = pack_decision(MemoryDecision(seconds, internal, dg, max_age=2.0), DT).blocks[0]
    assert (block.clock.cap, block.clock.unit) == (2.0, DT)
    nodes = tabulate_with_clock(_psi, [(-3.0, 3.0)], ("dG", AGE), DT, 1.0, (16,))
    layer = MemoryDecision(nodes, internal, dg, max_age=1.0, dt=DT)
    block = pack_decision(layer, DT).blocks[0]
    assert (block.clock.cap, block.clock.unit) == (20.0, 1.0)
    assert block.tables.origin[0].tolist() == [-3.0, 0.0]
    assert block.tables.scale[0, 1] == 1.0 and nodes.affine[1, 1] == pytest.approx(20.0)
    layer.initialize(torch.zeros(4, 2))
    held = layer.fused_state()[0]
    own = block.state.writable()
    assert own is not held and layer.fused_state()[0] is own and block.state.writable() is own
    assert block.state.current() is own


def test_a_class_chain_packs_its_rows_axes_lumps_and_classes() -> None:
    """A K-lumps chain: the cumulative rows as they are, each axis's float32 origin and scale
    (a constant axis: one node), the lumps, its d + 1 rows right-aligned beside a chain's one,
    and its classes as the layer's state; a feature map the engine does not know: why."""
    from surrogate.models.packed import CLASSES
    from surrogate.simulate.classes import ClassDecision, ClassTable

    model = EcoliModel()
    internal = model.internal
    c = len(internal.class_names)
    p = torch.rand(c, 5, 1, c, generator=torch.Generator().manual_seed(0)) + 0.1
    table = ClassTable(p, [(-1.0, 2.0), (0.0, 1.0)], ("dG", "m"), internal.class_names,
                       internal.class_lumps, DT)  # fmt: skip
    layer = ClassDecision(table, internal, model.featurizer(["dG", "m"]))
    chain = AbstractDecision(PsiLookupTable.from_function(_psi, [(0.0, 1.0)], ("dG",), (8,)),
                             internal, model.featurizer(["dG"]))  # fmt: skip
    packed = pack_decision(DecisionBatch([chain, layer], [4, 6]), DT)
    assert packed.randoms.uniform == 3
    block = packed.blocks[1]
    assert block.kind == CLASSES and block.why is None and block.start == 4
    assert block.decision_row == 0 and packed.blocks[0].decision_row == 2
    law = block.classes
    assert np.array_equal(law.cdf, table.cdf.reshape(-1).numpy())
    assert law.origin.tolist() == [-1.0, 0.0] and law.nodes.tolist() == [5, 1]
    assert law.scale[0] == np.float32(4 / 3.0) and law.strides.tolist() == [1, 1]
    assert law.origin_stride == 5 and law.lumps.tolist() == list(internal.class_lumps)
    assert block.features == ("dG", "m")
    layer.initialize(torch.tensor([[2.0, 0.0]]).expand(6, 2))
    assert block.state.current() is layer.cls
    odd = pack_decision(ClassDecision(table, internal, lambda x: x), DT).blocks[0]
    assert odd.kind == CLASSES and "feature map" in odd.why
