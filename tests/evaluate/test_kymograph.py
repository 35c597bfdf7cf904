"""The kymograph: density and concentration over x and t, runs side by side on shared scales."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from matplotlib.image import AxesImage

from surrogate.evaluate.kymograph import plot_kymograph
from surrogate.io import save_figure
from surrogate.simulate.profiles import Profiles

EDGES = np.linspace(0.0, 4.0, 41)


def profiles(n_cells: int, speed: float, t: np.ndarray | None = None) -> Profiles:
    """A band of ``n_cells`` moving at ``speed`` mm/s from x = 1 and a front 0.2 mm behind it,
    every cell in one column at the first record."""
    t = np.arange(0.0, 6.0) if t is None else t
    x = 0.5 * (EDGES[1:] + EDGES[:-1])
    centre = 1.0 + speed * t[:, None]
    share = np.exp(-0.5 * ((x - centre) / 0.3) ** 2)
    counts = np.round(n_cells * share / share.sum(1, keepdims=True)).astype(np.int64)
    counts[0] = 0
    counts[0, 10] = n_cells
    c = 0.1 / (1.0 + np.exp(-(x - centre + 0.2) / 0.1))
    c[0] = 0.1
    zero = np.zeros(t.size, dtype=np.int64)
    return Profiles(t=t, edges=EDGES, counts=counts, below=zero, above=zero,
                    concentration={"serine": c}, read="serine", n_cells=n_cells)  # fmt: skip


def test_full_and_abstract_side_by_side_on_shared_scales(tmp_path: Path) -> None:
    """Two rows (density, concentration) x two runs, each row on one colour scale up to its
    largest value after the first record; a PNG is written."""
    full, abstract = profiles(2_000, 0.2), profiles(100_000, 0.3)
    fig = plot_kymograph([full, abstract], ["full", "abstract"])
    images = [[im for im in ax.get_images() if isinstance(im, AxesImage)]
              for ax in fig.axes[:4]]  # fmt: skip
    assert all(len(i) == 1 for i in images)
    density = [images[0][0], images[1][0]]
    concentration = [images[2][0], images[3][0]]
    top = max(full.density[1:].max(), abstract.density[1:].max())
    assert all(im.get_clim() == pytest.approx((0.0, top)) for im in density)
    assert top < full.density[0].max()  # the start saturates, not the band
    assert all(im.get_clim() == pytest.approx((0.0, 0.1), rel=1e-3) for im in concentration)
    assert [ax.get_title() for ax in fig.axes[:2]] == ["full (n=2000)", "abstract (n=100000)"]
    fronts = fig.axes[0].get_lines()[0].get_xdata()
    assert np.isnan(fronts[0]) and np.all(np.diff(fronts[1:]) > 0)  # the front moves on
    path = save_figure(tmp_path / "kymograph.png", fig, crop=False)
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and path.stat().st_size > 10_000


def test_uneven_record_times_and_bad_calls() -> None:
    """Uneven record times are drawn as a mesh; no run, or labels that do not match, refused."""
    fig = plot_kymograph([profiles(100, 0.2, np.array([0.0, 1.0, 3.0, 7.0]))], front=False)
    assert not fig.axes[0].get_images() and fig.axes[0].collections
    with pytest.raises(ValueError, match="at least one"):
        plot_kymograph([])
    with pytest.raises(ValueError, match="labels"):
        plot_kymograph([profiles(10, 0.2)], ["a", "b"])
