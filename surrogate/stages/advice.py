"""Remedies that do not loop: what the previous reproduce run of the same model advised, and
whether this run applied it without a gain (the record a report's ``verdict.json`` keeps).

The verdict itself (whether to trust an abstraction, and what to try next) is measured below
the stages, from plain values: :func:`surrogate.diagnosis.advice.verdict`.
"""

from __future__ import annotations

from collections.abc import Collection, Mapping, Sequence
from typing import Any

from surrogate.diagnosis.advice import Verdict
from surrogate.stages.advice_check import apply_overrides


def outcome(failures: Mapping[str, Sequence[str]]) -> int:
    """A run's outcome figure: its comparisons beyond the noise floor (fewer is better)."""
    return sum(len(q) for q in failures.values())


def applied(before: Mapping[str, Any], now: Mapping[str, Any], overrides: Sequence[str]) -> bool:
    """Whether the run of config ``now`` applied the remedy ``overrides`` advised to the run
    of config ``before``: every key the remedy changes moved to its value, or (a number)
    at least as far in the same direction (20 times the rows applies a remedy of 4 times)."""
    try:
        want = _flat(apply_overrides(before, overrides))
    except Exception:  # a config the overrides no longer fit: not applied
        return False
    had, got = _flat(before), _flat(now)
    changed = {k: v for k, v in want.items() if had.get(k, _ABSENT) != v}
    if not changed:
        return False
    for k, v in changed.items():
        g, h = got.get(k, _ABSENT), had.get(k, _ABSENT)
        if g == v:
            continue
        numbers = all(isinstance(x, int | float) and not isinstance(x, bool) for x in (g, h, v))
        if not (numbers and (v - h) * (g - v) >= 0 and (g - h) * (v - h) > 0):
            return False
    return True


_ABSENT = object()


def _flat(cfg: Mapping[str, Any], prefix: str = "") -> dict[str, Any]:
    out: dict[str, Any] = {}
    for k, v in cfg.items():
        if isinstance(v, Mapping) and v:
            out.update(_flat(v, f"{prefix}{k}."))
        else:
            out[f"{prefix}{k}"] = v
    return out


def tried_remedies(
    previous: Mapping[str, Any] | None,
    config: Mapping[str, Any],
    now: int,
    causes: Collection[str] | None = None,
) -> dict[str, str]:
    """The remedy kinds not to advise again: those the previous run of the model (its
    :func:`verdict_record`) advised that this run (config ``config``, outcome ``now``) applied
    without a gain, with what was measured, and those it had already set aside. A remedy whose
    cause this run no longer finds (``causes``: the names of this run's causes; None: not
    known) had its gain, whatever the outcome: a larger diagnostic population that made its
    reference judge (Vilar's oscillator: 4,300 cells, then another cause) is no remedy tried
    in vain, and set aside it left the next noisy reference nothing to advise."""
    if not previous:
        return {}
    out = dict(previous.get("tried") or {})
    before = previous["outcome"]
    for r in previous.get("remedies") or []:
        if causes is not None and r.get("cause") not in causes:
            out.pop(r["kind"], None)  # its cause went: it worked
            continue
        if r["overrides"] and applied(previous["config"], config, r["overrides"]) \
                and now >= before:  # fmt: skip
            out[r["kind"]] = (f"tried: `{' '.join(r['overrides'])}` ran and the comparisons "
                              f"beyond the noise floor went from {before} to {now}")  # fmt: skip
    return out


def verdict_record(
    v: Verdict, config: Mapping[str, Any], now: int, tried: Mapping[str, str]
) -> dict[str, Any]:
    """What the next run of the model compares with (the report's ``verdict.json``): this
    run's config, its outcome figure, the remedies advised and those set aside."""
    return {"config": dict(config), "outcome": now, "trust": v.trust, "tried": dict(tried),
            "remedies": [{"cause": c, "kind": r.kind, "overrides": list(r.overrides)}
                         for c, r in v.remedies]}  # fmt: skip


__all__ = [
    "applied",
    "outcome",
    "tried_remedies",
    "verdict_record",
]
