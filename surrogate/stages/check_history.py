"""A fidelity check against the previous check of the same model at the same size: whether
this one followed the advice the previous report printed, and what that did to the count of
passing checks, so a remedy that made the check worse is said to be so and not followed again.

The reproduce stage keeps the same record for its verdict (:mod:`surrogate.stages.advice`);
here the record is each check's own ``summary.json`` (its printed remedies, and ``previous``:
what this module found) beside its ``manifest.json`` (its config and count). CERENA's
gene-expression network: 20 of 24 with no gp setting, whose report printed
``++model.classes=auto collect.keep_switches=true``; followed, 17 of 24 (docs/choice.md).
"""

from __future__ import annotations

import glob
import json
import logging
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from surrogate.io import MANIFEST
from surrogate.stages.advice import applied
from surrogate.stages.artefacts import SUMMARY

log = logging.getLogger(__name__)

#: the summary keys whose overrides a report prints as remedies (a new collection or a wider
#: choice; ``draw_again``, which draws the same check again, is a diagnosis, not a remedy)
REMEDY_KEYS = ("wider_choice", "settled_collection", "wider_collection")
#: the ``fidelity`` options two checks share to be compared (the directory's name already
#: holds the model, the cells, the duration and the training seeds)
SAME_CHECK = ("fields", "duration_tolerance", "ks_max", "ks_factor", "alpha", "start",
              "equilibration_time", "train_seeds")  # fmt: skip
#: the summary's key of the comparison
PREVIOUS = "previous"


def _read(path: Path) -> dict[str, Any] | None:
    try:
        value = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    return value if isinstance(value, dict) else None


def _same_check(a: Mapping[str, Any], b: Mapping[str, Any]) -> bool:
    fa, fb = a.get("fidelity") or {}, b.get("fidelity") or {}
    return all(_canonical(fa.get(k)) == _canonical(fb.get(k)) for k in SAME_CHECK)


def _canonical(value: Any) -> str:
    # a tuple reads as the list its JSON copy holds; a value JSON cannot write, as its text
    return json.dumps(value, sort_keys=True, default=str)


def other_checks(directory: Path, config: Mapping[str, Any]) -> list[dict[str, Any]]:
    """The complete checks beside ``directory`` of the same model, size and thresholds
    (``config``'s): each its ``directory`` (a Path), ``manifest`` and ``summary``, oldest
    first (by when its manifest was written, then by name)."""
    stem = directory.name.rsplit("-", 1)[0]
    found = []
    for other in directory.parent.glob(f"{glob.escape(stem)}-*"):
        if other.resolve() == directory.resolve() or other.name.rsplit("-", 1)[0] != stem:
            continue
        try:  # a check another job is remaking may lose its manifest meanwhile: skipped
            written = (other / MANIFEST).stat().st_mtime_ns
        except OSError:
            continue
        manifest, summary = _read(other / MANIFEST), _read(other / SUMMARY)
        if manifest is None or summary is None or "passed" not in manifest:
            continue
        if not _same_check(manifest.get("config") or {}, config):
            continue
        found.append({"directory": other, "manifest": manifest, "summary": summary,
                      "written": written})  # fmt: skip
    return sorted(found, key=lambda c: (c["written"], c["directory"].name))


def printed_remedies(summary: Mapping[str, Any]) -> list[list[str]]:
    """The remedies a check's report printed (its summary's :data:`REMEDY_KEYS`)."""
    return [list(summary[k]) for k in REMEDY_KEYS if summary.get(k)]


def _share(passed: Any, checks: Any) -> float:
    return int(passed) / max(int(checks), 1)


def compare_with_previous(
    directory: Path, config: Mapping[str, Any], passed: int, checks: int
) -> dict[str, Any] | None:
    """This check (``config``, ``passed`` of ``checks``, to be written in ``directory``)
    against the previous check of the same model, size and thresholds: the newest whose
    printed advice this config followed (:func:`~surrogate.stages.advice.applied`), else the
    newest (a check that itself followed this directory's advice is later, not previous):
    its directory's name, its count, whether it ``printed`` advice, the overrides of each
    remedy this check ``followed``, and whether this check then passes a smaller share
    (``fewer``); None where there is none."""
    others = [c for c in other_checks(directory, config)
              if (c["summary"].get(PREVIOUS) or {}).get("directory") != directory.name]  # fmt: skip
    if not others:
        return None

    def followed(check: Mapping[str, Any]) -> list[list[str]]:
        before = check["manifest"].get("config") or {}
        return [r for r in printed_remedies(check["summary"]) if applied(before, config, r)]

    last, advice = next(((c, f) for c in reversed(others) if (f := followed(c))),
                        (others[-1], []))  # fmt: skip
    before = last["manifest"]
    return {"directory": last["directory"].name, "passed": int(before["passed"]),
            "checks": int(before["checks"]), "printed": bool(printed_remedies(last["summary"])),
            "followed": advice, "now": passed,
            "fewer": bool(advice) and _share(passed, checks) < _share(before["passed"],
                                                                      before["checks"])}  # fmt: skip


def tried_in_vain(directory: Path, config: Mapping[str, Any]) -> dict[str, dict[str, Any]]:
    """The remedies not to print again for a check of ``config``: each remedy (its overrides
    joined by spaces) a check of the same model, size and thresholds followed from settings
    that ``config`` would reach it from too (:func:`~surrogate.stages.advice.applied` from
    ``config`` to that check's config) and then passed a smaller share than the check whose
    advice it was, with that check's directory name and the two counts."""
    out: dict[str, dict[str, Any]] = {}
    for later in other_checks(directory, config):
        previous = later["summary"].get(PREVIOUS) or {}
        if not previous.get("fewer"):
            continue
        for remedy in previous.get("followed") or []:
            if applied(config, later["manifest"].get("config") or {}, remedy):
                out[" ".join(remedy)] = {
                    "directory": later["directory"].name,
                    "passed": int(later["manifest"]["passed"]),
                    "checks": int(later["manifest"]["checks"]),
                    "before": f"{previous['passed']} of {previous['checks']}",
                }
    return out


def describe(previous: Mapping[str, Any] | None, checks: int) -> str:
    """The report's paragraph on :func:`compare_with_previous`'s record (empty for None).

    Example:
        >>> describe({"directory": "model=m-1", "passed": 20, "checks": 24, "now": 17,
        ...           "printed": True, "followed": [["++model.classes=auto"]],
        ...           "fewer": True}, 24)[:70]
        'The previous check of this model at this size (`model=m-1`) passed 20 '
    """
    if not previous:
        return ""
    text = (f"The previous check of this model at this size (`{previous['directory']}`) passed "
            f"{previous['passed']} of {previous['checks']}")  # fmt: skip
    followed = previous.get("followed") or []
    if not followed:
        return text + ("; this one followed none of the advice it printed."
                       if previous.get("printed", True) else ".")  # fmt: skip
    advice = " and ".join(f"`{' '.join(f)}`" for f in followed)
    text += (f" and printed {advice}, which this check followed: it passes {previous['now']} "
             f"of {checks}")  # fmt: skip
    if previous.get("fewer"):
        return (text + ", fewer. Keep the previous command's settings: this advice is not "
                "printed again for this model (the previous command, run again, reuses its "
                "check and says so in its log).")  # fmt: skip
    return text + "."


def describe_not_advised(tried: Mapping[str, Mapping[str, Any]]) -> str:
    """The report's line on the remedies :func:`tried_in_vain` kept from being printed (empty
    where none)."""
    return " ".join(
        f"Not advised again: `{remedy}`, which {t['directory']} followed from settings like "
        f"these and then passed {t['passed']} of {t['checks']} (the check before it "
        f"{t['before']})." for remedy, t in tried.items())  # fmt: skip


def followed_for_worse(directory: Path, config: Mapping[str, Any]) -> list[dict[str, Any]]:
    """The later checks of the same model, size and thresholds that followed advice the check
    in ``directory`` printed and passed fewer: each its directory's name, count and advice
    (what a reused check's log says, so that its report's advice is not followed again)."""
    out = []
    for other in other_checks(directory, config):
        previous = other["summary"].get(PREVIOUS) or {}
        if previous.get("directory") == directory.name and previous.get("fewer"):
            out.append({"directory": other["directory"].name,
                        "passed": int(other["manifest"]["passed"]),
                        "checks": int(other["manifest"]["checks"]),
                        "followed": [list(f) for f in previous.get("followed") or []]})  # fmt: skip
    return out


def warn_followed_for_worse(directory: Path, config: Mapping[str, Any], passed: int) -> None:
    """Log, for a reused check, each later check that followed its advice and passed fewer."""
    for later in followed_for_worse(directory, config):
        log.warning("fidelity: this check's advice %s was followed in %s, which passed %d of %d "
                    "against this check's %d: keep this command's settings, not that advice",
                    " and ".join(f"`{' '.join(f)}`" for f in later["followed"]), later["directory"],
                    later["passed"], later["checks"], passed)  # fmt: skip


__all__ = ["PREVIOUS", "REMEDY_KEYS", "SAME_CHECK", "compare_with_previous", "describe",
           "describe_not_advised", "followed_for_worse", "other_checks", "printed_remedies",
           "tried_in_vain", "warn_followed_for_worse"]  # fmt: skip
