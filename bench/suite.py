"""The benchmark suite: every synthetic preset plus the shared real sequence, one Markdown table.

    python bench/suite.py                    # every preset (300 frames, 640x480) and the real tail
    python bench/suite.py --quick            # under 15 min on 2 cores: 60 frames at 320x240, real: 120 frames
    python bench/suite.py --json out.json    # also write the figures
    python bench/suite.py --compare old.json # print the deltas against an earlier --json
    python bench/suite.py --only cube,crossing mapping.every=2   # some sequences; extra args: TivNe overrides

Each sequence runs ``tivne.train`` (default config plus the overrides) in its own process (its peak
RSS is its own). Meshes are evaluated at three times (20 %, 50 % and 90 % of the sequence); per
moving object the Chamfer distance over the part some camera saw within ±0.5 s of the mesh time
(``tivne.evaluation``; "absent": some camera saw it then but the mesh has no surface within 5 cm of
its box, a failure; "–": no camera saw it). Columns: ATE, per-object Chamfer at the three times, the worst object
track's error (``objects.track=true``: first-frame aligned ATE and rotation RMSE), the largest ghost
fraction, PSNR of re-rendered frames, s/frame and peak RSS. Figures are printed, never asserted.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
REAL_ROOT = REPO.parent / "shared" / "data" / "tum_fr1_rpy_tail"
sys.path.insert(0, str(REPO))

TIME_FRACTIONS = (0.2, 0.5, 0.9)
SCENE_SEED = 1  # one fixed draw of each preset's layout, so runs compare


def sequences(quick: bool) -> dict[str, list[str]]:
    """{name: dataset overrides} of every suite sequence."""
    from data_modules.synthetic.presets import PRESETS

    frames, size = (60, (320, 240)) if quick else (300, (640, 480))
    synth = {
        name: ["dataset=synthetic", f"dataset.scene={name}", f"dataset.seed={SCENE_SEED}", f"dataset.num_frames={frames}",
               f"dataset.width={size[0]}", f"dataset.height={size[1]}"]
        for name in PRESETS
    }
    real = ["dataset=tum", f"dataset.root={REAL_ROOT}", "dataset.camera=fr1"] + (["data.max_frames=120"] if quick else [])
    return synth | ({"tum_fr1_rpy_tail": real} if REAL_ROOT.is_dir() else {})


def mesh_times(overrides: list[str]) -> list[float]:
    """Timestamps at the suite's time fractions of the sequence the overrides select."""
    from hydra import compose, initialize_config_dir
    from hydra.utils import instantiate

    from data_modules.sequence import SequenceView
    from tivne.cli import register_defaults

    register_defaults()
    with initialize_config_dir(config_dir=str(REPO / "conf"), version_base="1.3"):
        cfg = compose("config", overrides=overrides)
    view = SequenceView(instantiate(cfg.dataset), **dict(cfg.data))
    stamps = [float(t) for t in view.timestamps]
    return [round(stamps[min(len(stamps) - 1, int(f * (len(stamps) - 1)))], 3) for f in TIME_FRACTIONS]


def child(overrides: list[str]) -> None:
    """Run one sequence in this process; print its figures as one JSON line."""
    from hydra import compose, initialize_config_dir

    from tivne.cli import register_defaults
    from tivne.slam.run import run

    register_defaults()  # the config nodes conf/*.yaml compose onto (the mask providers' defaults among them)
    with initialize_config_dir(config_dir=str(REPO / "conf"), version_base="1.3"):
        cfg = compose("config", overrides=["trainer.progress_bar=false", "output.image_every=0", *overrides])
    with tempfile.TemporaryDirectory(prefix="tivne-suite-") as run_dir:  # ~60-90 MB a run: a week of suites filled the disk
        metrics = run(cfg, Path(run_dir))
    metrics["peak_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    print("FIGURES " + json.dumps(metrics))


def run_sequence(name: str, dataset: list[str], extra: list[str]) -> dict | None:
    times = mesh_times([*dataset, *extra])
    overrides = [*dataset, f"mesh.times=[{','.join(str(t) for t in times)}]", *extra]
    proc = subprocess.run([sys.executable, __file__, "--child", *overrides], capture_output=True, text=True,
                          env=dict(os.environ, OMP_WAIT_POLICY="PASSIVE"))
    lines = [line for line in proc.stdout.splitlines() if line.startswith("FIGURES ")]
    if proc.returncode != 0 or not lines:
        tail = (proc.stderr.strip().splitlines() or ["?"])[-1]
        print(f"{name}: failed (exit {proc.returncode}): {tail}", file=sys.stderr)
        return None
    metrics = json.loads(lines[-1][len("FIGURES "):])
    return summarise(metrics, times)


def summarise(metrics: dict, times: list[float]) -> dict:
    """The suite's figures of one run: ATE, per-object Chamfer at each time, ghosts, PSNR, speed, memory."""
    chamfer, absent = {}, {}
    for key, value in metrics.items():
        for i, t in enumerate(times):
            prefix = f"mesh_t{t:.2f}_"
            if key.startswith(prefix) and key.endswith("_chamfer_m") and not key.startswith(prefix + "static"):
                name = key[len(prefix): -len("_chamfer_m")]
                chamfer.setdefault(name, [None] * len(times))[i] = value
                # seen by the camera around t, yet no surface near it: a failure, not a blank
                why = str(metrics.get(f"{prefix}{name}_reason") or "")
                absent.setdefault(name, [False] * len(times))[i] = "no reconstructed surface" in why and "no camera saw it" not in why
    keys = ("ate_rmse_m", "ghost_fraction_max", "psnr_db", "s_per_frame", "final_refine_share", "peak_rss_mb", "tracking_lost", "frames",
            "object_ate_max_m", "object_rot_max_deg")
    return {k: metrics.get(k) for k in keys} | {"chamfer_m": chamfer, "absent": absent, "times": times}


def fmt(value, scale: float = 1.0, digits: int = 2) -> str:
    return "–" if value is None else f"{value * scale:.{digits}f}"


def table(results: dict[str, dict | None], reference: dict | None = None) -> str:
    head = ("| sequence | ATE cm | object Chamfer cm @20/50/90 % | worst object track cm / deg | ghost max | PSNR dB | s/frame "
            "| peak RSS MB |")
    lines = [head, "|---|---|---|---|---|---|---|---|"]
    for name, r in results.items():
        if r is None:
            lines.append(f"| {name} | failed | | | | | | |")
            continue
        gone = r.get("absent", {})
        objs = "; ".join(f"{o} " + "/".join("absent" if gone.get(o, [False] * len(vals))[i] else fmt(v, 100, 1) for i, v in enumerate(vals))
                         for o, vals in sorted(r["chamfer_m"].items())) or "–"
        track = f"{fmt(r.get('object_ate_max_m'), 100)} / {fmt(r.get('object_rot_max_deg'))}" if r.get("object_ate_max_m") is not None else "–"
        cells = [fmt(r["ate_rmse_m"], 100), objs, track, fmt(r["ghost_fraction_max"], 1, 3), fmt(r["psnr_db"], 1, 1),
                 fmt(r["s_per_frame"], 1, 3), fmt(r["peak_rss_mb"], 1, 0)]
        old = (reference or {}).get(name)
        if old:
            for i, key, scale in ((0, "ate_rmse_m", 100), (3, "ghost_fraction_max", 1), (5, "s_per_frame", 1)):
                if r.get(key) is not None and old.get(key) is not None:
                    cells[i] += f" ({(r[key] - old[key]) * scale:+.2f})"
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--only", default=None, help="comma-separated sequence names")
    parser.add_argument("--json", default=None)
    parser.add_argument("--compare", default=None, help="JSON of an earlier run: deltas in brackets")
    parser.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args, extra = parser.parse_known_args()
    if args.child:
        return child(extra)
    chosen = sequences(args.quick)
    if args.only:
        chosen = {k: v for k, v in chosen.items() if k in args.only.split(",")}
    results = {}
    for name, dataset in chosen.items():
        results[name] = run_sequence(name, dataset, extra)
        print(f"done: {name}", file=sys.stderr, flush=True)
    reference = json.loads(Path(args.compare).read_text()) if args.compare else None
    print(f"\nbench/suite.py {'--quick ' if args.quick else ''}{' '.join(extra) or '(default config)'}")
    print(table(results, reference))
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=2) + "\n")


if __name__ == "__main__":
    main()
