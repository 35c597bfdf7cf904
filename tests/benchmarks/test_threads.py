"""The busy-machine bench (surrogate/benchmarks/threads.py): its parts run; no timing asserted."""

from __future__ import annotations

import pytest

from surrogate.benchmarks.threads import busy_loops, run_bench, time_fit


def test_busy_loops_run_inside_and_are_stopped_after() -> None:
    with busy_loops(2) as procs:
        assert len(procs) == 2 and all(p.poll() is None for p in procs)
    assert all(p.poll() is not None for p in procs)


def test_an_unknown_policy_is_refused_before_any_work() -> None:
    with pytest.raises(ValueError, match="policies: unknown policy 'lazy'"):
        run_bench(policies=("passive", "lazy"))


def test_a_fit_is_timed_in_a_fresh_process() -> None:
    assert time_fit("passive", 1, steps=1, n_gps=2) > 0
