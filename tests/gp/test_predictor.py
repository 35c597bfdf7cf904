"""PsiClassifier: routing by phi, chunking, large batches, export and save/load."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch
from torch import Tensor

from surrogate.errors import ArtefactError, NumericalError
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
INPUTS = ("m", "L")
LUMPS = ("tumble", "run")


pytestmark = pytest.mark.usefixtures("one_torch_thread")


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
    return fit_psi(data, INPUTS, TINY, progress=False, lump_names=LUMPS)


def queries(n: int, seed: int = 5) -> tuple[Tensor, Tensor]:
    """(phi, z) with z = (m, L) columns in the order of the classifier's input names."""
    gen = torch.Generator().manual_seed(seed)
    phi = torch.randint(0, 2, (n,), generator=gen)
    m = 1.0 + 2.5 * torch.rand(n, generator=gen)
    L = 0.1 * torch.rand(n, generator=gen)
    return phi, torch.stack([m, L], 1)


def test_fit_psi_splits_by_origin(psi: PsiClassifier, data: pd.DataFrame) -> None:
    n_zero = int((data["phi"] == 0).sum())
    assert psi.psi_0.n_train + psi.psi_0.n_val == n_zero
    assert psi.psi_1.n_train + psi.psi_1.n_val == len(data) - n_zero
    assert psi.classifiers == (psi.psi_0, psi.psi_1)
    assert psi.input_names == INPUTS and psi.lump_names == LUMPS
    assert psi.domain == data_domain(data, INPUTS)
    assert psi.domain["m"] == (float(data["m"].min()), float(data["m"].max()))
    assert set(psi.domain) == {"m", "L"}  # phi and phi_next are labels, not inputs


def test_routing_by_phi(psi: PsiClassifier) -> None:
    phi, x = queries(3000)
    out = psi(phi, x)
    one = phi == 1
    # Each row must come from its own classifier, bit for bit.
    assert torch.equal(out[one], psi.psi_1.predict_proba(x[one]))
    assert torch.equal(out[~one], psi.psi_0.predict_proba(x[~one]))
    assert torch.equal(psi.evaluate(phi, x), out)
    # And the two classifiers really differ here (else the check above could not fail):
    # the phi = 0 surface is capped at 0.3, the phi = 1 surface reaches 0.95.
    assert (psi.psi_1.predict_proba(x) - psi.psi_0.predict_proba(x)).abs().max() > 0.3


def test_input_columns_are_in_declared_order(data: pd.DataFrame) -> None:
    """A classifier declared over (L, m) takes z in that order and learns the same surface."""
    swapped = fit_psi(data, ("L", "m"), TINY, progress=False)
    assert swapped.input_names == ("L", "m")
    phi, x = queries(2000)
    reference = fit_psi(data, INPUTS, TINY, progress=False)
    # same data and seed, columns permuted: equal up to float32 round-off in the kernel sums
    torch.testing.assert_close(swapped(phi, x.flip(1)), reference(phi, x), atol=1e-4, rtol=0)
    # while feeding the wrong order gives another function
    assert (swapped(phi, x) - reference(phi, x)).abs().max() > 0.1


def test_bool_and_int_phi_agree(psi: PsiClassifier) -> None:
    phi, x = queries(500)
    assert torch.equal(psi(phi, x), psi(phi.bool(), x))


def test_input_checks(psi: PsiClassifier) -> None:
    phi, x = queries(50)
    with pytest.raises(ValueError, match="input column"):
        psi(phi, x[:, :1])
    with pytest.raises(ValueError, match="input column"):
        psi(phi, torch.cat([x, x], 1))
    with pytest.raises(ValueError, match="rows"):
        psi(phi[:10], x)
    bad = x.clone()
    bad[4, 1] = float("inf")
    with pytest.raises(NumericalError, match="NaN or infinite"):
        psi(phi, bad)
    assert bool(torch.isfinite(psi.evaluate(phi, bad)[:4]).all())  # unchecked: no raise


@pytest.mark.parametrize("chunk", [1, 7, 64, 100, 1000])
def test_chunking_is_exact(psi: PsiClassifier, chunk: int) -> None:
    phi, x = queries(2345)
    whole = psi(phi, x)
    psi.chunk_size = chunk
    try:
        chunked = psi(phi, x)
    finally:
        psi.chunk_size = 65_536
    assert torch.equal(chunked, whole)
    # A row's value does not depend on which other rows share the call.
    assert torch.equal(psi(phi[100:117], x[100:117]), whole[100:117])


def test_million_queries(psi: PsiClassifier) -> None:
    phi, x = queries(1_000_000, seed=9)
    out = psi(phi, x.double())
    assert out.dtype == torch.float32
    assert out.shape == (1_000_000,)
    assert out.device == x.device
    assert bool(((out >= 0) & (out <= 1)).all())
    assert torch.equal(out[-50:], psi(phi[-50:], x[-50:]))


def test_single_phi_batch(psi: PsiClassifier) -> None:
    phi, x = queries(100)
    ones = torch.ones_like(phi)
    assert torch.equal(psi(ones, x), psi.psi_1.predict_proba(x))
    zeros = torch.zeros_like(phi)
    assert torch.equal(psi(zeros, x), psi.psi_0.predict_proba(x))


def test_empty_batch(psi: PsiClassifier) -> None:
    phi, x = queries(100)
    assert psi(phi[:0], x[:0]).shape == (0,)


def test_save_load_round_trip(psi: PsiClassifier, tmp_path: Path) -> None:
    path = tmp_path / "psi.pt"
    save_psi(path, psi, {"source": "unit test", "n": 3})
    # The file is plain tensors and containers: a weights_only load must succeed.
    raw = torch.load(path, weights_only=True)
    assert raw["metadata"] == {"source": "unit test", "n": 3}
    loaded, meta = load_psi(path)
    assert meta == {"source": "unit test", "n": 3}
    phi, x = queries(5000, seed=11)
    for value in (0, 1):
        rows = torch.full_like(phi, value)
        assert torch.equal(loaded(rows, x), psi(rows, x))
    assert loaded.domain == psi.domain
    assert loaded.input_names == INPUTS and loaded.lump_names == LUMPS
    assert loaded.psi_1.history == psi.psi_1.history
    assert loaded.psi_1.validation == psi.psi_1.validation
    assert loaded.psi_0.settings == psi.psi_0.settings
    state = raw["psi"]
    assert state["format"] == "surrogate.gp.psi/2"
    assert state["input_names"] == list(INPUTS) and state["lump_names"] == list(LUMPS)


def test_state_format_is_checked(psi: PsiClassifier) -> None:
    state = psi.to_state()
    with pytest.raises(ArtefactError, match="psi/2"):  # the old (m, L)-only format
        PsiClassifier.from_state({**state, "format": "surrogate.gp.psi/1"})
    with pytest.raises(ArtefactError, match="incomplete"):
        PsiClassifier.from_state({k: v for k, v in state.items() if k != "input_names"})


def test_round_trip_with_other_settings(tmp_path: Path) -> None:
    # Matern kernel, no ARD, fixed inducing points, natural gradients, a linear mean: all rebuilt.
    settings = GPSettings(
        kernel="matern32",
        ard=False,
        n_inducing=6,
        learn_inducing=False,
        natural_gradient=True,
        epochs=2,
        batch_size=200,
        mean="linear",
    )
    d = transitions(600, seed=2)
    psi = fit_psi(d, INPUTS, settings, progress=False)
    save_psi(tmp_path / "p.pt", psi, {})
    loaded, _ = load_psi(tmp_path / "p.pt")
    phi, x = queries(777)
    assert torch.equal(loaded(phi, x), psi(phi, x))
    assert loaded.lump_names == ("0", "1")  # the default when none are given


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
        PsiClassifier(psi.psi_0, other, INPUTS)


def test_missing_columns() -> None:
    with pytest.raises(ArtefactError, match="phi_next"):
        fit_psi(pd.DataFrame({"m": [1.0], "L": [0.0], "phi": [1]}), INPUTS, TINY, progress=False)
    # a declared input the table lacks is named
    with pytest.raises(ArtefactError, match="dG"):
        fit_psi(transitions(100, seed=1), ("dG",), TINY, progress=False)


def test_no_rows_of_one_origin() -> None:
    d = transitions(300, seed=4)
    with pytest.raises(ArtefactError, match="phi == 0"):
        fit_psi(d[d["phi"] == 1], INPUTS, TINY, progress=False)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_round_trip(psi: PsiClassifier, tmp_path: Path) -> None:
    save_psi(tmp_path / "p.pt", psi, {})
    gpu, _ = load_psi(tmp_path / "p.pt", device="cuda")
    phi, x = queries(10_000)
    out = gpu(phi.cuda(), x.cuda())
    assert out.device.type == "cuda" and out.dtype == torch.float32
    # cuBLAS and the CPU BLAS round differently: agreement to float32 rounding, not bitwise.
    torch.testing.assert_close(out.cpu(), psi(phi, x), atol=1e-5, rtol=0)


# ----------------------------------------------------------------------------------------------
# figures and tables


def test_grid_frame_and_figure(psi: PsiClassifier, data: pd.DataFrame, tmp_path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import numpy as np
    from matplotlib.collections import PathCollection

    from surrogate.gp import plot_psi, plot_training_history, psi_grid_frame
    from surrogate.io import save_figure

    domain = {"m": (1.0, 3.5), "L": (0.0, 0.1)}
    frame = psi_grid_frame(psi, domain, INPUTS, size=(7, 5))
    assert list(frame.columns) == ["phi", "m", "L", "p"]
    assert len(frame) == 2 * 7 * 5
    assert sorted(frame["phi"].unique()) == [0, 1]
    np.testing.assert_allclose(np.unique(frame["m"]), np.linspace(1.0, 3.5, 7))
    np.testing.assert_allclose(np.unique(frame["L"]), np.linspace(0.0, 0.1, 5))
    for value in (0, 1):
        rows = frame[frame["phi"] == value]
        z = torch.tensor(rows[["m", "L"]].to_numpy(), dtype=torch.float32)
        expected = psi(torch.full((len(rows),), value, dtype=torch.long), z).double().numpy()
        np.testing.assert_array_equal(rows["p"].to_numpy(), expected)
    assert len(psi_grid_frame(psi, domain, INPUTS)) == 2 * 50 * 50  # default size

    L_curve = np.linspace(0, 0.1, 20)
    fig = plot_psi(psi, domain, INPUTS, data, lump_names=LUMPS, guide=(2.2 + 10 * L_curve, L_curve))
    assert len(fig.axes) == 3  # two panels and the colour bar
    titles = [ax.get_title() for ax in fig.axes[:2]]
    assert titles == ["current phi = run", "current phi = tumble"]
    # the guide is drawn with the second input across: x = L, y = m
    (guide,) = [line for line in fig.axes[0].get_lines() if line.get_label() == "steady state"]
    np.testing.assert_allclose(guide.get_xdata(), L_curve)
    np.testing.assert_allclose(guide.get_ydata(), 2.2 + 10 * L_curve)
    assert fig.axes[0].get_xlim() == domain["L"] and fig.axes[0].get_ylim() == domain["m"]
    # Points are subsampled to <= 2,000 per panel (two scatter collections: next 1 / next 0).
    big = transitions(5000, seed=3)
    fig2 = plot_psi(psi, domain, INPUTS, big, lump_names=LUMPS)
    for ax in fig2.axes[:2]:
        scattered = [c for c in ax.collections if isinstance(c, PathCollection)]
        assert len(scattered) == 2
        assert sum(len(c.get_offsets()) for c in scattered) == 2000  # ~2,500 rows per phi
    save_figure(tmp_path / "psi.png", fig)
    hist = plot_training_history({"psi_0": psi.psi_0.history, "psi_1": psi.psi_1.history})
    lines = hist.axes[0].get_lines()
    assert [line.get_label() for line in lines] == ["psi_0", "psi_1"]
    np.testing.assert_array_equal(lines[1].get_ydata(), psi.psi_1.history)
    # beside it, each loss above its lowest on a log axis (zero, its lowest point, left out)
    gap = hist.axes[1]
    assert gap.get_yscale() == "log"
    above = np.asarray(psi.psi_1.history) - min(psi.psi_1.history)
    np.testing.assert_allclose(gap.get_lines()[1].get_ydata(),
                               np.where(above > 0, above, np.nan))  # fmt: skip
    save_figure(tmp_path / "hist.png", hist)
    assert (tmp_path / "psi.png").stat().st_size > 0


# ----------------------------------------------------------------------------------------------
# one input and three inputs


def transitions_1d(n: int, seed: int) -> pd.DataFrame:
    """Transitions over one signal column dG: leaving phi = 0 gets likelier with dG, leaving
    phi = 1 rarer."""
    gen = torch.Generator().manual_seed(seed)
    dg = -2.0 + 4.0 * torch.rand(n, generator=gen, dtype=torch.float64)
    phi = torch.randint(0, 2, (n,), generator=gen)
    s = torch.sigmoid(dg / 0.4)
    p_one = torch.where(phi == 1, 0.5 + 0.45 * s, 0.4 * s)
    nxt = torch.bernoulli(p_one, generator=gen).long()
    return pd.DataFrame({"dG": dg, "phi": phi, "phi_next": nxt})


@pytest.fixture(scope="module")
def data_1d() -> pd.DataFrame:
    return transitions_1d(1500, seed=6)


@pytest.fixture(scope="module")
def psi_1d(data_1d: pd.DataFrame) -> PsiClassifier:
    return fit_psi(data_1d, ("dG",), TINY, progress=False, lump_names=LUMPS)


def test_one_input_classifier(psi_1d: PsiClassifier, data_1d: pd.DataFrame) -> None:
    assert psi_1d.input_names == ("dG",) and set(psi_1d.domain) == {"dG"}
    z = torch.linspace(-2.0, 2.0, 401)
    phi = torch.arange(401) % 2
    out = psi_1d(phi, z[:, None])
    assert torch.equal(psi_1d(phi, z), out)  # a flat vector is one column
    one = phi == 1
    assert torch.equal(out[one], psi_1d.psi_1.predict_proba(z[one, None]))
    assert torch.equal(out[~one], psi_1d.psi_0.predict_proba(z[~one, None]))
    # the two classifiers really differ (true p(1 | 1) - p(1 | 0) >= 0.5 everywhere), so the
    # routing checks above could fail
    gap = psi_1d.psi_1.predict_proba(z[:, None]) - psi_1d.psi_0.predict_proba(z[:, None])
    assert gap.mean() > 0.3


def test_binned_frequencies_by_hand() -> None:
    import numpy as np

    from surrogate.gp import binned_frequencies

    d = pd.DataFrame(
        {
            "x": [0.0, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0, 8.0, 9.0, 0.5, 8.5],
            "phi": [0] * 10 + [1, 1],  # the phi = 1 rows must be ignored
            "phi_next": [1, 0, 0, 0, 0, 1, 1, 1, 0, 1, 1, 1],
        }
    )
    centre, freq, se = binned_frequencies(d, "x", phi=0, bins=2)
    # equal-count bins: x in [0, 4.5) and [4.5, 9]
    np.testing.assert_allclose(centre, [2.0, 7.0])
    np.testing.assert_allclose(freq, [0.2, 0.8])
    np.testing.assert_allclose(se, np.sqrt([0.2 * 0.8 / 5, 0.8 * 0.2 / 5]))
    for arr in binned_frequencies(d[d["phi"] == 1], "x", phi=0):
        assert arr.size == 0


def test_one_input_grid_frame_and_curves(
    psi_1d: PsiClassifier, data_1d: pd.DataFrame, tmp_path: Path
) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import numpy as np

    from surrogate.gp import binned_frequencies, plot_psi, psi_grid_frame
    from surrogate.io import save_figure

    domain = {"dG": (-2.0, 2.0)}
    frame = psi_grid_frame(psi_1d, domain, ["dG"])
    assert list(frame.columns) == ["phi", "dG", "p"]
    assert len(frame) == 2 * 200  # default: 200 nodes for one input
    rows = frame[frame["phi"] == 1]
    z = torch.tensor(rows["dG"].to_numpy(), dtype=torch.float32)
    np.testing.assert_array_equal(
        rows["p"].to_numpy(), psi_1d(torch.ones(len(rows), dtype=torch.long), z).double().numpy()
    )

    def exact(x: np.ndarray) -> np.ndarray:
        s = 1.0 / (1.0 + np.exp(-x / 0.4))
        return np.stack([0.4 * s, 0.5 + 0.45 * s], 1)

    fig = plot_psi(psi_1d, domain, ["dG"], data_1d, lump_names=LUMPS, exact=exact)
    assert len(fig.axes) == 2  # one panel per origin state, no colour bar
    assert [ax.get_title() for ax in fig.axes] == ["from tumble (phi = 0)", "from run (phi = 1)"]
    for phi, ax in enumerate(fig.axes):
        learned, reference = ax.get_lines()[:2]
        x = np.asarray(learned.get_xdata())
        assert x[0] == -2.0 and x[-1] == 2.0
        p = psi_1d(torch.full((len(x),), phi), torch.tensor(x, dtype=torch.float32))
        p = p.double().numpy()
        # the probability of LEAVING the origin state: p(1 | 0) from 0, 1 - p(1 | 1) from 1
        np.testing.assert_allclose(learned.get_ydata(), p if phi == 0 else 1.0 - p)
        ref = exact(x)[:, phi]
        np.testing.assert_allclose(reference.get_ydata(), ref if phi == 0 else 1.0 - ref)
        assert "leave " + LUMPS[phi] in ax.get_ylabel()
        # the binned data points (an errorbar container)
        centre, freq, _ = binned_frequencies(data_1d, "dG", phi)
        (bars,) = ax.containers
        np.testing.assert_allclose(bars.lines[0].get_xdata(), centre)
        np.testing.assert_allclose(bars.lines[0].get_ydata(), freq if phi == 0 else 1.0 - freq)
    assert save_figure(tmp_path / "psi1.png", fig).stat().st_size > 0


def test_three_input_classifier(tmp_path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")

    from surrogate.gp import plot_psi, psi_grid_frame

    base = transitions(900, seed=7)
    gen = torch.Generator().manual_seed(8)
    data = base.assign(noise=torch.rand(len(base), generator=gen, dtype=torch.float64).numpy())
    names = ("m", "noise", "L")  # declared order, not the table's column order
    psi = fit_psi(data, names, TINY, progress=False)
    assert psi.input_names == names and psi.psi_1.normaliser.mean.shape == (3,)
    phi, x = queries(500)
    z = torch.stack([x[:, 0], torch.rand(500, generator=gen), x[:, 1]], 1)
    out = psi(phi, z)
    one = phi == 1
    assert torch.equal(out[one], psi.psi_1.predict_proba(z[one]))
    assert torch.equal(out[~one], psi.psi_0.predict_proba(z[~one]))
    save_psi(tmp_path / "p3.pt", psi, {})
    loaded, _ = load_psi(tmp_path / "p3.pt")
    assert loaded.input_names == names and torch.equal(loaded(phi, z), out)

    domain = data_domain(data, names)
    frame = psi_grid_frame(psi, domain, names, size=(3, 4, 5))
    assert list(frame.columns) == ["phi", "m", "noise", "L", "p"] and len(frame) == 2 * 60
    fig = plot_psi(psi, domain, names, data)  # first two inputs, the third at its midpoint
    assert len(fig.axes) == 3


def test_moving_a_classifier_drops_gpytorch_s_memoised_terms(psi: PsiClassifier) -> None:
    """``Module.to`` does not move GPyTorch's memoised predictive terms (plain attributes): a
    fit on CUDA moved to the CPU then solved against a CUDA Cholesky factor (train's psi grid
    failed on an H200). Moving drops them; predictions are unchanged."""
    z = torch.tensor([[0.5, 1.0], [1.5, 0.2]])
    phi = torch.tensor([0, 1])
    before = psi(phi, z)
    strategy = psi.psi_0.model.variational_strategy
    assert getattr(strategy, "_memoize_cache", {})  # predicting filled it
    psi.to("cpu")
    assert not getattr(strategy, "_memoize_cache", {})
    torch.testing.assert_close(psi(phi, z), before)


def test_log_warp_reads_an_input_on_a_log_axis(data: pd.DataFrame, tmp_path: Path) -> None:
    """A warped input is fitted, binned and evaluated as log(1 + value / knee): the same fit as
    one on the warped column itself, on raw values; it survives a save and the cached form."""
    from surrogate.gp.fast import CachedPsi
    from surrogate.gp.predictor import log_warp

    settings = GPSettings(n_inducing=10, epochs=3, bins=20, seed=3)
    torch.manual_seed(0)
    warped = fit_psi(data, INPUTS, settings, progress=False, warps={"m": 2.0})
    by_hand = data.assign(m=torch.log1p(torch.tensor(data["m"].to_numpy()) / 2.0).numpy())
    torch.manual_seed(0)
    plain = fit_psi(by_hand, INPUTS, settings, progress=False)
    phi, z = queries(500)
    expected = plain(phi, log_warp(z, INPUTS, {"m": 2.0}))
    torch.testing.assert_close(warped(phi, z), expected)
    assert warped.domain["m"] == pytest.approx((data["m"].min(), data["m"].max()))  # raw
    cached = CachedPsi.from_classifier(warped)
    torch.testing.assert_close(cached(phi, z), expected, atol=2e-6, rtol=0)
    torch.testing.assert_close(cached.tabulate(phi, z), expected, atol=2e-6, rtol=0)
    save_psi(tmp_path / "psi.pt", warped, {})
    again, _ = load_psi(tmp_path / "psi.pt")
    assert again.warps == {"m": 2.0}
    torch.testing.assert_close(again(phi, z), expected)
    z0 = z.clone()
    z0[:, 0] = 0.0
    assert torch.equal(log_warp(z0, INPUTS, {"m": 2.0})[:, 0], torch.zeros(z.shape[0]))
    with pytest.raises(ValueError, match="warps"):
        PsiClassifier(warped.psi_0, warped.psi_1, INPUTS, warps={"age": 1.0})
    with pytest.raises(ValueError, match="knees > 0"):
        PsiClassifier(warped.psi_0, warped.psi_1, INPUTS, warps={"m": 0.0})


def test_the_last_tenth_drop_says_whether_the_loss_has_flattened() -> None:
    """The loss's fall over the last tenth of its steps: 0 where flat, the fall where still
    falling, None where there are too few steps to say."""
    from surrogate.gp import last_tenth_drop

    assert last_tenth_drop([1.0] * 20) == 0.0
    assert last_tenth_drop(list(np.linspace(1.0, 0.0, 101))) == pytest.approx(0.1)
    assert last_tenth_drop([1.0, 0.5]) is None
