"""python -m tivne.collect: run dirs -> one table (a row per run, overrides as columns, metrics)."""

from __future__ import annotations

import csv
import io
import json
from pathlib import Path

import pytest

from tivne.collect import main
from tivne.reporting.runs import find_run_dirs, read_overrides, read_row, render_table, results_table


def make_run(root: Path, overrides: list[str], metrics: dict | None) -> Path:
    """A run dir as Hydra and tivne.train leave it (only the files collect reads)."""
    (root / ".hydra").mkdir(parents=True)
    (root / ".hydra" / "overrides.yaml").write_text("".join(f"- {o}\n" for o in overrides))
    if metrics is not None:
        (root / "metrics.json").write_text(json.dumps(metrics))
    return root


@pytest.fixture()
def ablation(tmp_path: Path) -> Path:
    """A multirun of 2 x 2 jobs + one that stopped early + one that failed before writing results,
    with job numbers past 9 (natural order)."""
    sweep = tmp_path / "multirun"
    common = ["experiment=smoke", "dataset.width=80"]
    jobs = [("tivne", "dataset"), ("tivne", "none"), ("static", "dataset"), ("static", "none")]
    for i, (field, masks) in enumerate(jobs):
        metrics = {"complete": True, "frames": 5, "ate_rmse_m": 0.001 * (i + 1), "s_per_frame": 0.5, "psnr_db": 20.0 + i,
                   "cube_accuracy_last_m": 0.01 * i, "object_chamfer_mean_m": 0.02, "ghost_fraction_max": 0.1}
        make_run(sweep / f"{i + 8}_field={field},masks={masks}", [*common, f"field={field}", f"masks={masks}"], metrics)
    make_run(sweep / "12_field=tivne,masks=geometric", [*common, "field=tivne", "masks=geometric"],
             {"complete": False, "frames": 3, "ate_rmse_m": None})
    make_run(sweep / "13_field=bad", [*common, "field=bad"], None)
    return sweep


def test_one_row_per_run_in_natural_order(ablation):
    dirs = find_run_dirs([ablation])
    assert [d.name.split("_")[0] for d in dirs] == ["8", "9", "10", "11", "12", "13"]
    assert find_run_dirs([ablation, dirs[0]]) == dirs  # each run once


def test_overrides_are_columns_and_shared_ones_a_caption(ablation):
    table = results_table([read_row(d) for d in find_run_dirs([ablation])], root=ablation)
    assert table.columns[:4] == ["run", "field", "masks", "status"]
    assert table.common == {"experiment": "smoke", "dataset.width": "80"}
    assert [row[0] for row in table.rows] == ["8", "9", "10", "11", "12", "13"]
    assert [row[3] for row in table.rows] == ["complete"] * 4 + ["incomplete", "failed"]
    ate = table.columns.index("ate_rmse_m")
    assert [row[ate] for row in table.rows] == [0.001, 0.002, 0.003, 0.004, None, None]
    for key in ("object_chamfer_mean_m", "ghost_fraction_max", "psnr_db", "s_per_frame", "frames"):
        assert key in table.columns
    assert "cube_accuracy_last_m" not in table.columns and "threads" not in table.columns  # no run has threads
    everything = results_table([read_row(d) for d in find_run_dirs([ablation])], all_keys=True, root=ablation)
    assert everything.common == {} and "experiment" in everything.columns


def test_extra_metrics_by_pattern(ablation):
    table = results_table([read_row(d) for d in find_run_dirs([ablation])], ("ate_rmse_m", "cube_*_m"))
    assert table.columns[-2:] == ["ate_rmse_m", "cube_accuracy_last_m"]


def test_formats(ablation):
    table = results_table([read_row(d) for d in find_run_dirs([ablation])], root=ablation)
    md = render_table(table, "md").splitlines()
    assert md[0] == "common: experiment=smoke dataset.width=80"
    assert md[2].startswith("| run | field | masks | status |") and len(md) == 3 + 1 + 6
    assert "| 10 | static | dataset | complete | 5 | 0.003 |" in md[6]
    rows = list(csv.DictReader(io.StringIO(render_table(table, "csv"))))
    assert len(rows) == 6 and rows[0]["ate_rmse_m"] == "0.001" and rows[5]["status"] == "failed"
    parsed = json.loads(render_table(table, "json"))
    assert parsed["common"]["experiment"] == "smoke" and parsed["runs"][4]["status"] == "incomplete"


def test_override_prefixes(tmp_path):
    run = make_run(tmp_path / "r", ["+extra=1", "++forced=2", "~gone", "list=[a,b]"], {})
    assert read_overrides(run) == {"extra": "1", "forced": "2", "gone": "~", "list": "[a,b]"}


def test_cli(ablation, tmp_path, capsys):
    out = tmp_path / "table.csv"
    text = main([str(ablation), "--format", "csv", "--metrics", "cube_*_m", "--out", str(out)])
    assert out.read_text() == text == capsys.readouterr().out
    assert text.splitlines()[0].endswith("cube_accuracy_last_m")


def test_cli_errors_are_one_line(tmp_path, capsys):
    with pytest.raises(SystemExit) as exc:
        main([str(tmp_path / "missing")])
    assert exc.value.code == 2
    assert capsys.readouterr().err.strip() == f"error: {tmp_path / 'missing'}: no such run or sweep directory"
    with pytest.raises(SystemExit) as exc:
        main([str(tmp_path)])
    assert exc.value.code == 2 and "no run directories" in capsys.readouterr().err


def test_collect_changes_nothing_and_reports_unreadable_or_mistyped_metrics(tmp_path, capsys):
    import hashlib

    sweep = tmp_path / "sweep"
    make_run(sweep / "0_good", ["field=tivne"], {"complete": True, "frames": 5, "ate_rmse_m": 0.01})
    make_run(sweep / "1_many", ["field=static"], {"complete": True, "frames": "many", "ate_rmse_m": 0.02})
    make_run(sweep / "2_bool", ["field=none"], {"complete": "yes", "frames": 5, "ate_rmse_m": True})
    for i, garbage in enumerate((b"{not json", b"[1, 2]", b"\xff\xfe")):
        run = make_run(sweep / f"{3 + i}_bad", [f"seed={i}"], None)
        (run / "metrics.json").write_bytes(garbage)
    before = {p: hashlib.sha1(p.read_bytes()).hexdigest() for p in sweep.rglob("*") if p.is_file()}
    text = main([str(sweep), "--format", "json"])
    after = {p: hashlib.sha1(p.read_bytes()).hexdigest() for p in sweep.rglob("*") if p.is_file()}
    assert after == before  # byte-identical, nothing renamed or added
    runs = {r["run"]: r for r in json.loads(text)["runs"]}
    assert runs["0_good"]["status"] == "complete" and runs["0_good"]["problem"] is None
    assert runs["1_many"]["status"] == "unreadable" and runs["1_many"]["frames"] is None
    assert "frames='many': must be a non-negative integer" in runs["1_many"]["problem"]
    assert runs["1_many"]["ate_rmse_m"] == 0.02  # the valid values are still shown
    assert runs["2_bool"]["status"] == "unreadable" and "complete='yes': must be true or false" in runs["2_bool"]["problem"]
    for i in range(3):
        assert runs[f"{3 + i}_bad"]["status"] == "unreadable" and "unreadable" in runs[f"{3 + i}_bad"]["problem"]
    warnings = [line for line in capsys.readouterr().err.splitlines() if line.startswith("warning:")]
    assert len(warnings) == 5 and all("metrics.json" in w for w in warnings)
