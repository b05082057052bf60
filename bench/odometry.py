"""Benchmark: dense RGB-D odometry alone (tivne/slam/odometry.py) on a TUM-layout sequence.

    python bench/odometry.py                                  # fr1/rpy tail from ../shared/data, keyframe mode
    python bench/odometry.py --mode frame --frames 100        # frame-to-frame, first 100 frames
    python bench/odometry.py --no-photometric --levels 4      # geometric-only, 4 pyramid levels

Poses are chained (c2w_cur = c2w_ref @ T_ref_cur) from the first frame's ground-truth pose; the initial
guess of every pair is a constant-velocity prediction. ``keyframe`` mode tracks against the last keyframe
and makes the current frame the new keyframe when its overlap or inlier ratio with the keyframe drops
below the thresholds (a failed keyframe pair is re-tracked against the previous frame). Prints ATE
(SE(3)-aligned to ground truth), the per-frame relative pose error, s/frame (wall and process CPU
time of pyramid + tracking, not image loading), the number of frames the odometry flagged as not ok
and those with a low inlier ratio.
Figures are printed, never asserted.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import torch

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from data_modules.tum import TUMSequence  # noqa: E402
from tivne.geometry import invert_pose, orthonormalize_pose, se3_exp, se3_log  # noqa: E402
from tivne.metrics.trajectory import absolute_trajectory_error, relative_pose_error  # noqa: E402
from tivne.slam.tracking.odometry import OdometryConfig, frame_pyramid, track_pyramids  # noqa: E402


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--root", default=str(REPO.parent / "shared" / "data" / "tum_fr1_rpy_tail"), help="TUM-layout folder")
    p.add_argument("--camera", default="fr1")
    p.add_argument("--preset", choices=("tum", "7scenes"), default=None, help="a shared real tail (root, camera, intrinsics as bench/real.py)")
    p.add_argument("--intrinsics", type=float, nargs=4, default=None, metavar=("FX", "FY", "CX", "CY"), help="with --camera custom")
    p.add_argument("--colour-camera", type=float, nargs=4, default=None, metavar=("FX", "FY", "CX", "CY"),
                   help="colour not registered to depth: its camera (dataset.colour_camera)")
    p.add_argument("--frames", type=int, default=0, help="frames to use after striding (0 = all)")
    p.add_argument("--stride", type=int, default=1)
    p.add_argument("--mode", choices=("frame", "keyframe"), default="keyframe")
    p.add_argument("--no-photometric", action="store_true")
    p.add_argument("--no-geometric", action="store_true")
    p.add_argument("--levels", type=int, default=3)
    p.add_argument("--iterations", type=int, default=OdometryConfig.max_iterations)
    p.add_argument("--robust", choices=("huber", "cauchy"), default="huber")
    p.add_argument("--max-points", type=int, default=OdometryConfig.max_points, help="finest level (0 = all)")
    p.add_argument("--coarse-points-ratio", type=float, default=OdometryConfig.coarse_points_ratio,
                   help="each coarser level takes this many times fewer points")
    p.add_argument("--outlier-sigmas", type=float, default=OdometryConfig.outlier_sigmas)
    p.add_argument("--no-brightness-offset", action="store_true")
    p.add_argument("--photometric-weight", type=float, default=OdometryConfig.photometric_weight)
    p.add_argument("--geometric-scale", choices=("data", "model"), default=OdometryConfig.geometric_scale)
    p.add_argument("--tol-pixels", type=float, default=OdometryConfig.tol_pixels, help="update tolerance in pixels")
    p.add_argument("--keyframe-overlap", type=float, default=0.7, help="new keyframe below this overlap")
    p.add_argument("--keyframe-inlier", type=float, default=0.5, help="new keyframe below this inlier ratio")
    p.add_argument("--motion-prior", choices=("velocity", "none"), default="velocity")
    p.add_argument("--sync-depth", action="store_true",
                   help="model the depth/colour timestamp offset (depth moved by the velocity over the offset)")
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--device", default="cpu")
    p.add_argument("--json", default=None, help="also write the figures to this JSON file")
    args = p.parse_args(argv)
    if args.preset:
        from bench.real import PRESETS

        folder, args.camera, args.intrinsics, preset_colour = PRESETS[args.preset]
        args.colour_camera = args.colour_camera or preset_colour
        args.root = str(REPO.parent / "shared" / "data" / folder)
    return args


def predict(poses: list[torch.Tensor], use_velocity: bool) -> torch.Tensor:
    """Constant-velocity c2w prediction of the next frame from the chained poses (4, 4) float64."""
    if use_velocity and len(poses) >= 2:
        return orthonormalize_pose(poses[-1] @ invert_pose(poses[-2]) @ poses[-1])
    return poses[-1].clone()


def rgb_depth_motion(c2w_a: torch.Tensor, c2w_b: torch.Tensor, dt_ab: float, offset: float) -> torch.Tensor:
    """T_rgb_depth (4, 4) of a frame whose depth is ``offset`` s after its colour, at the body velocity a -> b."""
    xi = se3_log(invert_pose(c2w_a) @ c2w_b) * (offset / dt_ab)
    return se3_exp(xi)


def run(args: argparse.Namespace) -> dict[str, float]:
    torch.set_num_threads(args.threads)
    kwargs = dict(zip(("fx", "fy", "cx", "cy"), args.intrinsics)) if args.intrinsics else {}
    seq = TUMSequence(root=args.root, camera=args.camera, colour_camera=args.colour_camera, **kwargs)
    ids = list(range(0, len(seq), args.stride))
    ids = ids[: args.frames] if args.frames > 0 else ids
    cfg = OdometryConfig(
        levels=args.levels, max_iterations=args.iterations, photometric=not args.no_photometric,
        geometric=not args.no_geometric, robust=args.robust, max_points=args.max_points,
        coarse_points_ratio=args.coarse_points_ratio,
        outlier_sigmas=args.outlier_sigmas, brightness_offset=not args.no_brightness_offset,
        tol_pixels=args.tol_pixels, photometric_weight=args.photometric_weight, geometric_scale=args.geometric_scale,
    )
    K = seq.intrinsics.K(dtype=torch.float32, device=args.device)
    first = seq[ids[0]]
    c2w = [first.gt_pose.double() if first.gt_pose is not None else torch.eye(4, dtype=torch.float64)]
    gt = [first.gt_pose]
    prev_pyr = kf_pyr = frame_pyramid(first.rgb.to(args.device), first.depth.to(args.device), K, cfg)
    kf_pose = c2w[0]
    times, offsets = [seq.timestamps[ids[0]]], seq.depth_timestamps - seq.timestamps
    prev_cd = kf_cd = cur_cd = None  # T_rgb_depth of the previous frame, the keyframe, the current frame
    not_ok = low_inlier = keyframes = 0
    track_s = cpu_s = 0.0
    for i in ids[1:]:
        frame = seq[i]
        t0, c0 = time.perf_counter(), time.process_time()
        pyr = frame_pyramid(frame.rgb.to(args.device), frame.depth.to(args.device), K, cfg)
        guess = predict(c2w, args.motion_prior == "velocity")
        if args.sync_depth and len(c2w) >= 2:
            cur_cd = rgb_depth_motion(c2w[-2], c2w[-1], times[-1] - times[-2], float(offsets[i]))
        ref_pyr, ref_pose, ref_cd = (kf_pyr, kf_pose, kf_cd) if args.mode == "keyframe" else (prev_pyr, c2w[-1], prev_cd)
        res = track_pyramids(ref_pyr, pyr, invert_pose(ref_pose) @ guess, cfg, ref_cd, cur_cd)
        fell_back = args.mode == "keyframe" and not res.ok and ref_pyr is not prev_pyr
        if fell_back:  # the keyframe is lost: track against the previous frame instead
            ref_pyr, ref_pose, ref_cd = prev_pyr, c2w[-1], prev_cd
            res = track_pyramids(ref_pyr, pyr, invert_pose(ref_pose) @ guess, cfg, ref_cd, cur_cd)
        track_s, cpu_s = track_s + time.perf_counter() - t0, cpu_s + time.process_time() - c0
        not_ok += not res.ok
        low_inlier += res.inlier_ratio < cfg.min_inlier_ratio
        pose = orthonormalize_pose(ref_pose @ res.T_ref_cur.cpu())
        if args.sync_depth:  # with this frame's own motion known, re-estimate its offset motion for later use
            cur_cd = rgb_depth_motion(c2w[-1], pose, float(seq.timestamps[i]) - times[-1], float(offsets[i]))
        c2w.append(pose)
        times.append(float(seq.timestamps[i]))
        gt.append(frame.gt_pose)
        if args.mode == "keyframe" and (fell_back or res.overlap < args.keyframe_overlap or res.inlier_ratio < args.keyframe_inlier):
            kf_pyr, kf_pose, kf_cd = pyr, pose, cur_cd
            keyframes += 1
        prev_pyr, prev_cd = pyr, cur_cd
    have = [k for k, g in enumerate(gt) if g is not None]
    est, ref = torch.stack([c2w[k] for k in have]).numpy(), torch.stack([gt[k] for k in have]).double().numpy()
    ate, rpe = absolute_trajectory_error(est, ref), relative_pose_error(est, ref, delta=1)
    return {
        "frames": len(ids),
        "ate_rmse_m": ate.rmse,
        "ate_mean_m": ate.mean,
        "ate_max_m": ate.max,
        "rpe_trans_rmse_m": rpe.trans_rmse_m,  # per frame (frames without ground truth are skipped)
        "rpe_rot_rmse_deg": rpe.rot_rmse_deg,
        "s_per_frame": track_s / max(len(ids) - 1, 1),
        "cpu_s_per_frame": cpu_s / max(len(ids) - 1, 1),
        "not_ok_frames": not_ok,
        "low_inlier_frames": low_inlier,
        "keyframes": keyframes + 1 if args.mode == "keyframe" else len(ids),
    }


def main() -> None:
    args = parse_args()
    figures = run(args)
    print(f"odometry on {Path(args.root).name}: mode={args.mode} levels={args.levels} "
          f"photometric={not args.no_photometric} geometric={not args.no_geometric} robust={args.robust}")
    for key, val in figures.items():
        print(f"  {key:<18} {val:.4f}" if isinstance(val, float) else f"  {key:<18} {val}")
    if args.json:
        Path(args.json).write_text(json.dumps({**vars(args), **figures}, indent=2))


if __name__ == "__main__":
    main()
