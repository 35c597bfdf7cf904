"""Run the SBML discrete stochastic test suite (DSMTS) and write its table into docs/sbml.md.

python scripts/dsmts.py --suite <sbml-test-suite>/cases/stochastic [--runs 10000] [--seed 1]
                        [--cases 00001 00002 ...] [--ssa compiled|batched] [--doc docs/sbml.md]

The suite: git clone https://github.com/sbmlteam/sbml-test-suite (LGPL 2.1+). Every case is
read, simulated ``--runs`` times by the compiled SSA (or the batched torch SSA) and checked with
the suite's Z and Y at its time points (surrogate/sbml/dsmts.py); a failing case is run again
with the next seed. ``--runs`` must be at least 1,000, the suite's minimum: its checks read Z
and Y against normal ranges, which fewer runs do not justify (a "passed" would mean nothing).
With ``--cases``, only those rows of the table in ``--doc`` are replaced (the summary recounted
over every row, naming the full-suite command and which rows were run again when); a table
written from a subset alone is headed by the command that ran it.
"""

from __future__ import annotations

import argparse
import re
import time
from collections.abc import Sequence
from pathlib import Path

from surrogate.sbml.dsmts import SSAS, DsmtsCase, DsmtsResult, run_case_twice

BEGIN, END = "<!-- dsmts-table: begin -->", "<!-- dsmts-table: end -->"
#: the suite's minimum number of runs per case (DSMTS user guide 3.1)
MIN_RUNS = 1000


def _row(case: DsmtsCase, r: DsmtsResult) -> str:
    if r.status == "refused":
        return f"| {case.id} | {case.synopsis} | refused | | | | | {r.reason} |"
    note = r.reason
    if r.retried is not None:
        first = r.retried
        note = (f"seed {first.seed}: {first.reason}; seed {r.seed}: "
                f"{r.reason or 'all within range'}")  # fmt: skip
    return (f"| {case.id} | {case.synopsis} | {r.status} | {r.checks} | "
            f"{r.z_outside} / {r.y_outside} | {r.max_abs_z:.2f} / {r.max_abs_y:.2f} | "
            f"{r.seconds:.1f} | {note} |")  # fmt: skip


def command(runs: int, seed: int, cases: Sequence[str] | None = None, ssa: str = "compiled") -> str:
    """The command line that runs ``cases`` (None: every case) as the table reports them."""
    subset = f" --cases {' '.join(cases)}" if cases else ""
    backend = "" if ssa == "compiled" else f" --ssa {ssa}"
    return (f"python3 scripts/dsmts.py --suite <sbml-test-suite>/cases/stochastic --runs {runs} "
            f"--seed {seed}{backend}{subset}")  # fmt: skip


def table(
    cases: list[DsmtsCase],
    results: list[DsmtsResult],
    runs: int,
    seed: int,
    ssa: str = "compiled",
    subset: Sequence[str] | None = None,
) -> str:
    """The markdown table and its summary, headed by the command that ran (``subset``: the
    ``--cases`` given, None for the whole suite)."""
    counts = {s: sum(r.status == s for r in results) for s in ("passed", "failed", "refused")}
    retried = sum(r.retried is not None for r in results)
    lines = [
        f"`{command(runs, seed, subset, ssa)}` ({time.strftime('%Y-%m-%d')}): {len(results)} cases, "
        f"**{counts['passed']} passed**, {counts['failed']} failed, {counts['refused']} "
        f"refused (the reader names the construct); {runs} runs per case, seed {seed} "
        f"({retried} case(s) run again with the next seed after a first failure).",
        "",
        "| case | synopsis | result | checks | Z / Y outside | max abs Z / Y | s | note |",
        "|---|---|---|---:|---:|---:|---:|---|",
    ]
    lines += [_row(c, r) for c, r in zip(cases, results, strict=True)]
    return "\n".join(lines)


def merge_rows(content: str, text: str, cases: list[str]) -> str:
    """The table of ``text`` (the cases run now) merged into the one in ``content``: its rows
    for ``cases`` replaced, the summary's counts recounted over every row."""
    old = content.split(BEGIN, 1)[1].split(END, 1)[0].strip().splitlines()
    new = text.splitlines()
    rows = {line.split("|")[1].strip(): line for line in old if line.startswith("| 0")}
    rows.update({line.split("|")[1].strip(): line for line in new if line.startswith("| 0")})
    merged = [rows[case] for case in sorted(rows)]
    status = [line.split("|")[3].strip() for line in merged]
    counts = {s: status.count(s) for s in ("passed", "failed", "refused")}
    retried = sum(bool(re.search(r"\| seed \d+: .*; seed \d+: ", line)) for line in merged)
    first = re.search(r"\((\d{4}-\d{2}-\d{2})[;)]", old[0])
    since = first.group(1) if first else "an earlier run"
    # the merged table is the whole suite's: its command without the subset run now
    full, _, _ = new[0].partition(" (")
    full = re.sub(r" --cases( \d+)+", "", full)
    ids = sorted(cases)
    listed = ", ".join(ids) if len(ids) <= 8 else f"{', '.join(ids[:6])}, ... {ids[-1]}"
    summary = (
        f"{full} ({since}; {len(ids)} case(s) run again with `--cases` on "
        f"{time.strftime('%Y-%m-%d')}: {listed}): {len(merged)} cases, "
        f"**{counts['passed']} passed**, "
        f"{counts['failed']} failed, {counts['refused']} refused (the reader names the "
        f"construct); {retried} case(s) run again with the next seed after a first failure."
    )
    return "\n".join([summary, "", *new[2:4], *merged])


def write_table(doc: Path, text: str) -> None:
    """Replace the table between the markers in ``doc`` (appended when missing)."""
    content = doc.read_text() if doc.exists() else ""
    block = f"{BEGIN}\n{text}\n{END}"
    if BEGIN in content:
        content = re.sub(re.escape(BEGIN) + r".*?" + re.escape(END), lambda _: block, content,
                         flags=re.S)  # fmt: skip
    else:
        content = content.rstrip("\n") + "\n\n" + block + "\n"
    doc.write_text(content)


def parse(argv: Sequence[str] | None = None) -> tuple[argparse.Namespace, list[Path]]:
    """The arguments and the case folders to run, every one checked: a usage error (exit 2)
    names the argument and what it must be, before any case runs."""
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawTextHelpFormatter
    )
    parser.add_argument("--suite", type=Path, required=True, help="cases/stochastic of the suite")
    parser.add_argument("--runs", type=int, default=10_000,
                        help=f"runs per case (>= {MIN_RUNS:,}, the suite's minimum)")  # fmt: skip
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--cases", nargs="*", help="case ids (default: every folder)")
    parser.add_argument("--ssa", choices=SSAS, default="compiled", help="the SSA that runs")
    parser.add_argument("--doc", type=Path, default=Path("docs/sbml.md"))
    args = parser.parse_args(argv)
    if args.runs < MIN_RUNS:
        parser.error(f"--runs {args.runs}: the suite's checks need at least {MIN_RUNS:,} runs "
                     f"per case (DSMTS user guide 3.1: Z and Y are read against normal ranges; "
                     f"10,000 to see small errors)")  # fmt: skip
    if not args.suite.is_dir():
        parser.error(f"--suite {args.suite}: no such directory (the cases/stochastic folder of "
                     f"a checkout of https://github.com/sbmlteam/sbml-test-suite)")  # fmt: skip
    folders = sorted(
        p for p in args.suite.iterdir() if p.is_dir() and re.fullmatch(r"\d{5}", p.name)
    )
    if not folders:
        parser.error(f"--suite {args.suite}: no case folders (NNNNN) in it; give the suite's "
                     f"cases/stochastic folder")  # fmt: skip
    if args.cases is not None:
        if not args.cases:
            parser.error("--cases needs one or more case ids (leave it out for every case)")
        unknown = [c for c in args.cases if c not in {f.name for f in folders}]
        if unknown:
            parser.error(f"--cases: no case(s) {unknown} in {args.suite} (it has "
                         f"{folders[0].name}..{folders[-1].name}, {len(folders)} cases)")  # fmt: skip
        folders = [f for f in folders if f.name in args.cases]
    return args, folders


def main(argv: Sequence[str] | None = None) -> None:
    """Parse arguments, run every case, print and write the table."""
    args, folders = parse(argv)
    cases, results = [], []
    for folder in folders:
        case = DsmtsCase.load(folder)
        result = run_case_twice(case, args.runs, args.seed, ssa=args.ssa)
        cases.append(case)
        results.append(result)
        print(_row(case, result), flush=True)
    subset = [f.name for f in folders] if args.cases else None
    text = table(cases, results, args.runs, args.seed, args.ssa, subset)
    content = args.doc.read_text() if args.doc.exists() else ""
    if args.cases and BEGIN in content:
        text = merge_rows(content, text, [c.id for c in cases])
    write_table(args.doc, text)
    print(text)


if __name__ == "__main__":
    main()
