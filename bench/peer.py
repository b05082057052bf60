"""The peer of the benchmarks: Open3D's frame-to-model dense SLAM on the frames TivNe runs on.

    python bench/peer.py [hydra overrides of conf/config.yaml]   # Open3D on that config's frames

Open3D is ``open3d.t.pipelines.slam`` (TSDF voxel blocks, projective ICP against the ray-cast
model) with its example's settings (examples/python/t_reconstruction_system/dense_slam.py). It is
a bench-only optional extra: ``pip install open3d-cpu`` (on Debian it needs ``libusb-1.0-0``).
The frames come through TivNe's own readers and ``data.*`` view (association, undistortion, resize,
depth clipping), so both systems see identical inputs. Prints one ``FIGURES {json}`` line: ATE
(SE(3)-aligned), RPE, s/frame (the SLAM calls only, as TivNe's s/frame), frames, threads, peak RSS.
"""

from __future__ import annotations

import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


MAP_DELTA = 30  # frames between the poses of a pair for the relative-motion map (about 1 s at 30 Hz)


def trajectory_figures(est: np.ndarray, gt: np.ndarray) -> dict[str, float]:
    """ATE (SE(3)-aligned) and per-frame RPE of (N, 4, 4) estimated vs GT c2w poses, and the linear
    map of the relative translations over ``MAP_DELTA`` frames (``relative_motion_map``: a map
    shared by both systems points at the calibration or the ground truth)."""
    from tivne.metrics.trajectory import absolute_trajectory_error, relative_motion_map, relative_pose_error

    ate = absolute_trajectory_error(est, gt, align="se3")
    rpe = relative_pose_error(est, gt, delta=1)
    out = {
        "ate_rmse_m": float(ate.rmse), "ate_mean_m": float(ate.mean), "ate_max_m": float(ate.max),
        "rpe_trans_rmse_m": float(rpe.trans_rmse_m), "rpe_rot_rmse_deg": float(rpe.rot_rmse_deg),
    }
    try:  # the table labels these MAP_DELTA-frame figures: a shorter run has none
        motion = relative_motion_map(est, gt, delta=MAP_DELTA)
    except ValueError:  # MAP_DELTA frames or fewer, or motion along a line or plane only
        return out
    return out | {"map_sv_max": float(motion.singular_values[0]), "map_sv_min": float(motion.singular_values[-1]),
                  "map_trans_rmse_m": motion.trans_rmse_m, "map_fit_rmse_m": motion.fit_rmse_m}


def run_open3d(view, voxel_size: float = 3.0 / 512, depth_max: float = 3.0) -> dict[str, float]:
    """Open3D's dense SLAM over a SequenceView (frames with rgb (H, W, 3) in [0, 1], depth (H, W) m,
    gt_pose (4, 4) c2w or None). voxel_size and depth_max: the example's defaults."""
    import open3d as o3d
    import open3d.core as o3c

    device = o3c.Device("CPU:0")
    K = o3c.Tensor(view.intrinsics.K().double().numpy())
    T = o3c.Tensor(np.identity(4))
    model = o3d.t.pipelines.slam.Model(voxel_size, 16, 40000, T, device)
    h, w = view.intrinsics.height, view.intrinsics.width
    frame, raycast = o3d.t.pipelines.slam.Frame(h, w, K, device), o3d.t.pipelines.slam.Frame(h, w, K, device)
    poses, gt, spent = [], [], 0.0
    depth_scale, trunc, odo_thr = 1000.0, 8.0, 0.1
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
    out = trajectory_figures(np.stack([poses[i] for i in keep]), np.stack([gt[i] for i in keep])) if len(keep) >= 3 else {}
    return out | {"frames": len(view), "s_per_frame": spent / len(view)}


def config_view(overrides: list[str]):
    """The SequenceView TivNe's ``run`` would read for these Hydra overrides."""
    from hydra import compose, initialize_config_dir
    from hydra.utils import instantiate
    from omegaconf import OmegaConf

    from data_modules.sequence import SequenceView
    from tivne.cli import register_defaults

    register_defaults()  # conf/config.yaml's defaults come from tivne/config.py
    with initialize_config_dir(config_dir=str(REPO / "conf"), version_base="1.3"):
        cfg = compose("config", overrides=overrides)
    return SequenceView(instantiate(cfg.dataset), **OmegaConf.to_container(cfg.data, resolve=True))


def figures_line(figures: dict) -> str:
    figures["peak_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    return "FIGURES " + json.dumps(figures)


def spawn(cmd: list[str], threads: int) -> tuple[dict | None, str]:
    """Run a child that prints a ``FIGURES {json}`` line, with ``threads`` OpenMP threads and the
    passive wait policy (set before its libraries load). Returns its figures (None on failure) and
    the reason of a failure."""
    env = dict(os.environ, OMP_WAIT_POLICY="PASSIVE", OMP_NUM_THREADS=str(threads))
    proc = subprocess.run(cmd, capture_output=True, text=True, env=env)
    lines = [line for line in proc.stdout.splitlines() if line.startswith("FIGURES ")]
    if proc.returncode != 0 or not lines:
        return None, f"exit {proc.returncode}: {(proc.stderr.strip().splitlines() or [''])[-1]}"
    return json.loads(lines[-1][len("FIGURES "):]), ""


def open3d_on_config(overrides: list[str], threads: int) -> tuple[dict | None, str]:
    """Open3D on the frames of a TivNe config, in its own process (its own RSS, its own threads)."""
    try:
        import open3d  # noqa: F401
    except ImportError as exc:  # absent, or present without a system library it loads (e.g. libusb-1.0)
        return None, f"open3d does not import ({exc}; pip install open3d-cpu, and its system libraries)"
    return spawn([sys.executable, __file__, *overrides], threads)


def main() -> None:
    view = config_view(sys.argv[1:])
    figures = run_open3d(view) | {"threads": int(os.environ.get("OMP_NUM_THREADS", "0") or 0)}
    print(figures_line(figures))


if __name__ == "__main__":
    main()
