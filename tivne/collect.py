"""One results table from run directories: ``python -m tivne.collect DIR [DIR ...] [--format md|csv|json]``.

A row per run found at or under the DIRs (a multirun / Optuna sweep dir, an outputs folder, single
run dirs), the overridden keys as columns (from each run's .hydra/overrides.yaml; keys every run
shares go in a ``common:`` line unless ``--all-keys``), its status (complete, incomplete, failed) and
its metrics (``--metrics`` adds metrics.json keys or patterns, e.g. ``'cube_*_last_m'``).
``--out FILE`` writes the table there as well. Nothing it reads is changed: a metrics.json that
cannot be read, or holds values of the wrong type, makes its row ``unreadable`` with the reason in a
``problem`` column and on stderr. Errors are one ``error: ...`` line, exit status 2.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

from tivne.cli import one_line_errors
from tivne.reporting.runs import DEFAULT_METRICS, FORMATS, find_run_dirs, read_row, render_table, results_table


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog="python -m tivne.collect", description=__doc__.splitlines()[0])
    parser.add_argument("dirs", nargs="+", type=Path, help="run or sweep directories")
    parser.add_argument("--format", choices=FORMATS, default="md")
    parser.add_argument("--metrics", default="", help="comma-separated extra metrics.json keys or fnmatch patterns")
    parser.add_argument("--all-keys", action="store_true", help="also the overrides that every run shares, as columns")
    parser.add_argument("--out", type=Path, help="also write the table to this file")
    return parser.parse_args(argv)


@one_line_errors
def main(argv: list[str] | None = None) -> str:
    args = parse_args(argv)
    run_dirs = find_run_dirs(args.dirs)
    if not run_dirs:
        raise FileNotFoundError(f"{', '.join(map(str, args.dirs))}: no run directories (metrics.json or .hydra/overrides.yaml) found")
    extra = [m.strip() for m in args.metrics.split(",") if m.strip()]
    root = Path(os.path.commonpath([p.resolve() for p in args.dirs]))
    rows = [read_row(p.resolve()) for p in run_dirs]
    for row in rows:  # reported, never fixed: collect changes nothing it reads
        if row.problem:
            print(f"warning: {row.problem}", file=sys.stderr)
    text = render_table(results_table(rows, (*DEFAULT_METRICS, *extra), args.all_keys, root), args.format)
    if args.out is not None:
        args.out.write_text(text)
    sys.stdout.write(text)
    return text


if __name__ == "__main__":
    main()
