"""Real RGB-D data, side by side: TivNe and Open3D's dense SLAM on the same frames, in one run.

    python bench/real.py                                   # the shared TUM fr1/rpy tail, all frames
    python bench/real.py --frames 100                      # the first 100 frames
    python bench/real.py --root path/to/rgbd_dataset_freiburg3_walking_xyz --camera fr3
    python bench/real.py --only tivne tracking.method=field  # one system; extra args: TivNe overrides
    python bench/real.py --sequence 7scenes                # the shared 7-Scenes redkitchen tail
    python bench/real.py --also backend.method=graph       # a second TivNe config in the same run

Both systems read the frames through TivNe's TUM reader (association, undistortion of colour and
depth onto one K), so they see identical inputs. Each runs in its own process, so its peak RSS is
its own. Open3D is the frame-to-model dense SLAM of ``open3d.t.pipelines.slam`` (TSDF voxel blocks,
projective ICP against the ray-cast model) with its example's settings; it is a bench-only optional
extra: ``pip install open3d-cpu`` (on Debian it needs ``libusb-1.0-0``).

Prints ATE RMSE / mean / max (SE(3)-aligned to ground truth), RPE per frame, s/frame and peak RSS for
both, and their ratios. Figures are printed, never asserted.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
DEFAULT_ROOT = REPO.parent / "shared" / "data" / "tum_fr1_rpy_tail"
# --sequence: (folder under shared/data, camera, fx fy cx cy for camera=custom)
SEQUENCES = {
    "fr1": ("tum_fr1_rpy_tail", "fr1", None),
    "7scenes": ("7scenes_redkitchen_tail", "custom", (585.0, 585.0, 320.0, 240.0)),  # 7-Scenes' documented Kinect defaults
}
sys.path.insert(0, str(REPO))


def trajectory_figures(est: np.ndarray, gt: np.ndarray) -> dict[str, float]:
    """ATE (SE(3)-aligned) and per-frame RPE of (N, 4, 4) estimated vs GT c2w poses."""
    from tivne.metrics.trajectory import absolute_trajectory_error, relative_pose_error

    ate = absolute_trajectory_error(est, gt, align="se3")
    rpe = relative_pose_error(est, gt, delta=1)
    return {
        "ate_rmse_m": float(ate.rmse), "ate_mean_m": float(ate.mean), "ate_max_m": float(ate.max),
        "rpe_trans_rmse_m": float(rpe.trans_rmse_m), "rpe_rot_rmse_deg": float(rpe.rot_rmse_deg),
    }


def parse_intrinsics(text: str | None) -> tuple[float, ...] | None:
    return None if not text else tuple(float(x) for x in text.split(","))


def load_view(root: str, camera: str, frames: int, intrinsics: str | None = None):
    from data_modules.sequence import SequenceView
    from data_modules.tum import TUMSequence

    fx = dict(zip(("fx", "fy", "cx", "cy"), parse_intrinsics(intrinsics) or ()))
    return SequenceView(TUMSequence(root=root, camera=camera, **fx), max_frames=frames or None)


def run_open3d(root: str, camera: str, frames: int, intrinsics: str | None) -> dict[str, float]:
    """Open3D's frame-to-model dense SLAM (examples/python/t_reconstruction_system/dense_slam.py settings)."""
    import open3d as o3d
    import open3d.core as o3c

    view = load_view(root, camera, frames, intrinsics)
    device = o3c.Device("CPU:0")
    K = o3c.Tensor(view.intrinsics.K().double().numpy())
    T = o3c.Tensor(np.identity(4))
    model = o3d.t.pipelines.slam.Model(0.0058, 16, 40000, T, device)  # voxel 3/512 m (example default)
    h, w = view.intrinsics.height, view.intrinsics.width
    frame, raycast = o3d.t.pipelines.slam.Frame(h, w, K, device), o3d.t.pipelines.slam.Frame(h, w, K, device)
    poses, gt, spent = [], [], 0.0
    depth_scale, depth_max, trunc, odo_thr = 1000.0, 3.0, 8.0, 0.1
    for i in range(len(view)):
        f = view[i]
        depth = o3d.t.geometry.Image(o3c.Tensor((f.depth.numpy() * depth_scale).astype(np.uint16)))
        color = o3d.t.geometry.Image(o3c.Tensor(np.ascontiguousarray((f.rgb.numpy() * 255).round().astype(np.uint8))))
        start = time.perf_counter()
        frame.set_data_from_image("depth", depth)
        frame.set_data_from_image("color", color)
        if i > 0:
            result = model.track_frame_to_model(frame, raycast, depth_scale, depth_max, odo_thr)
            T = T @ result.transformation
        model.update_frame_pose(i, T)
        model.integrate(frame, depth_scale, depth_max, trunc)
        model.synthesize_model_frame(raycast, depth_scale, 0.1, depth_max, trunc, False)
        spent += time.perf_counter() - start
        poses.append(T.cpu().numpy())
        gt.append(f.gt_pose.double().numpy() if f.gt_pose is not None else None)
    keep = [i for i, g in enumerate(gt) if g is not None]
    out = trajectory_figures(np.stack([poses[i] for i in keep]), np.stack([gt[i] for i in keep]))
    return out | {"frames": len(view), "s_per_frame": spent / len(view)}


def run_tivne(root: str, camera: str, frames: int, intrinsics: str | None, overrides: list[str]) -> dict[str, float]:
    from hydra import compose, initialize_config_dir

    from data_modules.tables import read_tum_trajectory
    from tivne.train import run

    args = ["dataset=tum", f"dataset.root={root}", f"dataset.camera={camera}", "trainer.progress_bar=false", "output.image_every=0"]
    if frames:
        args.append(f"data.max_frames={frames}")
    args += [f"dataset.{k}={v}" for k, v in zip(("fx", "fy", "cx", "cy"), parse_intrinsics(intrinsics) or ())]
    with initialize_config_dir(config_dir=str(REPO / "conf"), version_base="1.3"):
        cfg = compose("config", overrides=[*args, *overrides])
    out = Path(tempfile.mkdtemp(prefix="tivne-real-"))
    metrics = run(cfg, out)
    view = load_view(root, camera, frames, intrinsics)
    ts, est = read_tum_trajectory(out / "trajectory.txt")
    gt = {float(view.timestamps[i]): view[i].gt_pose for i in range(len(view))}
    keep = [i for i, t in enumerate(ts) if gt.get(float(t)) is not None]
    figures = trajectory_figures(est.numpy()[keep], np.stack([gt[float(ts[i])].double().numpy() for i in keep]))
    keys = ("frames", "s_per_frame", "track_ms_per_frame", "map_ms_per_iter", "final_refine_s", "tracking_lost", "frames_without_tracking")
    graph = {k: v for k, v in metrics.items() if k.startswith("graph_")}
    return figures | {k: metrics.get(k) for k in keys} | graph | {"run_dir": str(out)}


def child(args: argparse.Namespace, overrides: list[str]) -> None:
    """Run one system in this process and print its figures (plus peak RSS) as one JSON line."""
    if args.only == "open3d":
        figures = run_open3d(args.root, args.camera, args.frames, args.intrinsics)
    else:
        figures = run_tivne(args.root, args.camera, args.frames, args.intrinsics, overrides)
    figures["peak_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    print("FIGURES " + json.dumps(figures))


def spawn(system: str, args: argparse.Namespace, overrides: list[str]) -> dict[str, float] | None:
    cmd = [sys.executable, __file__, "--child", "--only", system, "--root", args.root, "--camera", args.camera, "--frames", str(args.frames)]
    cmd += (["--intrinsics", args.intrinsics] if args.intrinsics else []) + overrides
    proc = subprocess.run(cmd, capture_output=True, text=True, env=dict(os.environ, OMP_WAIT_POLICY="PASSIVE"))
    lines = [line for line in proc.stdout.splitlines() if line.startswith("FIGURES ")]
    if proc.returncode != 0 or not lines:
        print(f"{system}: failed (exit {proc.returncode}): {proc.stderr.strip().splitlines()[-1:] or ''}", file=sys.stderr)
        return None
    return json.loads(lines[-1][len("FIGURES "):])


def table(results: dict[str, dict[str, float] | None]) -> str:
    """One column per system, then each TivNe column's ratio to Open3D's."""
    rows = [
        ("ATE RMSE cm", "ate_rmse_m", 100), ("ATE mean cm", "ate_mean_m", 100), ("ATE max cm", "ate_max_m", 100),
        ("RPE trans cm/frame", "rpe_trans_rmse_m", 100), ("RPE rot deg/frame", "rpe_rot_rmse_deg", 1),
        ("s/frame", "s_per_frame", 1), ("peak RSS MB", "peak_rss_mb", 1), ("frames", "frames", 1),
        ("graph edges", "graph_edges", 1), ("loop closures accepted", "graph_loops_accepted", 1),
        ("loop closures rejected", "graph_loops_rejected", 1), ("graph optimise ms", "graph_optimise_ms", 1),
        ("graph align ms", "graph_align_ms", 1),
    ]
    names = [n for n, r in results.items() if r is not None]
    base = "Open3D" if "Open3D" in names else None
    ratios = [n for n in names if base and n != base]
    lines = ["| figure | " + " | ".join(names + [f"{n} / Open3D" for n in ratios]) + " |", "|---" * (1 + len(names) + len(ratios)) + "|"]
    for label, key, scale in rows:
        vals = {n: results[n].get(key) for n in names}
        if all(v is None for v in vals.values()):
            continue
        cells = ["n/a" if vals[n] is None else f"{vals[n] * scale:.3f}" for n in names]
        cells += [f"{vals[n] / vals[base]:.2f}" if vals[n] is not None and vals[base] else "n/a" for n in ratios]
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--root", default=str(DEFAULT_ROOT), help="a TUM-layout folder")
    parser.add_argument("--camera", default="fr1")
    parser.add_argument("--frames", type=int, default=0, help="first n frames (0 = all)")
    parser.add_argument("--only", choices=("tivne", "open3d"), default=None)
    parser.add_argument("--sequence", choices=sorted(SEQUENCES), default=None, help="a shared real tail (sets --root, --camera, --intrinsics)")
    parser.add_argument("--data", default=str(REPO.parent / "shared" / "data"), help="the folder holding the shared real tails (for --sequence)")
    parser.add_argument("--intrinsics", default=None, help="fx,fy,cx,cy for --camera custom")
    parser.add_argument("--also", action="append", default=[], help="another TivNe config in the same run: space-separated overrides")
    parser.add_argument("--json", default=None, help="also write the figures here")
    parser.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args, overrides = parser.parse_known_args()
    if args.sequence:
        folder, args.camera, fx = SEQUENCES[args.sequence]
        args.root = str(Path(args.data) / folder)
        args.intrinsics = ",".join(str(x) for x in fx) if fx else None
    if args.child:
        return child(args, overrides)
    results: dict[str, dict[str, float] | None] = {}
    if args.only != "open3d":
        results["TivNe"] = spawn("tivne", args, overrides)
        for extra in args.also:
            results[f"TivNe {extra}"] = spawn("tivne", args, overrides + extra.split())
    if args.only != "tivne":
        results["Open3D"] = spawn("open3d", args, overrides)
    print(f"\nbench/real.py on {args.root} ({args.frames or 'all'} frames; TivNe overrides: {' '.join(overrides) or 'none'})")
    print(table(results))
    print(json.dumps(results))
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=2) + "\n")


if __name__ == "__main__":
    main()
