"""Run directories -> one results table: a row per run, its command-line overrides as columns,
then its metrics (``python -m tivne.collect``).

A run dir is any folder holding ``metrics.json`` or ``.hydra/overrides.yaml`` (a Hydra run, a job of
a multirun or an Optuna trial). A run without metrics.json is listed as ``failed`` (it stopped
before writing results, or is still running): a table never drops a run silently.
"""

from __future__ import annotations

import csv
import fnmatch
import io
import json
import math
import re
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

from tivne.slam.outputs import RunDir

# The metrics every table shows (a column only where some run has the key).
DEFAULT_METRICS = (
    "frames", "ate_rmse_m", "object_chamfer_mean_m", "object_chamfer_max_m", "ghost_fraction_max", "psnr_db",
    "s_per_frame", "threads", "error",
)
FORMATS = ("md", "csv", "json")


@dataclass(frozen=True)
class RunRow:
    """One run: its folder, overrides {key: value as typed}, metrics.json content ({} when absent) and
    status: complete | incomplete (stopped early, ``complete: false``) | failed (``error`` in
    metrics.json, or no metrics.json)."""

    path: Path
    overrides: dict[str, str]
    metrics: dict[str, Any]
    problem: str | None = None  # why metrics.json / overrides.yaml could not be (wholly) read

    @property
    def status(self) -> str:
        if self.problem is not None:
            return "unreadable"
        if not self.metrics or self.metrics.get("error"):
            return "failed"
        return "complete" if self.metrics.get("complete") is True else "incomplete"


@dataclass(frozen=True)
class ResultsTable:
    """columns: names; rows: one list of values per run (None = missing); common: overrides that
    every run shares (left out of the columns unless asked for)."""

    columns: list[str]
    rows: list[list[Any]]
    common: dict[str, str]


def natural_key(path: Path) -> list[Any]:
    """Sort key that puts job 10 after job 9."""
    return [int(part) if part.isdigit() else part for part in re.split(r"(\d+)", str(path))]


def find_run_dirs(paths: Iterable[str | Path]) -> list[Path]:
    """Every run dir at or under ``paths`` (folders with metrics.json or .hydra/overrides.yaml), in
    natural order, each once.

    Raises:
        FileNotFoundError: a path that does not exist.
    """
    found: set[Path] = set()
    for path in map(Path, paths):
        if not path.exists():
            raise FileNotFoundError(f"{path}: no such run or sweep directory")
        for marker in (RunDir.METRICS, ".hydra/overrides.yaml"):
            found.update(p.parents[len(Path(marker).parts) - 1] for p in path.rglob(marker))
    return sorted(found, key=natural_key)


def read_overrides(run_dir: Path) -> dict[str, str]:
    """{key: value} of the run's .hydra/overrides.yaml ({} when absent); a ``+`` or ``++`` prefix is
    dropped, ``~key`` (a deletion) becomes ``key: "~"``."""
    path = RunDir(run_dir).overrides
    if not path.is_file():
        return {}
    entries = yaml.safe_load(path.read_text()) or []
    out: dict[str, str] = {}
    for entry in entries:
        key, _, value = str(entry).partition("=")
        if key.startswith("~"):
            key, value = key[1:], "~"
        out[key.lstrip("+")] = value
    return out


# metrics.json keys collect shows, by the type their value must have (null is allowed for all).
COUNT_KEYS = ("frames", "sequence_frames", "ate_frames", "threads")
TEXT_KEYS = ("error",)


def check_metric(key: str, value: Any) -> str | None:
    """Why ``value`` is not a valid value of metrics.json's ``key`` (None when it is)."""
    if value is None:
        return None
    if key == "complete":
        return None if isinstance(value, bool) else "must be true or false"
    if key in TEXT_KEYS or key.endswith("_reason"):
        return None if isinstance(value, str) else "must be a string"
    number = isinstance(value, (int, float)) and not isinstance(value, bool)
    if key in COUNT_KEYS and not (number and math.isfinite(value) and float(value).is_integer() and value >= 0):
        return "must be a non-negative integer"
    if key in DEFAULT_METRICS and not number:
        return "must be a number"
    return None


def read_metrics_file(path: Path) -> tuple[dict[str, Any], str | None]:
    """metrics.json's content and the first problem with it, reading only: ({}, reason) when it
    is not a JSON object; wrong-typed values (``"frames": "many"``) are dropped and named."""
    if not path.is_file():
        return {}, None
    try:
        metrics = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        return {}, f"{path}: unreadable ({type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''})"
    if not isinstance(metrics, dict):
        return {}, f"{path}: unreadable (not a JSON object)"
    problems = {k: why for k, v in metrics.items() if (why := check_metric(k, v)) is not None}
    if not problems:
        return metrics, None
    key = next(iter(problems))
    valid = {k: v for k, v in metrics.items() if k not in problems}
    return valid, f"{path}: {key}={metrics[key]!r}: {problems[key]}" + (f" (and {len(problems) - 1} more)" if len(problems) > 1 else "")


def read_row(run_dir: Path) -> RunRow:
    """A run's row, read without changing anything in the folder (a problem is recorded, not fixed)."""
    run_dir = Path(run_dir)
    try:
        overrides, problem = read_overrides(run_dir), None
    except (OSError, ValueError, yaml.YAMLError) as exc:
        overrides, problem = {}, f"{RunDir(run_dir).overrides}: unreadable ({type(exc).__name__})"
    metrics, metrics_problem = read_metrics_file(RunDir(run_dir).metrics)
    return RunRow(run_dir, overrides, metrics, problem or metrics_problem)


def metric_columns(rows: Sequence[RunRow], patterns: Sequence[str]) -> list[str]:
    """The metrics.json keys matching ``patterns`` (exact keys or fnmatch patterns, in that order)
    that some run has; ``*_reason`` keys only when a pattern names them."""
    present = sorted({k for r in rows for k in r.metrics})
    columns: list[str] = []
    for pattern in patterns:
        for key in present if any(c in pattern for c in "*?[") else [pattern]:
            if key in present and fnmatch.fnmatchcase(key, pattern) and key not in columns:
                if key.endswith("_reason") and not pattern.endswith("_reason"):
                    continue
                columns.append(key)
    return columns


def run_label(path: Path, root: Path | None) -> str:
    """The ``run`` cell: the folder relative to ``root`` (its name when it is ``root``), where a
    multirun job folder (``<num>_<overrides>``, conf/config.yaml's hydra.sweep.subdir) is shortened
    to its parent and number, since its overrides are columns of the table anyway."""
    if root is not None and path == root:  # a single run dir given: its name is enough
        return path.name
    label = path.relative_to(root) if root is not None and path.is_relative_to(root) else path
    number = re.match(r"(\d+)_.*=", label.name)
    return str(label.parent / number.group(1)) if number else str(label)


def results_table(rows: Sequence[RunRow], metrics: Sequence[str] = DEFAULT_METRICS, all_keys: bool = False, root: Path | None = None) -> ResultsTable:
    """One table over ``rows``: ``run`` (:func:`run_label`), the overridden keys (in order of first
    appearance; those equal in every run only with ``all_keys``), ``status``, then ``metrics``
    (see :func:`metric_columns`)."""
    keys: list[str] = []
    for r in rows:
        keys += [k for k in r.overrides if k not in keys]
    values = {k: [r.overrides.get(k) for r in rows] for k in keys}
    common = {k: v[0] for k, v in values.items() if len(rows) > 1 and len(set(v)) == 1 and v[0] is not None}
    shown = [k for k in keys if all_keys or k not in common]
    measured = metric_columns(rows, metrics)
    problems = ["problem"] if any(r.problem for r in rows) else []
    table = [[run_label(r.path, root), *[r.overrides.get(k) for k in shown], r.status, *[r.metrics.get(m) for m in measured],
              *([r.problem] if problems else [])] for r in rows]
    return ResultsTable(["run", *shown, "status", *measured, *problems], table, {} if all_keys else common)


def format_value(value: Any) -> str:
    """A cell as text: floats with 4 significant digits (also overrides typed as long decimals, such
    as an Optuna trial's ``5.269299097981381``), None as empty."""
    if value is None:
        return ""
    if isinstance(value, str) and re.fullmatch(r"-?\d+\.\d{5,}", value):
        value = float(value)
    if isinstance(value, float):
        return "nan" if math.isnan(value) else f"{value:.4g}"
    if isinstance(value, (list, dict)):
        return json.dumps(value)
    return str(value)


def to_markdown(table: ResultsTable) -> str:
    """A GitHub Markdown table, with the shared overrides in a line above it."""
    lines = []
    if table.common:
        lines += ["common: " + " ".join(f"{k}={v}" for k, v in table.common.items()), ""]
    lines.append("| " + " | ".join(table.columns) + " |")
    lines.append("|" + "|".join("---" for _ in table.columns) + "|")
    lines += ["| " + " | ".join(format_value(v).replace("|", "\\|") for v in row) + " |" for row in table.rows]
    return "\n".join(lines) + "\n"


def to_csv(table: ResultsTable) -> str:
    """CSV with full-precision numbers (shared overrides are columns here only with ``all_keys``)."""
    out = io.StringIO()
    writer = csv.writer(out, lineterminator="\n")
    writer.writerow(table.columns)
    writer.writerows([["" if v is None else v for v in row] for row in table.rows])
    return out.getvalue()


def to_json(table: ResultsTable) -> str:
    """{"common": {...}, "runs": [{column: value}, ...]} with full-precision numbers."""
    runs = [dict(zip(table.columns, row)) for row in table.rows]
    return json.dumps({"common": table.common, "runs": runs}, indent=2) + "\n"


def render_table(table: ResultsTable, fmt: str) -> str:
    """The table as ``md``, ``csv`` or ``json`` text."""
    writers = {"md": to_markdown, "csv": to_csv, "json": to_json}
    if fmt not in writers:
        raise ValueError(f"format {fmt!r}: must be one of {', '.join(FORMATS)}")
    return writers[fmt](table)
