"""Tests of surrogate.evaluate.figures and surrogate.evaluate.report."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from matplotlib.figure import Figure
from scipy import stats

from surrogate.evaluate.figures import (
    plot_drift,
    plot_duration_histograms,
    plot_observable_histograms,
    plot_observable_over_time,
)
from surrogate.evaluate.report import (
    format_markdown_table,
    split_quantity,
    table1_markdown,
    write_comparison,
    write_report,
)
from surrogate.evaluate.runs import SimulationRun, load_run, mean_std_over_time, observable_at
from surrogate.evaluate.statistics import PAPER_TIMES, combine_with_noise_floor, comparison_table
from surrogate.io import save_figure
from surrogate.models.ecoli import EcoliModel
from surrogate.models.ecoli.reference import PAPER_QUANTITIES, PAPER_TABLE1, paper_table1_frame

from .test_statistics import TIMES, write_synthetic_run


@pytest.fixture
def runs(tmp_path: Path) -> tuple[SimulationRun, SimulationRun]:
    """A reference run and a shifted candidate run, loaded from disk."""
    ref = load_run(write_synthetic_run(tmp_path / "ref", seed=1, n_durations=500))
    cand = load_run(write_synthetic_run(tmp_path / "cand", seed=2, shift=0.3, n_durations=500))
    return ref, cand


def _paper_time_table(ks: float, pvalue: float) -> pd.DataFrame:
    """A comparison table at the paper's quantities with constant values."""
    return pd.DataFrame(
        {
            "quantity": list(PAPER_QUANTITIES),
            "ks": ks,
            "ks_pvalue": pvalue,
            "wasserstein": 0.1,
            "n_reference": 100,
            "n_candidate": 100,
            "ks_critical_05": 0.192,
            "ks_full": np.nan,
            "ks_pvalue_full": np.nan,
        }
    )


# ----------------------------------------------------------------------------------------------
# figures


def test_observable_histograms(runs: tuple[SimulationRun, SimulationRun], tmp_path: Path) -> None:
    fig = plot_observable_histograms(*runs, times=TIMES, labels=("full", "abstract"))
    assert isinstance(fig, Figure)
    assert len(fig.axes) == 4
    assert fig.axes[0].get_title().startswith("t = 5 s (KS ")
    assert fig.axes[0].get_xlabel() == "distance"  # the first observable, by default
    assert [t.get_text() for t in fig.axes[0].get_legend().get_texts()] == [
        "full (n=50)",
        "abstract (n=50)",
    ]
    out = save_figure(tmp_path / "hist.png", fig)
    assert out.stat().st_size > 1000


def test_observable_histograms_single_time(runs: tuple[SimulationRun, SimulationRun]) -> None:
    assert len(plot_observable_histograms(*runs, times=[10.0]).axes) == 1
    with pytest.raises(ValueError, match="t=99"):
        plot_observable_histograms(*runs, times=[99.0])
    with pytest.raises(ValueError, match="at least one time"):
        plot_observable_histograms(*runs, times=[])


def test_observable_histograms_of_a_named_observable(tmp_path: Path) -> None:
    ref = load_run(write_synthetic_run(tmp_path / "r", seed=1, extra_observable=True))
    cand = load_run(write_synthetic_run(tmp_path / "c", seed=2, shift=0.3, extra_observable=True))
    fig = plot_observable_histograms(ref, cand, times=[5.0, 20.0], name="speed",
                                     axis_label="speed (mm/s)")  # fmt: skip
    assert [ax.get_xlabel() for ax in fig.axes] == ["speed (mm/s)"] * 2
    # the title's KS is that of the named observable, not of the distance
    a, b = observable_at(ref, "speed", 20.0), observable_at(cand, "speed", 20.0)
    ks = stats.ks_2samp(a, b).statistic
    assert fig.axes[1].get_title() == f"t = 20 s (KS {ks:.3f})"
    # the bins (shared by all panels) span the speed values (a few 1e-2), not the distances
    speeds = np.concatenate([observable_at(r, "speed", t) for r in (ref, cand) for t in (5, 20)])
    for ax in fig.axes:
        xs = np.concatenate([p.get_path().vertices[:, 0] for p in ax.patches])
        np.testing.assert_allclose([xs.min(), xs.max()], [speeds.min(), speeds.max()], rtol=1e-9)


@pytest.mark.parametrize(("separate", "n_axes"), [(False, 1), (True, 2)])
def test_observable_over_time(
    runs: tuple[SimulationRun, SimulationRun], tmp_path: Path, separate: bool, n_axes: int
) -> None:
    fig = plot_observable_over_time(*runs, labels=("full", "abstract"), separate=separate)
    assert len(fig.axes) == n_axes
    lines = [line for ax in fig.axes for line in ax.get_lines()]
    assert len(lines) == 2  # one mean line per model
    np.testing.assert_allclose(lines[0].get_xdata(), np.arange(21.0))
    np.testing.assert_allclose(lines[0].get_ydata(), mean_std_over_time(runs[0])["mean"])
    np.testing.assert_allclose(lines[1].get_ydata(), mean_std_over_time(runs[1])["mean"])
    assert fig.axes[0].get_ylabel() == "distance"
    assert save_figure(tmp_path / "time.pdf", fig).stat().st_size > 1000


def test_drift_is_the_gap_of_the_means_on_the_noise_band(
    runs: tuple[SimulationRun, SimulationRun], tmp_path: Path
) -> None:
    """plot_drift draws mean(candidate) - mean(reference) per record time (and the second full
    run's gap), on a band of +- 1.96 sqrt(2) s.d./sqrt(n) of the reference around zero."""
    ref, cand = runs
    fig = plot_drift(ref, cand, repeat=ref)
    _zero, gap, repeat = fig.axes[0].get_lines()
    want = mean_std_over_time(cand)["mean"] - mean_std_over_time(ref)["mean"]
    np.testing.assert_allclose(gap.get_ydata(), want)
    np.testing.assert_allclose(repeat.get_ydata(), 0.0)  # the reference against itself
    ms = mean_std_over_time(ref)
    (band,) = fig.axes[0].collections
    top = band.get_paths()[0].vertices[:, 1].max()
    assert top == pytest.approx(float((1.96 * np.sqrt(2) * ms["std"] / np.sqrt(ms["n"])).max()))
    assert save_figure(tmp_path / "drift.png", fig).stat().st_size > 1000


def test_observable_over_time_of_a_named_observable(tmp_path: Path) -> None:
    ref = load_run(write_synthetic_run(tmp_path / "r", seed=1, extra_observable=True))
    cand = load_run(write_synthetic_run(tmp_path / "c", seed=2, shift=0.3, extra_observable=True))
    fig = plot_observable_over_time(ref, cand, name="speed", axis_label="speed (mm/s)")
    lines = fig.axes[0].get_lines()
    np.testing.assert_allclose(lines[0].get_ydata(), mean_std_over_time(ref, "speed")["mean"])
    np.testing.assert_allclose(lines[1].get_ydata(), mean_std_over_time(cand, "speed")["mean"])
    assert fig.axes[0].get_ylabel() == "speed (mm/s)"


def test_duration_histograms(runs: tuple[SimulationRun, SimulationRun], tmp_path: Path) -> None:
    fig = plot_duration_histograms(*runs)
    assert len(fig.axes) == 2
    assert [ax.get_yscale() for ax in fig.axes] == ["log", "log"]
    assert [ax.get_title() for ax in fig.axes] == ["run durations", "tumble durations"]
    assert save_figure(tmp_path / "dur.png", fig).exists()


def test_duration_histograms_of_other_lumps(tmp_path: Path) -> None:
    kw = {"lump_names": ("off", "on"), "n_durations": 200}
    ref = load_run(write_synthetic_run(tmp_path / "r", seed=1, **kw))
    cand = load_run(write_synthetic_run(tmp_path / "c", seed=2, **kw))
    fig = plot_duration_histograms(ref, cand)
    assert [ax.get_title() for ax in fig.axes] == ["on durations", "off durations"]
    assert [t.get_text() for t in fig.axes[0].get_legend().get_texts()] == [
        "full (n=200)",
        "abstract (n=200)",
    ]


def _drawn_extent(fig: Figure) -> tuple[float, float, float, float]:
    """The bounding box (inches) of everything ``fig`` draws: what ``bbox_inches="tight"``
    would crop to."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    renderer = FigureCanvasAgg(fig).get_renderer()
    fig.draw(renderer)
    box = fig.get_tightbbox(renderer)
    return box.x0, box.y0, box.x1, box.y1


def test_fixed_margins_keep_every_label_on_the_canvas(
    runs: tuple[SimulationRun, SimulationRun], tmp_path: Path
) -> None:
    """The evaluation's figures are saved uncropped (margins set by hand): nothing drawn (tick
    labels, axis labels, titles, legends) may fall off the canvas, even with a long axis
    label."""
    from PIL import Image

    label = "distance from the peak of the field (mm)"
    figures = {
        "hist": plot_observable_histograms(*runs, times=TIMES, axis_label=label),
        "time": plot_observable_over_time(*runs, separate=True, axis_label=label),
        "time1": plot_observable_over_time(*runs, axis_label=label),
        "dur": plot_duration_histograms(*runs),
    }
    for name, fig in figures.items():
        x0, y0, x1, y1 = _drawn_extent(fig)
        width, height = fig.get_size_inches()
        assert x0 >= 0 and y0 >= 0 and x1 <= width and y1 <= height, (name, x0, y0, x1, y1)
        with Image.open(save_figure(tmp_path / f"{name}.png", fig, crop=False)) as image:
            assert image.size == (round(width * 120), round(height * 120)), name  # not cropped
    cropped = save_figure(tmp_path / "cropped.png", plot_duration_histograms(*runs), crop=True)
    with Image.open(cropped) as image:
        assert image.size != (9 * 120, round(3.5 * 120))


# ----------------------------------------------------------------------------------------------
# markdown and files


def test_paper_table1_values() -> None:
    assert EcoliModel().reference_table() is PAPER_TABLE1
    assert set(PAPER_TABLE1) == {"gaussian", "linear", "dynamic"}
    assert PAPER_TABLE1["gaussian"]["ks"]["tumble"] == 0.101
    assert PAPER_TABLE1["gaussian"]["ks_pvalue"]["tumble"] == 7e-5
    assert PAPER_TABLE1["linear"]["ks"]["distance_t250"] == 0.150
    assert PAPER_TABLE1["dynamic"]["ks_pvalue"]["distance_t250"] == 0.961
    assert [PAPER_TABLE1[f]["speedup"] for f in ("gaussian", "linear", "dynamic")] == [
        7.8,
        9.4,
        8.9,
    ]
    frame = paper_table1_frame()
    assert frame.shape == (18, 4)
    # our comparison rows at the paper's times carry the same quantity names as the paper
    assert [f"distance_t{t:g}" for t in PAPER_TIMES] == list(PAPER_QUANTITIES[:4])


def test_format_markdown_table() -> None:
    df = pd.DataFrame(
        {
            "quantity": ["run", "a|b"],
            "ks": [0.12345, np.nan],
            "p": [1e-5, 0.5],
            "n": [10, 20],
            "ok": [True, False],
        }
    )
    text = format_markdown_table(df, floatfmt={"p": ".2g"})
    assert text.splitlines() == [
        "| quantity | ks | p | n | ok |",
        "|:---|---:|---:|---:|:---|",
        "| run | 0.123 | 1e-05 | 10 | yes |",
        "| a\\|b |  | 0.5 | 20 | no |",
    ]
    assert "| run | 0.12 |" in format_markdown_table(df, floatfmt=".2f")


def test_table1_markdown_ours_published_and_noise_floor() -> None:
    ours = _paper_time_table(0.2, 0.03)
    floor = _paper_time_table(0.05, 0.9)
    combined = combine_with_noise_floor(ours, floor)  # 0.2 > max(0.05, 0.192): flagged
    text = table1_markdown(
        {"gaussian": combined, "linear": ours}, {"gaussian": 7.25}, reference=PAPER_TABLE1
    )
    lines = text.splitlines()
    assert lines[0] == (
        "| Field | Source | t=125 s | t=250 s | t=375 s | t=500 s | Run | Tumble | Speed-up |"
    )
    assert lines[1] == "|:---|:---|---:|---:|---:|---:|---:|---:|---:|"
    assert lines[2].startswith("| gaussian | ours | 0.200 (0.030) † |")
    assert lines[2].endswith("| 7.2 |")
    assert lines[3] == (
        "|  | published | 0.110 (0.556) | 0.160 (0.140) | 0.170 (0.099) | 0.160 (0.140) "
        "| 0.039 (0.425) | 0.101 (7e-05) | 7.8 |"
    )
    assert lines[4].startswith("|  | noise floor | 0.050 | 0.050 |")
    assert lines[5].startswith("| linear | ours | 0.200 (0.030) |")
    assert lines[5].endswith("| – |")  # no speed-up given
    assert "†" not in lines[5]
    assert lines[6].startswith("|  | published | 0.010 (0.677) |")
    assert lines[7] == ""  # no noise floor for linear: the notes follow
    assert any(line.startswith("† KS distance above") for line in lines)


def test_table1_markdown_without_reference() -> None:
    ours = _paper_time_table(0.1, 0.5)
    lines = table1_markdown({"gaussian": ours}, {"gaussian": 3.0}).splitlines()
    assert lines[2] == (
        "| gaussian | ours | 0.100 (0.500) | 0.100 (0.500) | 0.100 (0.500) | 0.100 (0.500) "
        "| 0.100 (0.500) | 0.100 (0.500) | 3.0 |"
    )
    assert lines[3] == ""  # neither published nor noise-floor rows
    assert not any("†" in line for line in lines)


def test_table1_markdown_other_times(runs: tuple[SimulationRun, SimulationRun]) -> None:
    table = comparison_table(*runs, times=TIMES, subsample=200)
    text = table1_markdown({"custom": table}, {"custom": 2.0}, reference=PAPER_TABLE1)
    lines = text.splitlines()
    assert lines[0] == (
        "| Field | Source | t=5 s | t=10 s | t=15 s | t=20 s | Run | Tumble | Speed-up |"
    )
    by_q = table.set_index("quantity")
    ks5, p5 = by_q.loc["distance_t5", "ks"], by_q.loc["distance_t5", "ks_pvalue"]
    p5_text = f"{p5:.3f}" if p5 >= 1e-3 else f"{p5:.0e}"
    assert lines[2].startswith(f"| custom | ours | {ks5:.3f} ({p5_text}) |")
    assert lines[2].endswith("| 2.0 |")
    assert not any("| published |" in line for line in lines)  # not a field of the reference


def test_table1_markdown_several_observables_and_lumps(tmp_path: Path) -> None:
    kw = {"extra_observable": True, "lump_names": ("off", "on"), "n_durations": 300}
    ref = load_run(write_synthetic_run(tmp_path / "r", seed=1, **kw))
    cand = load_run(write_synthetic_run(tmp_path / "c", seed=2, shift=0.2, **kw))
    table = comparison_table(ref, cand, times=(20.0, 5.0), subsample=100)
    reference = {"f": {"ks": {"speed_t5": 0.5, "on": 0.25}, "ks_pvalue": {"speed_t5": 1e-4,
                                                                          "on": 0.5}}}  # fmt: skip
    lines = table1_markdown({"f": table}, {}, reference=reference, floatfmt=".2f").splitlines()
    # quantities named in full (two observables), each in time order, then the lumps
    assert lines[0] == (
        "| Field | Source | distance_t5 | distance_t20 | speed_t5 | speed_t20 | On | Off "
        "| Speed-up |"
    )
    by_q = table.set_index("quantity")
    cells = lines[2].split(" | ")
    assert cells[2].startswith(f"{by_q.loc['distance_t5', 'ks']:.2f} (")
    assert cells[4].startswith(f"{by_q.loc['speed_t5', 'ks']:.2f} (")
    assert cells[6].startswith(f"{by_q.loc['on', 'ks']:.2f} (")
    assert lines[3] == "|  | published |  |  | 0.50 (1e-04) |  | 0.25 (0.500) |  |  |"


def test_split_quantity() -> None:
    assert split_quantity("distance_t125") == ("distance", 125.0)
    assert split_quantity("distance_t2.5") == ("distance", 2.5)
    assert split_quantity("mean_speed_t10") == ("mean_speed", 10.0)
    assert split_quantity("run") is None
    assert split_quantity("tumble") is None


def test_write_report(tmp_path: Path) -> None:
    fig_path = tmp_path / "figures" / "hist.png"
    fig_path.parent.mkdir()
    fig_path.write_bytes(b"png")
    path = write_report(
        tmp_path / "report" / "report.md",
        sections=[("Table 1", "| a |\n|---|\n| 1 |\n"), ("Notes", "text")],
        figures=[("Distances", fig_path)],
    )
    text = path.read_text()
    assert text.startswith("# Evaluation report\n")
    assert "## Table 1\n\n| a |\n|---|\n| 1 |\n\n## Notes\n\ntext\n" in text
    assert "![Distances](../figures/hist.png)" in text
    assert not list(path.parent.glob("*.tmp"))


def test_write_comparison(runs: tuple[SimulationRun, SimulationRun], tmp_path: Path) -> None:
    table = comparison_table(*runs, times=TIMES, subsample=200)
    csv_path, md_path = write_comparison(tmp_path / "out", table, prefix="gaussian")
    assert (csv_path.name, md_path.name) == ("gaussian.csv", "gaussian.md")
    back = pd.read_csv(csv_path)
    pd.testing.assert_frame_equal(back, table, check_dtype=False)
    md = md_path.read_text().splitlines()
    assert md[0].startswith("| quantity | ks | ks_pvalue | wasserstein |")
    assert len(md) == 2 + len(table)
    assert md[2].startswith(f"| distance_t5 | {table['ks'].iloc[0]:.3f} |")
