"""Diagnose tracking on a sequence with ground truth: is the error the tracker's or the map's?

    python bench/diagnose_tracking.py dataset=tum dataset.root=../shared/data/tum_fr1_rpy_tail dataset.camera=fr1 data.max_frames=60
    python bench/diagnose_tracking.py --mode slam ...        # the normal loop: tracked poses build the map
    python bench/diagnose_tracking.py --iters 10,30,100 ...  # convergence of the field tracker per frame

``--mode oracle`` (default) builds the map with the ground-truth poses and, on every frame, runs
the configured tracker from the motion model's prediction (computed from the ground-truth poses of
the two previous frames) against that map, records its error and then *uses the ground-truth pose*:
tracking errors cannot compound, so what is left is the tracker's own error against a map made
without tracking error. ``--mode slam`` runs the normal loop and records the per-frame error of the
tracked poses (after aligning the first pose). With ``--iters`` each frame is also tracked with
those iteration counts from the same start, showing whether the optimiser has converged.

Per frame it prints: rotation / translation between consecutive GT poses, error of the initial
guess, error after tracking, the tracker's inlier ratio; then percentiles. The map's own quality
is the depth L1 of the field rendered at the ground-truth pose (before the frame is mapped).
Extra arguments are Hydra overrides of conf/config.yaml. Figures are printed, never asserted.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import sys
import tempfile
import warnings
from pathlib import Path

import numpy as np
import torch
from hydra import compose, initialize_config_dir
from hydra.utils import instantiate

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from data_modules.sequence import SequenceView  # noqa: E402
from tivne.geometry import invert_pose  # noqa: E402
from tivne.render.rays import View  # noqa: E402
from tivne.render.renderer import render_image  # noqa: E402
from tivne.slam.run import TrainSettings, build_system  # noqa: E402
from tivne.slam.tracking import frozen, predict_pose  # noqa: E402


def pose_error(T: torch.Tensor, ref: torch.Tensor) -> tuple[float, float]:
    """(rotation error degrees, translation error cm) of T against ref."""
    D = invert_pose(ref.double()) @ T.double()
    cos = ((D[:3, :3].trace() - 1) / 2).clamp(-1, 1)
    return math.degrees(float(torch.arccos(cos))), 100 * float(D[:3, 3].norm())


def map_depth_error(system, view: View) -> float:
    """Median |rendered - observed| depth (cm) at ``view.pose`` over every 4th pixel with depth."""
    with frozen(system.field):
        _, depth = render_image(system.field, view, system.K, system.render_cfg, stride=4)
    obs = view.depth[::4, ::4]
    ok = (obs > 0) & (depth > 0)
    return 100 * float((depth - obs).abs()[ok].median()) if ok.any() else float("nan")


class Probe:
    """Replaces the system's tracking step: tracks, records, and (oracle mode) returns the GT pose."""

    def __init__(self, system, gt: list[torch.Tensor], oracle: bool, iters: list[int]) -> None:
        self.system, self.gt, self.oracle, self.iters = system, gt, oracle, iters
        self.tracked_track = system._track
        self.rows: list[dict[str, float]] = []

    def __call__(self, k: int, tau: float, frame, mask):
        s = self.system
        if k == 0:
            return torch.eye(4, device=s.device), {}
        gt_k = self.gt[k].to(s.device)
        prior = [p.to(s.device).float() for p in self.gt[max(0, k - 2) : k]] if self.oracle else s.tracked
        init = predict_pose(prior, s.tracking_cfg.motion_model)
        row = {"frame": k, "step_deg": pose_error(self.gt[k], self.gt[k - 1])[0], "step_cm": pose_error(self.gt[k], self.gt[k - 1])[1]}
        row["init_deg"], row["init_cm"] = pose_error(init, gt_k)
        row["map_cm"] = map_depth_error(s, View(k, s.last_mapped_tau, frame.rgb, frame.depth, mask, gt_k.float()))
        saved, cfg = s.tracked, s.tracking_cfg
        s.tracked = prior
        try:
            pose, stats = self.tracked_track(k, tau, frame, mask)
            for n in self.iters:
                s.tracking_cfg = dataclasses.replace(s.tracking_cfg, iters=n)
                p_n, _ = self.tracked_track(k, tau, frame, mask)
                row[f"deg@{n}"], row[f"cm@{n}"] = pose_error(p_n, gt_k)
        finally:
            s.tracked, s.tracking_cfg = saved, cfg
        row["deg"], row["cm"] = pose_error(pose, gt_k)
        row["inliers"] = float(stats.get("track/inlier_ratio", float("nan")))
        self.rows.append(row)
        return (gt_k.float() if self.oracle else pose), stats


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--mode", choices=("oracle", "slam"), default="oracle")
    parser.add_argument("--iters", default="", help="comma-separated extra tracking iteration counts, e.g. 10,30,100")
    parser.add_argument("--every", type=int, default=1, help="print every n-th frame's row")
    args, overrides = parser.parse_known_args()
    with initialize_config_dir(config_dir=str(REPO / "conf"), version_base="1.3"):
        cfg = compose("config", overrides=["trainer.progress_bar=false", "output.image_every=0", *overrides])
    settings = TrainSettings.from_config(cfg)
    view = SequenceView(instantiate(cfg.dataset), **dict(cfg.data))
    frames = [view[i] for i in range(len(view))]
    if any(f.gt_pose is None for f in frames):
        raise SystemExit("error: every frame needs a ground-truth pose")
    g0 = frames[0].gt_pose.double()
    gt = [invert_pose(g0) @ f.gt_pose.double() for f in frames]  # in the first camera's frame
    system = build_system(cfg, view.intrinsics, tempfile.mkdtemp(prefix="tivne-diag-"), settings)
    probe = Probe(system, gt, args.mode == "oracle", [int(x) for x in args.iters.split(",") if x])
    system._track = probe
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # self.log without a Trainer
        for k, frame in enumerate(frames):
            system.training_step(frame, k)
    report(probe.rows, args.every)


def report(rows: list[dict[str, float]], every: int) -> None:
    if not rows:
        return
    keys = list(rows[0])
    print(" ".join(f"{k:>8}" for k in keys))
    for row in rows[::every]:
        print(" ".join(f"{row[k]:8.3f}" if isinstance(row[k], float) else f"{row[k]:8d}" for k in keys))
    print("\npercentiles (50 / 90 / max):")
    for k in keys[1:]:
        v = np.array([r[k] for r in rows], dtype=float)
        v = v[np.isfinite(v)]
        if len(v):
            print(f"  {k:>10}: {np.percentile(v, 50):8.3f} {np.percentile(v, 90):8.3f} {v.max():8.3f}")


if __name__ == "__main__":
    main()
