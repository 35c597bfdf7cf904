"""PsiClassifier: routing by phi, chunking, large batches, export and save/load."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pandas as pd
import pytest
import torch
from torch import Tensor

from surrogate.errors import ArtefactError
from surrogate.gp import (
    GPSettings,
    PsiClassifier,
    data_domain,
    fit_classifier,
    fit_psi,
    load_psi,
    save_psi,
)

TINY = GPSettings(n_inducing=10, epochs=3, batch_size=200)


@pytest.fixture(autouse=True, scope="module")
def _one_thread() -> Iterator[None]:
    # Shared 2-core machine: avoid OpenMP oversubscription with other test processes.
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


def transitions(n: int, seed: int) -> pd.DataFrame:
    """Synthetic transition table: RUN persists below m0(L), TUMBLE ends with prob ~ 0.3."""
    gen = torch.Generator().manual_seed(seed)
    m = 1.0 + 2.5 * torch.rand(n, generator=gen, dtype=torch.float64)
    L = 0.1 * torch.rand(n, generator=gen, dtype=torch.float64)
    phi = torch.randint(0, 2, (n,), generator=gen)
    switch = torch.sigmoid((2.2 + 10.0 * L - m) / 0.1)
    p_run = torch.where(phi == 1, 0.05 + 0.9 * switch, 0.3 * switch)
    nxt = torch.bernoulli(p_run, generator=gen).long()
    return pd.DataFrame({"m": m, "L": L, "phi": phi, "phi_next": nxt})


@pytest.fixture(scope="module")
def data() -> pd.DataFrame:
    return transitions(1200, seed=0)


@pytest.fixture(scope="module")
def psi(data: pd.DataFrame) -> PsiClassifier:
    return fit_psi(data, TINY, progress=False)


def queries(n: int, seed: int = 5) -> tuple[Tensor, Tensor, Tensor]:
    gen = torch.Generator().manual_seed(seed)
    phi = torch.randint(0, 2, (n,), generator=gen)
    m = 1.0 + 2.5 * torch.rand(n, generator=gen)
    L = 0.1 * torch.rand(n, generator=gen)
    return phi, m, L


def test_fit_psi_splits_by_origin(psi: PsiClassifier, data: pd.DataFrame) -> None:
    n_tumble = int((data["phi"] == 0).sum())
    assert psi.psi_tumble.n_train + psi.psi_tumble.n_val == n_tumble
    assert psi.psi_run.n_train + psi.psi_run.n_val == len(data) - n_tumble
    assert psi.domain == data_domain(data)
    assert psi.domain["m"] == (float(data["m"].min()), float(data["m"].max()))


def test_routing_by_phi(psi: PsiClassifier) -> None:
    phi, m, L = queries(3000)
    out = psi(phi, m, L)
    x = torch.stack([m, L], dim=1)
    run = phi == 1
    # Each row must come from its own classifier, bit for bit.
    assert torch.equal(out[run], psi.psi_run.predict_proba(x[run]))
    assert torch.equal(out[~run], psi.psi_tumble.predict_proba(x[~run]))
    # And the two classifiers really differ here (else the check above could not fail):
    # the tumble surface is capped at 0.3, the run surface reaches 0.95.
    assert (psi.psi_run.predict_proba(x) - psi.psi_tumble.predict_proba(x)).abs().max() > 0.3


def test_bool_and_int_phi_agree(psi: PsiClassifier) -> None:
    phi, m, L = queries(500)
    assert torch.equal(psi(phi, m, L), psi(phi.bool(), m, L))


@pytest.mark.parametrize("chunk", [1, 7, 64, 100, 1000])
def test_chunking_is_exact(psi: PsiClassifier, chunk: int) -> None:
    phi, m, L = queries(2345)
    whole = psi(phi, m, L)
    psi.chunk_size = chunk
    try:
        chunked = psi(phi, m, L)
    finally:
        psi.chunk_size = 65_536
    assert torch.equal(chunked, whole)
    # A row's value does not depend on which other rows share the call.
    assert torch.equal(psi(phi[100:117], m[100:117], L[100:117]), whole[100:117])


def test_million_queries(psi: PsiClassifier) -> None:
    phi, m, L = queries(1_000_000, seed=9)
    out = psi(phi, m, L.double())
    assert out.dtype == torch.float32
    assert out.shape == (1_000_000,)
    assert out.device == m.device
    assert bool(((out >= 0) & (out <= 1)).all())
    assert torch.equal(out[-50:], psi(phi[-50:], m[-50:], L[-50:]))


def test_single_phi_batch(psi: PsiClassifier) -> None:
    phi, m, L = queries(100)
    ones = torch.ones_like(phi)
    assert torch.equal(psi(ones, m, L), psi.psi_run.predict_proba(torch.stack([m, L], 1)))
    assert psi(phi[:0], m[:0], L[:0]).shape == (0,)


def test_save_load_round_trip(psi: PsiClassifier, tmp_path: Path) -> None:
    path = tmp_path / "psi.pt"
    save_psi(path, psi, {"source": "unit test", "n": 3})
    # The file is plain tensors and containers: a weights_only load must succeed.
    raw = torch.load(path, weights_only=True)
    assert raw["metadata"] == {"source": "unit test", "n": 3}
    loaded, meta = load_psi(path)
    assert meta == {"source": "unit test", "n": 3}
    phi, m, L = queries(5000, seed=11)
    for value in (0, 1):
        rows = torch.full_like(phi, value)
        assert torch.equal(loaded(rows, m, L), psi(rows, m, L))
    assert loaded.domain == psi.domain
    assert loaded.psi_run.history == psi.psi_run.history
    assert loaded.psi_run.validation == psi.psi_run.validation
    assert loaded.psi_tumble.settings == psi.psi_tumble.settings


def test_round_trip_with_other_settings(tmp_path: Path) -> None:
    # Matern kernel, no ARD, fixed inducing points, natural gradients: all must be rebuilt.
    settings = GPSettings(
        kernel="matern32",
        ard=False,
        n_inducing=6,
        learn_inducing=False,
        natural_gradient=True,
        epochs=2,
        batch_size=200,
    )
    d = transitions(600, seed=2)
    psi = fit_psi(d, settings, progress=False)
    save_psi(tmp_path / "p.pt", psi, {})
    loaded, _ = load_psi(tmp_path / "p.pt")
    phi, m, L = queries(777)
    assert torch.equal(loaded(phi, m, L), psi(phi, m, L))


def test_load_rejects_other_files(tmp_path: Path) -> None:
    torch.save({"something": torch.zeros(3)}, tmp_path / "other.pt")
    with pytest.raises(ArtefactError, match="psi"):
        load_psi(tmp_path / "other.pt")
    (tmp_path / "broken.pt").write_bytes(b"not a torch file")
    with pytest.raises(ArtefactError):
        load_psi(tmp_path / "broken.pt")


def test_classifiers_on_different_devices_rejected(psi: PsiClassifier) -> None:
    meta = torch.device("meta")
    other = fit_classifier(
        torch.rand(100, 2), torch.bernoulli(torch.full((100,), 0.5)), TINY, progress=False
    )
    other.to(meta)
    with pytest.raises(ValueError, match="device"):
        PsiClassifier(psi.psi_tumble, other)


def test_missing_columns() -> None:
    with pytest.raises(ArtefactError, match="phi_next"):
        fit_psi(pd.DataFrame({"m": [1.0], "L": [0.0], "phi": [1]}), TINY, progress=False)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_round_trip(psi: PsiClassifier, tmp_path: Path) -> None:
    save_psi(tmp_path / "p.pt", psi, {})
    gpu, _ = load_psi(tmp_path / "p.pt", device="cuda")
    phi, m, L = queries(10_000)
    out = gpu(phi.cuda(), m.cuda(), L.cuda())
    assert out.device.type == "cuda" and out.dtype == torch.float32
    # cuBLAS and the CPU BLAS round differently: agreement to float32 rounding, not bitwise.
    torch.testing.assert_close(out.cpu(), psi(phi, m, L), atol=1e-5, rtol=0)


def test_grid_frame_and_figure(psi: PsiClassifier, data: pd.DataFrame, tmp_path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import numpy as np
    from matplotlib.collections import PathCollection

    from surrogate.gp import plot_psi_surfaces, plot_training_history, psi_grid_frame
    from surrogate.io import save_figure

    frame = psi_grid_frame(psi, (1.0, 3.5), (0.0, 0.1), size=(7, 5))
    assert list(frame.columns) == ["phi", "m", "L", "p"]
    assert len(frame) == 2 * 7 * 5
    assert sorted(frame["phi"].unique()) == [0, 1]
    for value in (0, 1):
        rows = frame[frame["phi"] == value]
        m = torch.tensor(rows["m"].to_numpy(), dtype=torch.float32)
        L = torch.tensor(rows["L"].to_numpy(), dtype=torch.float32)
        expected = psi(torch.full_like(m, value, dtype=torch.long), m, L).double().numpy()
        np.testing.assert_array_equal(rows["p"].to_numpy(), expected)

    L_curve = np.linspace(0, 0.1, 20)
    fig = plot_psi_surfaces(psi, data, (1.0, 3.5), (0.0, 0.1), (L_curve, 2.2 + 10 * L_curve))
    titles = [ax.get_title() for ax in fig.axes]
    assert any("RUN" in t for t in titles) and any("TUMBLE" in t for t in titles)
    # Points are subsampled to <= 2,000 per panel (two scatter collections: next RUN / TUMBLE).
    big = transitions(5000, seed=3)
    fig2 = plot_psi_surfaces(psi, big, (1.0, 3.5), (0.0, 0.1))
    for ax in fig2.axes[:2]:
        scattered = [c for c in ax.collections if isinstance(c, PathCollection)]
        assert sum(len(c.get_offsets()) for c in scattered) == 2000  # ~2,500 rows per phi
    save_figure(tmp_path / "psi.png", fig)
    save_figure(tmp_path / "hist.png", plot_training_history({"psi_1": psi.psi_run.history}))
    assert (tmp_path / "psi.png").stat().st_size > 0
