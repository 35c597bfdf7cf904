"""The after-jump lag of a collection (surrogate/diagnosis/jumps.py): a synthetic table whose
rows switch faster soon after a jump is flagged, with its ratio; one without a lag is not."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from surrogate.diagnosis.jumps import (
    BLACKOUT_SHARE,
    SETTLED_AFTER,
    after_jump_lag,
    blackout_advice,
    lag_message,
    lagging_window,
    outlasts,
    settled_rows,
)

DT = 0.05


def table(early_factor: float, n: int = 200_000, seed: int = 0) -> pd.DataFrame:
    """Rows at inputs x in [0, 1], switching at 0.05 + 0.1 x per window, times
    ``early_factor`` within 2 s of a jump; a tenth never perturbed (since_jump -1)."""
    rng = np.random.default_rng(seed)
    x = rng.random(n)
    since = rng.integers(0, int(40 / DT), n)
    since[rng.random(n) < 0.1] = -1
    rate = (0.05 + 0.1 * x) * np.where((since >= 0) & (since * DT < 2.0), early_factor, 1.0)
    phi = rng.integers(0, 2, n)
    switched = rng.random(n) < rate
    return pd.DataFrame({"x": x, "phi": phi, "phi_next": np.where(switched, 1 - phi, phi),
                         "since_jump": since})  # fmt: skip


def test_rows_that_switch_faster_after_a_jump_are_flagged_with_their_ratio() -> None:
    lag = after_jump_lag(table(1.5), ["x"], DT, ("off", "on"))
    assert lag is not None and lag["settled_after_s"] == SETTLED_AFTER
    for lump in ("off", "on"):
        first = lag["origins"][lump][0]
        assert (first["from_s"], first["to_s"]) == (0.0, 2.0)
        # 1.5x, within 4 standard errors of the ratio (~0.03 here)
        assert abs(first["ratio"] - 1.5) < 4 * first["se"]
        later = lag["origins"][lump][1:]
        assert all(abs(b["ratio"] - 1.0) < 4 * b["se"] for b in later)
    assert {(lump, lo) for lump, lo, _, _ in lag["lagging"]} == {("off", 0.0), ("on", 0.0)}
    message = lag_message(lag, 1.0)
    assert message is not None and "collect.blackout_time=1 s" in message
    assert "off 1.5" in message or "off 1.4" in message or "off 1.6" in message


def test_a_lag_in_the_clocks_alone_is_flagged_without_the_clock() -> None:
    """Rows switch at a rate set by their clock alone (fast in the first 0.5 s of a segment),
    and rows 0-2 s after a jump carry old clocks (no young ones): at the same clock they switch
    as settled rows do, so the clock's view sees nothing; at the same inputs alone they switch
    slower, which the two-state psi learns. Flagged as lagging without the clock."""
    rng = np.random.default_rng(1)
    n = 200_000
    x = rng.random(n)
    since = rng.integers(0, int(40 / DT), n)
    early = since * DT < 2.0
    age = np.where(early, rng.uniform(0.5, 10.0, n), rng.uniform(0.0, 10.0, n))
    rate = np.where(age < 0.5, 0.3, 0.03)
    phi = rng.integers(0, 2, n)
    switched = rng.random(n) < rate
    rows = pd.DataFrame({"x": x, "phi": phi, "phi_next": np.where(switched, 1 - phi, phi),
                         "since_jump": since, "phi_age": age})  # fmt: skip
    lag = after_jump_lag(rows, ["x"], DT, ("off", "on"))
    assert lag is not None
    assert all(abs(b["ratio"] - 1.0) < 4 * b["se"] for bins in lag["origins"].values()
               for b in bins)  # fmt: skip
    # expected 0.03 against the settled mix 0.05 x 0.3 + 0.95 x 0.03 = 0.0435: 0.69x
    first = lag["origins_without_clock"]["on"][0]
    assert abs(first["ratio"] - 0.03 / 0.0435) < 4 * first["se"]
    assert {(lump, lo) for lump, lo, _, _ in lag["lagging"]} == {
        ("off (without the clock)", 0.0),
        ("on (without the clock)", 0.0),
    }
    advice = blackout_advice(lag, 1.0, 0.1)
    assert advice[0] == f"collect.blackout_time={SETTLED_AFTER:g}"
    message = lag_message(lag, 1.0, advice)
    assert message is not None and "on (without the clock) 0." in message


def test_a_lag_through_the_last_bin_gets_no_blackout() -> None:
    """Rows lag by the same factor in every bin up to 20 s after a jump (a hidden state slower
    than that, as the auto-regulatory network's protein count): the rows counted as settled
    lag too, so no blackout this measurement can name is advised, and the message says why;
    a lag in the first bins only is still advised its blackout."""
    rng = np.random.default_rng(2)
    n = 200_000
    x = rng.random(n)
    since = rng.integers(0, int(40 / DT), n)
    since[rng.random(n) < 0.1] = -1
    within = (since >= 0) & (since * DT < SETTLED_AFTER)
    rate = (0.05 + 0.1 * x) * np.where(within, 0.8, 1.0)
    phi = rng.integers(0, 2, n)
    switched = rng.random(n) < rate
    rows = pd.DataFrame({"x": x, "phi": phi, "phi_next": np.where(switched, 1 - phi, phi),
                         "since_jump": since})  # fmt: skip
    lag = after_jump_lag(rows, ["x"], DT, ("off", "on"))
    assert lag is not None and outlasts(lag)
    assert {hi for _, _, hi, _ in lag["lagging"]} >= {SETTLED_AFTER}
    assert blackout_advice(lag, 1.0, 0.1) == ()
    message = lag_message(lag, 1.0)
    assert message is not None and "lasts through the last bin" in message
    assert lagging_window(lag) is None and "gp.jump_rows" not in message  # train keeps all
    early = after_jump_lag(table(1.5), ["x"], DT, ("off", "on"))
    assert early is not None and not outlasts(early) and blackout_advice(early, 1.0, 0.1)


def test_a_collection_without_a_lag_says_nothing() -> None:
    lag = after_jump_lag(table(1.0), ["x"], DT, ("off", "on"))
    assert lag is not None and lag["lagging"] == []
    assert lag_message(lag, 1.0) is None


@pytest.mark.parametrize("drop", ["since_jump", "rows"])
def test_nothing_is_measured_without_jumps_or_settled_rows(drop: str) -> None:
    rows = table(1.0, n=5_000)
    if drop == "since_jump":
        rows = rows.drop(columns="since_jump")
    else:  # every row within 20 s of a jump: no settled reference
        rows = rows.assign(since_jump=np.minimum(rows["since_jump"].clip(lower=0), 10))
    assert after_jump_lag(rows, ["x"], DT, ("off", "on")) is None


def test_the_advised_blackout_ends_where_rows_count_as_settled() -> None:
    """Rows lag 0-2 s after a jump: the advice is a blackout until rows count as settled
    (20 s) and one jump per 40 s (BLACKOUT_SHARE of the time blacked out); a rate already that
    low is left; a blackout already that long, or no lag, asks for nothing."""
    lag = after_jump_lag(table(1.5), ["x"], DT, ("off", "on"))
    assert lag is not None
    advice = blackout_advice(lag, 1.0, 0.1)
    assert advice == (f"collect.blackout_time={SETTLED_AFTER:g}",
                      f"collect.perturb_rate={BLACKOUT_SHARE / SETTLED_AFTER:g}")  # fmt: skip
    message = lag_message(lag, 1.0, advice)
    assert message is not None and f"`{' '.join(advice)}`" in message
    assert blackout_advice(lag, 1.0, 0.01) == (f"collect.blackout_time={SETTLED_AFTER:g}",)
    assert blackout_advice(lag, SETTLED_AFTER, 0.01) == ()
    assert blackout_advice({**lag, "lagging": []}, 1.0, 0.1) == ()
    assert blackout_advice(None, 1.0, 0.1) == ()
    refused = lag_message(lag, 1.0, (), "collect.blackout_time must be >= 0")
    assert refused is not None and "refused: collect.blackout_time must be >= 0" in refused


def test_train_leaves_out_the_rows_of_a_lag_that_ends_within_the_measurement() -> None:
    """The window train leaves out (gp.jump_rows=auto) is the settled rows' 20 s where rows
    lag in the first bins only; none where nothing lags or the lag outlasts the bins; the rows
    kept are those 20 s or more after a jump and those before the first; collect's warning
    says train leaves them out, and that psi learns the lag only where it does not."""
    early = after_jump_lag(table(1.5), ["x"], DT, ("off", "on"))
    assert early is not None and lagging_window(early) == SETTLED_AFTER
    assert lagging_window(after_jump_lag(table(1.0), ["x"], DT, ("off", "on"))) is None
    assert lagging_window(None) is None
    kept = settled_rows(np.array([-1, 0, 399, 400, 1000]), DT, SETTLED_AFTER)
    assert kept.tolist() == [True, False, False, True, True]
    message = lag_message(early, 1.0, blackout_advice(early, 1.0, 0.1))
    assert message is not None and "gp.jump_rows=auto" in message
    assert "psi learns that lag" not in message and "more of them" in message


def test_rows_that_keep_every_switch_measure_the_lag_weighted() -> None:
    """On every switch and a tenth of the held rows (collect.keep_switches), each weighted by
    the windows it stands for, the first 2 s read 1.5x within 4 standard errors, as the whole
    table does; read unweighted the same rows would say ~1.2x."""
    from surrogate.gp.windows import WINDOWS

    full = table(1.5, n=1_000_000)
    switched = (full["phi"] != full["phi_next"]).to_numpy()
    keep = switched | (np.random.default_rng(1).random(len(full)) < 0.1)
    rows = full[keep].assign(**{WINDOWS: np.where(switched[keep], 1.0, 10.0)})
    for name, lag in (("weighted", after_jump_lag(rows, ["x"], DT, ("off", "on"))),
                      ("plain", after_jump_lag(rows.drop(columns=WINDOWS), ["x"], DT,
                                               ("off", "on")))):  # fmt: skip
        assert lag is not None
        for lump in ("off", "on"):
            first = lag["origins"][lump][0]
            if name == "weighted":
                assert abs(first["ratio"] - 1.5) < 4 * first["se"], first
            else:
                assert first["ratio"] < 1.5 - 8 * first["se"], first
