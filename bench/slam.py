"""Benchmark: run SLAM on a sequence and print speed, memory and accuracy figures.

    python bench/slam.py                                # the default run (cube, 640x480, 150 frames)
    python bench/slam.py data.max_frames=30 --profile   # plus a profile of where the time goes
    python bench/slam.py field.time=false sampler=uniform keyframe=random   # an ablation
    python bench/slam.py --no-peer                      # without the Open3D run

Extra arguments are Hydra overrides of conf/config.yaml. Besides the run's own figures it times one
mesh extraction (the run's mesh times and ``mesh.*`` settings, on the saved map) and, where Open3D is
installed (``pip install open3d-cpu``), runs Open3D's dense SLAM on the same frames in its own
process with as many threads (bench/peer.py) and prints TivNe's s/frame over Open3D's. Figures are
printed, never asserted.
"""

from __future__ import annotations

import argparse
import cProfile
import io
import json
import pstats
import sys
import tempfile
import time
from pathlib import Path

from hydra import compose, initialize_config_dir

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from bench.peer import open3d_on_config  # noqa: E402
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
    ("mesh_s", "s per mesh (extraction + culling, mean)", "{:.2f}"),
    ("open3d_s_per_frame", "Open3D dense SLAM s/frame, same frames", "{:.3f}"),
    ("open3d_ate_rmse_m", "Open3D ATE RMSE cm", "{:.2f}", 100.0),
    ("ratio_vs_open3d", "TivNe s/frame / Open3D s/frame", "{:.2f}"),
]


def mesh_seconds(run_dir: Path, mesh_cfg) -> float | None:
    """Mean wall time of one mesh extraction with culling at the run's mesh times, on the saved map."""
    from tivne.meshing import extract_mesh, select_mesh_times
    from tivne.slam.checkpoint import camera_centres, load_checkpoint

    field, meta = load_checkpoint(run_dir / "checkpoints" / "slam.pt", device="cpu")
    times = select_mesh_times(meta["timestamps"], list(mesh_cfg.times) or None)
    spent = []
    for ts in times:
        start = time.perf_counter()
        extract_mesh(field, meta["clock"].tau(ts), mesh_cfg.resolution, culling=mesh_cfg,
                     camera_centres=camera_centres(meta))
        spent.append(time.perf_counter() - start)
    return sum(spent) / len(spent) if spent else None


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


def torch_threads() -> int:
    import torch

    return torch.get_num_threads()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", default=None, help="run directory (default: a temporary one)")
    parser.add_argument("--profile", action="store_true", help="print the 25 most expensive functions")
    parser.add_argument("--json", default=None, help="write the figures to this JSON file (a reference for --compare)")
    parser.add_argument("--compare", default=None, help="a JSON file of an earlier run (--json) to print ratios against")
    parser.add_argument("--no-peer", action="store_true", help="do not run Open3D on the same frames")
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
    from tivne.cli import mesh_settings
    from tivne.config import MeshConfig

    mesh_cfg = mesh_settings(cfg.mesh) if "mesh" in cfg else MeshConfig()
    metrics["mesh_s"] = mesh_seconds(out, mesh_cfg)
    if not args.no_peer:
        threads = int(metrics.get("threads") or torch_threads())
        peer, why = open3d_on_config(["trainer.progress_bar=false", *overrides], threads)
        if peer is None:
            print(f"Open3D: {why}", file=sys.stderr)
        else:
            metrics["open3d_s_per_frame"] = peer.get("s_per_frame")
            metrics["open3d_ate_rmse_m"] = peer.get("ate_rmse_m")
            if peer.get("s_per_frame") and metrics.get("s_per_frame"):
                metrics["ratio_vs_open3d"] = metrics["s_per_frame"] / peer["s_per_frame"]
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
