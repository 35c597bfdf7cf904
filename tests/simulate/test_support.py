"""The share of cell-steps outside an abstraction's trained range: counted exactly, per run of a
batch, and warned about above its threshold (never at or below it)."""

from __future__ import annotations

import json
import logging
import math
from typing import Any

import numpy as np
import pandas as pd
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
    TrainingHistogram,
    describe_outside,
    describe_sparse,
    merge_reports,
    min_rows_of,
    sparse_share,
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


def _whole_and_merged(trained: TrainedRange, parts: list[torch.Tensor]) -> tuple[Any, Any]:
    """The report of one monitor over all ``parts`` (a run's shards), and the merge of one
    report per part (with an unobserved part's None first)."""
    whole = SupportMonitor([(slice(0, None), None, trained)])
    reports = []
    for x in parts:
        whole.observe(x)
        one = SupportMonitor([(slice(0, None), None, trained)])
        one.observe(x)
        reports.extend(one.report())
    (want,) = whole.report()
    return want, merge_reports([None, *reports])


def _assert_same_regions(got: list[dict[str, Any]], want: list[dict[str, Any]]) -> None:
    """The sparse regions of two reports: the same places (and classes), shares equal to
    rounding. Compared field by field since ``pytest.approx`` refuses nested structures
    (pytest >= 9.2)."""
    assert [sorted(r) for r in got] == [sorted(r) for r in want]
    for g, w in zip(got, want, strict=True):
        assert {k: v for k, v in g.items() if k != "share"} == {
            k: v for k, v in w.items() if k != "share"
        }
        assert g["share"] == pytest.approx(w["share"])


def test_shards_reports_merge_into_the_report_of_all_their_rows() -> None:
    """Merging the reports of a run's parts (its shards) gives what one monitor over all their
    rows reports: shares weighted by sampled cell-steps, ranges joined; unobserved parts skip."""
    trained = TrainedRange(("a", "b"), (0.0, -1.0), (1.0, 1.0))
    gen = torch.Generator().manual_seed(3)
    parts = [torch.randn(n, 2, generator=gen, dtype=torch.float64) * 1.5 for n in (7, 30, 2)]
    want, got = _whole_and_merged(trained, parts)
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


# --- the density check: sparse bins of the training rows' histogram --------------------------


def _histogram(counts0, counts1, lo=(0.0,), hi=(4.0,), bins=(4,), joint=True, names=("dG",)):
    return TrainingHistogram(names, lo, hi, bins, joint, (tuple(counts0), tuple(counts1)),
                             (0.2, 0.5))  # fmt: skip


def test_the_histogram_counts_each_states_rows_and_reads_back() -> None:
    """Rows at 0, 0.5, ..., 4 over [0, 4] in 64 bins: each row in its bin (the last closed),
    per state; the switching shares per state; the JSON reads back equal."""
    z = np.arange(9, dtype=np.float64)[:, None] / 2
    phi = np.array([0, 0, 0, 0, 1, 1, 1, 1, 1])
    switched = np.array([1, 0, 0, 0, 1, 1, 0, 0, 0], dtype=bool)
    hist = TrainingHistogram.of_rows(z, phi, switched, ["dG"])
    assert hist.bins == (64,) and hist.joint and (hist.lo, hist.hi) == ((0.0,), (4.0,))
    want = [np.zeros(64, dtype=int) for _ in range(2)]
    for v, s in zip(z[:, 0], phi, strict=True):
        want[s][min(int(v / 4 * 64), 63)] += 1
    assert [list(c) for c in hist.counts] == [w.tolist() for w in want]
    assert hist.switching == (0.25, 0.4)
    assert TrainingHistogram.from_dict(json.loads(json.dumps(hist.as_dict()))) == hist
    two = TrainingHistogram.of_rows(np.c_[z, -z], phi, switched, ["a", "b"])
    assert two.joint and two.bins == (16, 16) and sum(map(sum, two.counts)) == 9
    assert two.counts[0][0 * 16 + 15] == 1  # (0, -0) -> a's first bin, b's last (b = -0 = hi)
    three = TrainingHistogram.of_rows(np.c_[z, z, z], phi, switched, ["a", "b", "c"])
    assert not three.joint and three.n_bins == 3 * 64 and sum(map(sum, three.counts)) == 27


def test_the_default_minimum_is_25_expected_switches() -> None:
    assert min_rows_of(0.5) == 25 and min_rows_of(0.05) == 475 and min_rows_of(0.2) == 100
    assert min_rows_of(0.0) == min_rows_of(1.0) == 100  # no rate to go by
    assert min_rows_of(0.05, min_rows=7) == 7
    assert _histogram([0] * 4, [0] * 4).min_rows() == (100, 25)


def test_the_sparse_share_is_the_hand_counted_one() -> None:
    """Bins [0,1) [1,2) [2,3) [3,4] with 200/5/200/200 rows of state 0 and 200/200/200/50 of
    state 1, 100 needed: bins 1 and 3 are sparse. Of 9 cell-steps, 2 are outside, 2 in bin 1
    and 3 in bin 3: 5/9 sparse, most in [3, 4] (3/9)."""
    hist = _histogram([200, 5, 200, 200], [200, 200, 200, 50])
    trained = TrainedRange(("dG",), (0.0,), (4.0,), hist, min_rows=100)
    monitor = SupportMonitor([(slice(0, None), None, trained)])
    z = torch.tensor([[0.5], [1.5], [1.2], [2.5], [3.5], [3.9], [3.1], [5.0], [-1.0]])
    monitor.observe(z[:4])
    monitor.observe(z[4:])
    (report,) = monitor.report()
    assert report["share_outside"] == pytest.approx(2 / 9)
    assert report["share_sparse"] == pytest.approx(5 / 9)
    assert report["sparse_where"] == {"dG": [3.0, 4.0]}
    assert report["sparse_where_share"] == pytest.approx(3 / 9)
    assert report["min_rows"] == [100, 100]
    # the default rule: 100 rows of state 0 (p = 0.2), 25 of state 1 (p = 0.5): bin 3 is not
    default = SupportMonitor([(slice(0, None), None, TrainedRange(("dG",), (0.0,), (4.0,), hist))])
    default.observe(z)
    (report,) = default.report()
    assert report["share_sparse"] == pytest.approx(2 / 9)
    assert report["sparse_where"] == {"dG": [1.0, 2.0]} and report["min_rows"] == [100, 25]


def test_each_cell_is_checked_against_its_own_states_rows() -> None:
    """The hand-counted case above with the cells' phi: bin 1 is sparse for state 0 only (5 rows),
    bin 3 for state 1 only (50). Cells in bin 1 count where they tumble (phi 0), those in bin 3
    where they run (phi 1): a running cell where tumbles were barely trained is not sparse."""
    hist = _histogram([200, 5, 200, 200], [200, 200, 200, 50])
    trained = TrainedRange(("dG",), (0.0,), (4.0,), hist, min_rows=100)
    monitor = SupportMonitor([(slice(0, None), None, trained)])
    z = torch.tensor([[0.5], [1.5], [1.2], [2.5], [3.5], [3.9], [3.1], [5.0], [-1.0]])
    phi = torch.tensor([0, 0, 1, 0, 1, 0, 1, 0, 1], dtype=torch.bool)
    monitor.observe(z, phi)
    (report,) = monitor.report()
    assert report["share_outside"] == pytest.approx(2 / 9)
    assert report["share_sparse"] == pytest.approx(3 / 9)  # z 1.5 (phi 0); 3.5, 3.1 (phi 1)
    assert report["sparse_where"] == {"dG": [3.0, 4.0]}
    assert report["sparse_where_share"] == pytest.approx(2 / 9)
    assert hist.sparse_by_state(100) == ((False, True, False, False), (False, False, False, True))


def test_a_joint_sparse_region_is_the_visited_part_of_its_component() -> None:
    """Two inputs over [0, 2]^2 in 2 x 2 bins, only bin (1, 1) trained: bins (0, 0), (0, 1)
    and (1, 0) form one sparse region; the visited ones are (0, 1) and (1, 0)."""
    hist = _histogram([0, 0, 0, 500], [0, 0, 0, 500], lo=(0.0, 0.0), hi=(2.0, 2.0),
                      bins=(2, 2), names=("a", "b"))  # fmt: skip
    trained = TrainedRange(("a", "b"), (0.0, 0.0), (2.0, 2.0), hist, min_rows=100)
    monitor = SupportMonitor([(slice(0, None), None, trained)])
    monitor.observe(torch.tensor([[0.5, 1.5], [1.5, 0.5], [1.5, 1.5], [1.9, 1.1], [3.0, 0.1]]))
    (report,) = monitor.report()
    assert report["share_sparse"] == pytest.approx(2 / 5)
    assert report["sparse_where"] == {"a": [0.0, 2.0], "b": [0.0, 2.0]}
    assert report["sparse_where_share"] == pytest.approx(2 / 5)


def test_each_input_alone_beyond_two_inputs() -> None:
    """Three inputs: a cell-step is sparse when any input's own bin is; the region is the most
    visited one of any input."""
    names = ("a", "b", "c")
    counts = [500, 500, 500, 500, 0, 500, 500, 0, 500, 500]
    counts = [*counts[:4], 500, *counts[4:]]  # a, b, c: 4, 3, 4 bins (flat bins 5 and 8 empty)
    hist = TrainingHistogram(names, (0.0,) * 3, (4.0, 3.0, 4.0), (4, 3, 4), False,
                             (tuple(counts), tuple(counts)), (0.5, 0.5))  # fmt: skip
    trained = TrainedRange(names, (0.0,) * 3, (4.0, 3.0, 4.0), hist, min_rows=100)
    monitor = SupportMonitor([(slice(0, None), None, trained)])
    x = torch.tensor([[0.5, 0.5, 1.5], [0.5, 0.5, 0.5], [0.5, 0.5, 1.2], [0.5, 1.5, 1.5]])
    monitor.observe(x)
    (report,) = monitor.report()
    assert hist.sparse(100) == tuple(c < 100 for c in counts)
    assert report["share_sparse"] == pytest.approx(3 / 4)  # b's bin 1 once, c's bin 1 thrice
    assert report["sparse_where"] == {"c": [1.0, 2.0]}
    assert report["sparse_where_share"] == pytest.approx(3 / 4)


def test_the_warning_names_the_sparse_interval_and_what_to_do(caplog) -> None:
    hist = _histogram([200, 5, 200, 200], [200, 200, 200, 200])
    trained = TrainedRange(("dG",), (0.0,), (4.0,), hist, min_rows=100)
    monitor = SupportMonitor([(slice(0, None), None, trained)])
    monitor.observe(torch.tensor([[0.5]] * 97 + [[1.5]] * 3))  # 3 % sparse, none outside
    (report,) = monitor.report()
    with caplog.at_level(logging.WARNING, logger="surrogate.simulate.support"):
        assert not warn_outside(report, 0.03, "run")  # at the threshold: quiet
        assert warn_outside(report, 0.02, "run")
    (record,) = caplog.records
    message = record.getMessage()
    assert "3 % of 100 sampled cell-steps inside the trained range" in message
    assert "dG in [1, 2] (3 %)" in message and "fewer than 100/100 rows" in message
    assert "collect.n_per_state" in message and "model.body.perturbation" in message
    assert "outside its training data" not in message
    # every comparison passed: trusted, with the sparse rows as a caveat
    passed = verdict_of(report)
    assert passed.startswith("**Trust it at this size**")
    assert "Caveat, **Sparse training data**" in passed and "dG in [1, 2]" in passed
    # a comparison failed: the sparse rows are the first cause named
    failed = verdict_of(report, failures={"f": ["distance_t100"]})
    assert failed.startswith("**Do not trust it yet.**")
    assert "1. **Sparse training data**" in failed and "dG in [1, 2]" in failed


def verdict_of(report, failures=None) -> str:
    from surrogate.diagnosis.advice import VerdictInputs, verdict
    from surrogate.kinds import chain_kind

    unbiased = {"rel_bias": 0.0, "rel_bias_se": 0.01, "settling_z": 0.0}
    v = verdict(VerdictInputs(diagnostic={"phi0": unbiased, "phi1": unbiased},
                              lump_names=("off", "on"), failures=failures or {},
                              outside={"f": report}, outside_warning=0.01, tolerance=0.03,
                              kind=chain_kind("phi", "none", "learned"), network=False,
                              n_per_state=None))  # fmt: skip
    return v.markdown()


def test_an_older_fit_without_a_histogram_is_checked_by_range_only() -> None:
    """A fit's domain without ``support_histogram`` (or one over other inputs, or unreadable):
    the range alone, and a report without the sparse keys, which the readers skip."""
    domain = {"dG": [0.0, 4.0]}
    hist = _histogram([200] * 4, [200] * 4).as_dict()
    assert TrainedRange.from_domain(domain, ["dG"]).histogram is None
    assert TrainedRange.from_domain(domain, ["dG"], {"inputs": ["dG"]}).histogram is None
    assert TrainedRange.from_domain(domain, ["dG"], {**hist, "inputs": ["L"]}).histogram is None
    assert TrainedRange.from_domain(domain, ["dG"], hist, 7).histogram is not None
    monitor = SupportMonitor([(slice(0, None), None, TrainedRange.from_domain(domain, ["dG"]))])
    monitor.observe(torch.tensor([[1.0], [5.0]]))
    (report,) = monitor.report()
    assert report["share_outside"] == 0.5 and "share_sparse" not in report
    assert sparse_share(report) is None and "Sparse" not in verdict_of(report)
    assert "share_sparse" not in merge_reports([report, report])  # type: ignore[operator]


def test_shards_sparse_shares_merge_into_the_report_of_all_their_rows() -> None:
    """As the range's shares, the sparse share and each sparse region's merge into what one
    monitor over all the shards' rows reports."""
    hist = _histogram([200, 5, 200, 200], [200, 200, 200, 50])
    trained = TrainedRange(("dG",), (0.0,), (4.0,), hist, min_rows=100)
    gen = torch.Generator().manual_seed(5)
    parts = [torch.rand(n, 1, generator=gen, dtype=torch.float64) * 5 for n in (40, 7, 300)]
    want, got = _whole_and_merged(trained, parts)
    assert got is not None
    assert got["share_sparse"] == pytest.approx(want["share_sparse"])
    _assert_same_regions(got["sparse_regions"], want["sparse_regions"])
    assert got["sparse_where"] == want["sparse_where"]
    assert got["sparse_where_share"] == pytest.approx(want["sparse_where_share"])
    assert got["min_rows"] == want["min_rows"]


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_the_density_counts_are_the_same_on_the_gpu() -> None:
    hist = _histogram([200, 5, 200, 200], [200, 200, 200, 50])
    trained = TrainedRange(("dG",), (0.0,), (4.0,), hist, min_rows=100)
    x = torch.rand(10_000, 1, generator=torch.Generator().manual_seed(1)) * 5
    reports = []
    for device in ("cpu", "cuda"):
        monitor = SupportMonitor([(slice(0, None), None, trained)])
        monitor.observe(x.to(device))
        reports.extend(monitor.report())
    assert reports[0] == reports[1]


# --- the K-lumps chain: each cell against its own class's rows ------------------------------

#: four classes, two per lump, as a network's count classes are named
CLASSES = ("off|total<766", "off|total>=766", "on|total<766", "on|total>=766")


def _class_rows(rare: int = 5) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A K-lumps fit's training rows over dG in [0, 4] (64 bins, 200 rows of every class at
    each bin's centre, one more of class 0 at each edge), except class 1 ("off|total>=766"),
    which has ``rare`` rows in bins 20-23 (dG in [1.25, 1.5)), where its lump off still has
    200 + ``rare`` rows; a fifth of each class's rows leave it, so either rule asks for 100
    rows (per state too: a move out of a class here changes its lump). Returns the values, each row's class, whether it left its class, and its phi."""
    centres = (np.arange(64) + 0.5) / 16
    z, cls = [0.0, 4.0], [0, 0]
    for c in range(4):
        for j, v in enumerate(centres):
            n = rare if c == 1 and 20 <= j < 24 else 200
            z += [v] * n
            cls += [c] * n
    label = np.array(cls)
    moved = np.zeros(label.size, dtype=bool)
    for c in range(4):  # every fifth row of each class leaves it (into the other lump)
        moved[np.flatnonzero(label == c)[::5]] = True
    return np.array(z)[:, None], label, moved, (label >= 2).astype(np.int64)


def _class_range(per_class: bool = True, min_rows: int | None = None) -> TrainedRange:
    """The trained range of :func:`_class_rows`'s fit as the simulate stage reads it from the
    fit's manifest (``per_class``: with the per-class histogram, as a K-lumps fit stores it)."""
    from surrogate.stages.train import support_class_histogram, support_histogram

    z, label, moved, phi = _class_rows()
    table = pd.DataFrame({"dG": z[:, 0], "phi": phi, "phi_next": phi ^ moved,
                          "phi_class": label, "phi_class_next": np.where(moved, label ^ 2, label)})  # fmt: skip
    manifest = json.loads(json.dumps({
        "domain": {"dG": [0.0, 4.0]},
        "support_histogram": support_histogram(table, ["dG"]),
        "support_class_histogram": support_class_histogram(table, ["dG"], CLASSES),
    }))  # fmt: skip
    return TrainedRange.from_domain(manifest["domain"], ["dG"], manifest["support_histogram"],
                                    min_rows, manifest["support_class_histogram"] if per_class
                                    else None, CLASSES)  # fmt: skip


def test_the_class_histogram_counts_each_classs_rows_and_reads_back() -> None:
    z, label, moved, _ = _class_rows()
    hist = TrainingHistogram.of_rows(z, label, moved, ["dG"], CLASSES)
    assert hist.classes == CLASSES and hist.groups == CLASSES and hist.bins == (64,)
    assert [sum(c) for c in hist.counts] == [200 * 64 + 2, 200 * 60 + 20, 200 * 64, 200 * 64]
    assert hist.counts[1][19:25] == (200, 5, 5, 5, 5, 200)
    assert hist.switching == tuple(float(moved[label == c].mean()) for c in range(4))
    assert hist.min_rows() == (100,) * 4  # 25 expected moves out of the class at ~0.2
    sparse = hist.sparse_by_state()
    assert [(c, j) for c in range(4) for j in range(64) if sparse[c][j]] == [
        (1, 20), (1, 21), (1, 22), (1, 23)]  # fmt: skip
    back = json.loads(json.dumps(hist.as_dict()))
    assert back["classes"] == list(CLASSES) and TrainingHistogram.from_dict(back) == hist
    # the per-state histogram keeps its keys (no classes) and reads back without them
    states = TrainingHistogram.of_rows(z, label >= 2, moved, ["dG"])
    assert "classes" not in states.as_dict() and states.groups == ("0", "1")
    assert TrainingHistogram.from_dict(states.as_dict()) == states
    with pytest.raises(ValueError, match="counts"):
        TrainingHistogram.from_dict({**hist.as_dict(), "classes": list(CLASSES[:3])})


def test_a_rare_class_in_a_well_filled_bin_is_flagged_per_class_not_per_state() -> None:
    """The rare class's cells in bins 20-23, where its lump has 205 rows, are sparse per class
    (5 of its own rows) and not per state; the other classes' cells there, and its cells where
    it has 200 rows, are not. The region names the class."""
    z = torch.tensor([[1.3]] * 10 + [[1.3]] * 10 + [[1.4]] * 10 + [[3.0]] * 10 + [[9.0]] * 4)
    cls = torch.tensor([1] * 10 + [0] * 10 + [2] * 10 + [1] * 10 + [1] * 4)
    phi = torch.tensor(CLASS_LUMPS)[cls].to(torch.bool)
    per_state = SupportMonitor([(slice(0, None), None, _class_range(per_class=False))])
    per_state.observe(z, phi)
    (state_report,) = per_state.report()
    assert state_report["share_sparse"] == 0.0 and "sparse_class" not in state_report
    monitor = SupportMonitor([(slice(0, None), None, _class_range())])
    assert monitor.needs_classes and not per_state.needs_classes
    monitor.observe(z[:25], phi[:25], cls[:25])
    monitor.observe(z[25:], phi[25:], cls[25:])
    (report,) = monitor.report()
    assert report["share_outside"] == pytest.approx(4 / 44)
    assert report["share_sparse"] == pytest.approx(10 / 44)
    assert report["sparse_class"] == CLASSES[1] and report["classes"] == list(CLASSES)
    assert report["sparse_where"] == {"dG": [1.25, 1.5]}
    assert report["sparse_regions"] == [
        {"where": {"dG": [1.25, 1.5]}, "class": CLASSES[1], "share": pytest.approx(10 / 44)}
    ]
    assert report["min_rows"] == [100] * 4
    assert f"class {CLASSES[1]} at dG in [1.25, 1.5]" in describe_sparse(report)
    # an explicit minimum applies per class alike: 4 rows are enough, nothing is sparse
    lenient = SupportMonitor([(slice(0, None), None, _class_range(min_rows=4))])
    lenient.observe(z, phi, cls)
    assert lenient.report()[0]["share_sparse"] == 0.0  # type: ignore[index]
    # cells of unknown class: sparse where any class is (its first such class named)
    blind = SupportMonitor([(slice(0, None), None, _class_range())])
    blind.observe(z, phi)
    (report,) = blind.report()
    assert report["share_sparse"] == pytest.approx(30 / 44)
    assert report["sparse_class"] == CLASSES[1]


CLASS_LUMPS = (0, 0, 1, 1)


def test_an_older_k_lumps_fit_without_the_class_histogram_is_checked_per_state() -> None:
    """No ``support_class_histogram`` (a fit made before it was stored), an unreadable one or
    one over other classes: the per-state check, with the per-state report's keys."""
    whole = _class_range()
    assert whole.class_histogram is not None
    stored = whole.class_histogram.as_dict()
    domain, hist = {"dG": [0.0, 4.0]}, whole.histogram.as_dict()  # type: ignore[union-attr]
    assert TrainedRange.from_domain(domain, ["dG"], hist).class_histogram is None
    assert TrainedRange.from_domain(domain, ["dG"], hist, None, {"inputs": ["dG"]},
                                    CLASSES).class_histogram is None  # fmt: skip
    assert TrainedRange.from_domain(domain, ["dG"], hist, None, stored,
                                    CLASSES[::-1]).class_histogram is None  # fmt: skip
    older = TrainedRange.from_domain(domain, ["dG"], hist, None, None, CLASSES)
    monitor = SupportMonitor([(slice(0, None), None, older)])
    assert not monitor.needs_classes
    monitor.observe(torch.tensor([[1.3], [3.0]]), torch.tensor([False, True]))
    (report,) = monitor.report()
    assert report["share_sparse"] == 0.0 and report["min_rows"] == [100, 100]
    assert "sparse_class" not in report and "classes" not in report


def test_class_shards_merge_into_the_report_of_all_their_rows(caplog) -> None:
    """Shards of a K-lumps run: the sparse share and each (class, interval) region merge into
    what one monitor over all their cell-steps reports; the warning names the class, the
    interval and the remedies (more rows, coarser classes)."""
    trained = _class_range()
    gen = torch.Generator().manual_seed(3)
    parts = [(1.0 + torch.rand(n, 1, generator=gen, dtype=torch.float64),
              torch.randint(0, 4, (n,), generator=gen)) for n in (50, 9, 400)]  # fmt: skip
    whole = SupportMonitor([(slice(0, None), None, trained)])
    reports = []
    for x, cls in parts:
        whole.observe(x, None, cls)
        one = SupportMonitor([(slice(0, None), None, trained)])
        one.observe(x, None, cls)
        reports.extend(one.report())
    (want,) = whole.report()
    got = merge_reports([None, *reports])
    assert got is not None and want is not None and want["share_sparse"] > 0.02
    assert got["share_sparse"] == pytest.approx(want["share_sparse"])
    _assert_same_regions(got["sparse_regions"], want["sparse_regions"])
    assert {r["class"] for r in got["sparse_regions"]} == {CLASSES[1]}
    assert got["sparse_class"] == want["sparse_class"] == CLASSES[1]
    assert got["classes"] == list(CLASSES) and got["min_rows"] == want["min_rows"]
    with caplog.at_level(logging.WARNING, logger="surrogate.simulate.support"):
        assert warn_outside(got, 0.01, "run")
    message = caplog.records[-1].getMessage()
    assert f"class {CLASSES[1]} at dG in [1.25, 1.5]" in message
    assert "collect.n_per_state" in message and "coarser classes" in message
    assert "model.classes" in message
    text = verdict_of(got, failures={"f": ["distance_t100"]})
    assert "1. **Sparse training data**" in text and f"class {CLASSES[1]}" in text
    assert "coarser classes" in text


def test_a_k_lumps_run_checks_each_cell_against_its_own_class() -> None:
    """A batch of the full model and the exact K-lumps chain whose (made-up) training rows
    lack one class everywhere: the chain's sparse share is exactly its sampled cell-steps in
    that class (the layer's own classes, read from the batch's decision), and observing
    changes neither the cells' classes nor the random stream."""
    from surrogate.simulate.classes import ClassDecision, exact_class_table

    model, dt = EcoliModel(), 0.05
    table = exact_class_table(model.internal, dt, size=16)
    lo, hi = table.bounds[0]
    counts = tuple((0 if c == 3 else 1000,) * 4 for c in range(table.n_classes))
    hist = TrainingHistogram(("dG",), (lo,), (hi,), (4,), True, counts,
                             (0.5,) * table.n_classes, table.class_names)  # fmt: skip
    states = TrainingHistogram(("dG",), (lo,), (hi,), (4,), True, ((1000,) * 4,) * 2, (0.5, 0.5))

    def batch(observe: bool) -> tuple[list[float], Any, torch.Tensor]:
        layer = ClassDecision(table, model.internal, model.featurizer(("dG",)))
        layer.trained_range = TrainedRange(("dG",), (lo,), (hi,), states,  # type: ignore[attr-defined]
                                           class_histogram=hist)  # fmt: skip
        sim = BatchSimulator(model, [Replicate(FullDecision(model.internal), GaussianField(), 30, 0),
                                     Replicate(layer, GaussianField(), 40, 1)], dt)  # fmt: skip
        rare = []
        with torch.inference_mode():
            state = sim.initial_state()
            for _ in range(4):
                sim.advance(state, 3)
                if observe:
                    sim.observe_support(state)
                z = model.featurizer(("dG",))(state.inputs[30:])[:, 0].double()
                inside = (z >= lo) & (z <= hi)
                rare.append(float(((layer.cls == 3) & inside).sum()))
        return rare, sim.support_report(), state.phi.clone()

    rare, (full, report), phi = batch(observe=True)
    again, _, phi_unobserved = batch(observe=False)
    assert full is None and report["sampled_cell_steps"] == 160
    assert rare == again and torch.equal(phi, phi_unobserved)
    assert report["share_sparse"] == pytest.approx(sum(rare) / 160)
    assert sum(rare) > 0 and report["classes"] == list(table.class_names)
    assert {r["class"] for r in report["sparse_regions"]} == {table.class_names[3]}


def test_a_two_state_runs_report_keeps_its_keys() -> None:
    """Per state (a two-state or clock chain, no per-class histogram): the report's keys and
    its regions' keys are the ones it had before classes were checked, merged alike, and no
    classes are asked of the simulator."""
    hist = _histogram([200, 5, 200, 200], [200, 200, 200, 50])
    trained = TrainedRange(("dG",), (0.0,), (4.0,), hist, min_rows=100)
    monitor = SupportMonitor([(slice(0, None), None, trained)])
    assert not monitor.needs_classes
    z = torch.tensor([[0.5], [1.5], [1.2], [2.5], [3.5], [3.9], [3.1], [5.0], [-1.0]])
    monitor.observe(z, torch.tensor([0, 0, 1, 0, 1, 0, 1, 0, 1], dtype=torch.bool))
    (report,) = monitor.report()
    keys = {"sampled_cell_steps", "share_outside", "inputs", "share_sparse", "sparse_where",
            "sparse_where_share", "sparse_regions", "min_rows"}  # fmt: skip
    assert set(report) == keys and report["sparse_regions"] == [
        {"where": {"dG": [3.0, 4.0]}, "share": pytest.approx(2 / 9)},
        {"where": {"dG": [1.0, 2.0]}, "share": pytest.approx(1 / 9)}]  # fmt: skip
    merged = merge_reports([report, report])
    assert merged is not None and set(merged) == keys
    assert [set(r) for r in merged["sparse_regions"]] == [{"where", "share"}] * 2
    assert "class" not in describe_sparse(report) and "per state phi = 0/1" in describe_sparse(
        report
    )
    assert hist.as_dict().keys() == {"inputs", "lo", "hi", "bins", "joint", "counts", "switching"}


@pytest.mark.parametrize("names", [["a"], ["a", "b", "c"]])  # joint, and marginal per input
def test_rows_standing_for_several_windows_count_as_that_many(names) -> None:
    """A collection that keeps every switch: each row counted as the windows it stands for,
    in the counts and the switching shares alike, as the rows replicated that many times."""
    rng = np.random.default_rng(3)
    values = rng.random((300, len(names)))
    phi, switched = rng.integers(0, 2, 300), rng.random(300) < 0.2
    windows = np.where(switched, 1, rng.integers(2, 6, 300))
    copies = np.repeat(np.arange(300), windows)
    weighted = TrainingHistogram.of_rows(values, phi, switched, names, windows=windows)
    replicated = TrainingHistogram.of_rows(values[copies], phi[copies], switched[copies], names)
    assert weighted.counts == replicated.counts
    assert weighted.switching == pytest.approx(replicated.switching, rel=1e-12)
