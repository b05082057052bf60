"""Benchmark: run SLAM on a sequence and print speed, memory and accuracy figures.

    python bench/slam.py                                # the default run (cube, 640x480, 150 frames)
    python bench/slam.py data.max_frames=30 --profile   # plus a profile of where the time goes
    python bench/slam.py field.time=false sampler=uniform keyframe=random   # an ablation

Extra arguments are Hydra overrides of conf/config.yaml. Figures are printed, never asserted.
"""

from __future__ import annotations

import argparse
import cProfile
import io
import json
import pstats
import sys
import tempfile
from pathlib import Path

from hydra import compose, initialize_config_dir

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from tivne.cli import register_defaults  # noqa: E402
from tivne.slam.run import run  # noqa: E402

register_defaults()  # the config nodes conf/*.yaml compose onto

FIGURES = [
    ("frames", "frames", "{:.0f}"),
    ("s_per_frame", "s/frame (mean, incl. first-frame init)", "{:.3f}"),
    ("s_per_frame_after_first", "s/frame (after the first frame)", "{:.3f}"),
    ("first_frame_s", "first frame s (map initialisation)", "{:.2f}"),
    ("s_per_frame_first100", "s/frame, frames 2-101", "{:.3f}"),
    ("s_per_frame_last100", "s/frame, last 100 frames", "{:.3f}"),
    ("track_ms_per_frame", "tracking ms/frame", "{:.1f}"),
    ("track_ms_per_iter", "tracking ms/iter (field tracker)", "{:.1f}"),
    ("map_ms_per_iter", "mapping ms/iter", "{:.1f}"),
    ("final_refine_s", "final mapping pass s", "{:.1f}"),
    ("final_refine_share", "final pass share of the run", "{:.3f}"),
    ("peak_rss_mb", "peak RSS MB", "{:.0f}"),
    ("ate_rmse_m", "ATE RMSE cm", "{:.2f}", 100.0),
    ("ate_max_m", "ATE max cm", "{:.2f}", 100.0),
    ("cube_accuracy_first_m", "cube accuracy @first cm", "{:.2f}", 100.0),
    ("cube_accuracy_last_m", "cube accuracy @last cm", "{:.2f}", 100.0),
    ("cube_completion_ratio_first", "cube completion @5cm seen ±0.5s, first", "{:.3f}"),
    ("cube_completion_ratio_last", "cube completion @5cm seen ±0.5s, last", "{:.3f}"),
    ("object_chamfer_mean_m", "moving objects Chamfer mean cm", "{:.2f}", 100.0),
    ("object_chamfer_max_m", "moving objects Chamfer max cm", "{:.2f}", 100.0),
    ("ghost_fraction_first", "ghost fraction @first", "{:.3f}"),
    ("ghost_fraction_last", "ghost fraction @last", "{:.3f}"),
    ("ghost_fraction_max", "ghost fraction max", "{:.3f}"),
    ("static_completion_ratio_first", "static completion @5cm, first", "{:.3f}"),
    ("static_completion_ratio_last", "static completion @5cm, last", "{:.3f}"),
    ("psnr_db", "PSNR dB (re-rendered, pixels with depth)", "{:.2f}"),
    ("ssim", "SSIM (re-rendered, pixels with depth)", "{:.3f}"),
]


def print_figures(metrics: dict, reference: dict | None) -> None:
    """The figures, and with a reference run (same machine, ideally the same session) the ratio
    new / reference of each (for times below 1 is faster)."""
    for key, label, fmt, *scale in FIGURES:
        value = metrics.get(key)
        text = "n/a" if value is None else fmt.format(value * (scale[0] if scale else 1.0))
        if reference is not None:
            old = reference.get(key)
            ratio = f"{value / old:.2f}x" if isinstance(value, (int, float)) and isinstance(old, (int, float)) and old else "n/a"
            old_text = "n/a" if old is None else fmt.format(old * (scale[0] if scale else 1.0))
            text = f"{text:>10}   ref {old_text:>10}   ratio {ratio}"
        print(f"  {label:<42} {text}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", default=None, help="run directory (default: a temporary one)")
    parser.add_argument("--profile", action="store_true", help="print the 25 most expensive functions")
    parser.add_argument("--json", default=None, help="write the figures to this JSON file (a reference for --compare)")
    parser.add_argument("--compare", default=None, help="a JSON file of an earlier run (--json) to print ratios against")
    args, overrides = parser.parse_known_args()
    reference = json.loads(Path(args.compare).read_text()) if args.compare else None
    with initialize_config_dir(config_dir=str(REPO / "conf"), version_base="1.3"):
        cfg = compose("config", overrides=["trainer.progress_bar=false", *overrides])
    out = Path(args.out or tempfile.mkdtemp(prefix="tivne-bench-"))
    profiler = cProfile.Profile() if args.profile else None
    if profiler:
        profiler.enable()
    metrics = run(cfg, out)
    if profiler:
        profiler.disable()
    print(f"\nbenchmark: {' '.join(overrides) or 'default'}  (run dir {out})" + (f"  vs {args.compare}" if reference else ""))
    print_figures(metrics, reference)
    figures = {k: metrics.get(k) for k, *_ in FIGURES}
    print(json.dumps(figures))
    if args.json:
        Path(args.json).write_text(json.dumps(figures | {"overrides": overrides}, indent=2) + "\n")
    if profiler:
        buf = io.StringIO()
        pstats.Stats(profiler, stream=buf).sort_stats("tottime").print_stats(25)
        print(buf.getvalue())


if __name__ == "__main__":
    main()
