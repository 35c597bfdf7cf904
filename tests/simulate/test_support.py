"""The share of cell-steps outside an abstraction's trained range: counted exactly, per run of a
batch, and warned about above its threshold (never at or below it)."""

from __future__ import annotations

import logging
import math

import numpy as np
import pytest
import torch

from surrogate.fields import GaussianField
from surrogate.gp import PsiLookupTable
from surrogate.models.ecoli import EcoliModel
from surrogate.simulate import AbstractDecision, FullDecision
from surrogate.simulate.batch import BatchSimulator, Replicate
from surrogate.simulate.support import (
    SupportMonitor,
    TrainedRange,
    describe_outside,
    merge_reports,
    warn_outside,
)


def test_counts_are_exact_per_input_and_side() -> None:
    trained = TrainedRange(("a", "b"), (0.0, -1.0), (1.0, 1.0))
    monitor = SupportMonitor([(slice(0, None), None, trained)])
    x = torch.tensor(
        [[0.5, 0.0], [-0.1, 0.0], [2.0, 3.0], [0.5, -2.0], [1.0, 1.0]], dtype=torch.float64
    )
    monitor.observe(x)
    monitor.observe(x[:2])
    (report,) = monitor.report()
    assert report["sampled_cell_steps"] == 7
    assert report["share_outside"] == pytest.approx(4 / 7)  # rows 2, 3, 4 of x, row 2 again
    a, b = report["inputs"]["a"], report["inputs"]["b"]
    assert (a["share_below"], a["share_above"]) == (pytest.approx(2 / 7), pytest.approx(1 / 7))
    assert (b["share_below"], b["share_above"]) == (pytest.approx(1 / 7), pytest.approx(1 / 7))
    assert a["seen"] == [-0.1, 2.0] and b["trained"] == [-1.0, 1.0]  # the edges are inside
    assert "a seen [-0.1, 2] vs trained [0, 1]" in describe_outside(report)


def test_shards_reports_merge_into_the_report_of_all_their_rows() -> None:
    """Merging the reports of a run's parts (its shards) gives what one monitor over all their
    rows reports: shares weighted by sampled cell-steps, ranges joined; unobserved parts skip."""
    trained = TrainedRange(("a", "b"), (0.0, -1.0), (1.0, 1.0))
    gen = torch.Generator().manual_seed(3)
    parts = [torch.randn(n, 2, generator=gen, dtype=torch.float64) * 1.5 for n in (7, 30, 2)]
    whole = SupportMonitor([(slice(0, None), None, trained)])
    reports = []
    for x in parts:
        whole.observe(x)
        one = SupportMonitor([(slice(0, None), None, trained)])
        one.observe(x)
        reports.extend(one.report())
    (want,) = whole.report()
    got = merge_reports([None, *reports])
    assert got is not None and got["sampled_cell_steps"] == want["sampled_cell_steps"] == 39
    assert got["share_outside"] == pytest.approx(want["share_outside"])
    for name in ("a", "b"):
        g, w = got["inputs"][name], want["inputs"][name]
        assert g["share_below"] == pytest.approx(w["share_below"])
        assert g["share_above"] == pytest.approx(w["share_above"])
        assert g["seen"] == pytest.approx(w["seen"]) and g["trained"] == w["trained"]
    assert merge_reports([None, None]) is None


def test_the_features_are_checked_not_the_raw_inputs() -> None:
    trained = TrainedRange(("sum",), (0.0,), (1.0,))
    monitor = SupportMonitor([(slice(0, None), lambda x: x.sum(1, keepdim=True), trained)])
    monitor.observe(torch.tensor([[0.4, 0.4], [0.4, 0.7]]))
    assert monitor.report()[0]["share_outside"] == 0.5


def test_a_sampled_share_is_within_its_binomial_error() -> None:
    """Uniform features on [0, 1] against a range [0, 0.9]: the share is 0.1 up to sampling
    error (4 standard errors of a binomial proportion)."""
    gen = torch.Generator().manual_seed(0)
    monitor = SupportMonitor([(slice(0, None), None, TrainedRange(("z",), (0.0,), (0.9,)))])
    for _ in range(20):
        monitor.observe(torch.rand(1000, 1, generator=gen))
    (report,) = monitor.report()
    n = report["sampled_cell_steps"]
    assert abs(report["share_outside"] - 0.1) < 4 * math.sqrt(0.1 * 0.9 / n)


def test_the_warning_fires_above_its_threshold_only(caplog) -> None:
    trained = TrainedRange(("z",), (0.0,), (1.0,))
    monitor = SupportMonitor([(slice(0, None), None, trained)])
    monitor.observe(torch.tensor([[0.5]] * 99 + [[2.0]]))  # 1 of 100 outside
    (report,) = monitor.report()
    with caplog.at_level(logging.WARNING, logger="surrogate.simulate.support"):
        assert not warn_outside(report, 0.01, "run")  # at the threshold: quiet
        assert not caplog.records
        assert warn_outside(report, 0.009, "run")
    (record,) = caplog.records
    assert "1 % of 100 sampled cell-steps" in record.getMessage()
    assert "z seen [0.5, 2] vs trained [0, 1]" in record.getMessage()
    assert not warn_outside(None, 0.0, "a run with no learned layer")


def test_each_replicate_of_a_batch_is_counted_on_its_own() -> None:
    """A batch of a learned chain (trained on a narrow range) and the full model: the learned
    run's cells are counted, the full run's are not; the counts are the features' own."""
    model = EcoliModel()
    table = PsiLookupTable(torch.full((2, 11), 0.5), [(-1.0, 1.0)], ("dG",))
    learned = AbstractDecision(table, model.internal, model.featurizer(("dG",)))
    learned.trained_range = TrainedRange(("dG",), (0.0,), (0.1,))
    field = GaussianField()
    sim = BatchSimulator(model, [Replicate(FullDecision(model.internal), field, 30, 0),
                                 Replicate(learned, field, 20, 1)], 0.05)  # fmt: skip
    with torch.inference_mode():
        state = sim.initial_state()
        seen = []
        for _ in range(3):
            sim.advance(state, 5)
            sim.observe_support(state)
            seen.append(model.featurizer(("dG",))(state.inputs[30:])[:, 0].double().numpy())
    full_report, learned_report = sim.support_report()
    assert full_report is None
    z = np.concatenate(seen)
    assert learned_report["sampled_cell_steps"] == 60
    assert learned_report["share_outside"] == pytest.approx(np.mean((z < 0.0) | (z > 0.1)))
    assert learned_report["inputs"]["dG"]["seen"] == [pytest.approx(z.min()),
                                                      pytest.approx(z.max())]  # fmt: skip
