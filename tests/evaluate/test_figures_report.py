"""Tests of surrogate.evaluate.figures and surrogate.evaluate.report."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from matplotlib.figure import Figure

from surrogate.evaluate.figures import (
    plot_distance_histograms,
    plot_distance_over_time,
    plot_duration_histograms,
)
from surrogate.evaluate.report import (
    PAPER_QUANTITIES,
    PAPER_TABLE1,
    format_markdown_table,
    paper_table1_frame,
    table1_markdown,
    write_comparison,
    write_report,
)
from surrogate.evaluate.statistics import (
    PAPER_TIMES,
    SimulationRun,
    combine_with_noise_floor,
    comparison_table,
    load_run,
)
from surrogate.io import save_figure

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


def test_distance_histograms(runs: tuple[SimulationRun, SimulationRun], tmp_path: Path) -> None:
    fig = plot_distance_histograms(*runs, times=TIMES, labels=("full", "abstract"))
    assert isinstance(fig, Figure)
    assert len(fig.axes) == 4
    assert fig.axes[0].get_title().startswith("t = 5 s (KS ")
    assert [t.get_text() for t in fig.axes[0].get_legend().get_texts()] == [
        "full (n=50)",
        "abstract (n=50)",
    ]
    out = save_figure(tmp_path / "hist.png", fig)
    assert out.stat().st_size > 1000


def test_distance_histograms_single_time(runs: tuple[SimulationRun, SimulationRun]) -> None:
    assert len(plot_distance_histograms(*runs, times=[10.0]).axes) == 1
    with pytest.raises(ValueError, match="t=99"):
        plot_distance_histograms(*runs, times=[99.0])


@pytest.mark.parametrize(("separate", "n_axes"), [(False, 1), (True, 2)])
def test_distance_over_time(
    runs: tuple[SimulationRun, SimulationRun], tmp_path: Path, separate: bool, n_axes: int
) -> None:
    fig = plot_distance_over_time(*runs, labels=("full", "abstract"), separate=separate)
    assert len(fig.axes) == n_axes
    lines = [line for ax in fig.axes for line in ax.get_lines()]
    assert len(lines) == 2  # one mean line per model
    np.testing.assert_allclose(lines[0].get_xdata(), np.arange(21.0))
    assert save_figure(tmp_path / "time.pdf", fig).stat().st_size > 1000


def test_duration_histograms(runs: tuple[SimulationRun, SimulationRun], tmp_path: Path) -> None:
    fig = plot_duration_histograms(*runs)
    assert len(fig.axes) == 2
    assert [ax.get_yscale() for ax in fig.axes] == ["log", "log"]
    assert [ax.get_title() for ax in fig.axes] == ["run durations", "tumble durations"]
    assert save_figure(tmp_path / "dur.png", fig).exists()


# ----------------------------------------------------------------------------------------------
# markdown and files


def test_paper_table1_values() -> None:
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


def test_table1_markdown_ours_paper_and_noise_floor() -> None:
    ours = _paper_time_table(0.2, 0.03)
    floor = _paper_time_table(0.05, 0.9)
    combined = combine_with_noise_floor(ours, floor)  # 0.2 > max(0.05, 0.192): flagged
    text = table1_markdown({"gaussian": combined, "linear": ours}, {"gaussian": 7.25})
    lines = text.splitlines()
    assert lines[0] == (
        "| Field | Source | t=125 s | t=250 s | t=375 s | t=500 s | Run | Tumble | Speed-up |"
    )
    assert lines[2].startswith("| gaussian | ours | 0.200 (0.030) † |")
    assert lines[2].endswith("| 7.2 |")
    assert lines[3] == (
        "|  | paper | 0.110 (0.556) | 0.160 (0.140) | 0.170 (0.099) | 0.160 (0.140) "
        "| 0.039 (0.425) | 0.101 (7e-05) | 7.8 |"
    )
    assert lines[4].startswith("|  | noise floor | 0.050 | 0.050 |")
    assert lines[5].startswith("| linear | ours | 0.200 (0.030) |")
    assert lines[5].endswith("| – |")  # no speed-up given
    assert "†" not in lines[5]
    assert lines[6].startswith("|  | paper | 0.010 (0.677) |")
    assert any(line.startswith("† KS distance above") for line in lines)


def test_table1_markdown_other_times(runs: tuple[SimulationRun, SimulationRun]) -> None:
    table = comparison_table(*runs, times=TIMES, subsample=200)
    text = table1_markdown({"custom": table}, {"custom": 2.0})
    lines = text.splitlines()
    assert "distance 1 (paper t=125 s)" in lines[0]
    ks5 = table.set_index("quantity").loc["distance_t5", "ks"]
    assert lines[2].startswith(f"| custom | ours | {ks5:.3f} (")
    assert "@5 s" in lines[2]
    assert not any("| paper |" in line for line in lines)  # no paper row for unknown fields


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
