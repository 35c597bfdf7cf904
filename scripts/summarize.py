"""One table (and plot) for a whole sweep: every job's settings, outcome and headline results.

python scripts/summarize.py data/multirun/reproduce/2025-01-01_12-00-00
python scripts/summarize.py <sweep dir> --strict     # exit 1 when a job failed (for CI)

Writes <sweep dir>/summary.csv (one row per job) and summary.png (max KS distance and speed-up
against dt, one line per setting of the other swept parameters; only when dt was swept).
A multirun writes both itself when it ends; rerun this after rerunning failed jobs.
"""

import argparse
import sys

from surrogate.cli import EXIT_USER_ERROR, configure_logging, exit_when_done
from surrogate.errors import SurrogateError
from surrogate.sweep import summarize


def main(argv: list[str] | None = None) -> int:
    """Command-line entry point; returns the exit code."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("sweep_dir", help="the multirun's sweep output dir")
    parser.add_argument("--strict", action="store_true", help="exit 1 when a job did not succeed")
    args = parser.parse_args(argv)
    configure_logging()
    try:
        df, csv, png = summarize(args.sweep_dir)
    except SurrogateError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_USER_ERROR
    bad = df[df["status"] != "ok"]
    print(f"{len(df)} job(s), {len(df) - len(bad)} ok, {len(bad)} failed or missing")
    print(f"table: {csv}" + (f"\nplot:  {png}" if png else "\nplot:  none (dt was not swept)"))
    return 1 if args.strict and len(bad) else 0


if __name__ == "__main__":
    exit_when_done(main() or 0)
