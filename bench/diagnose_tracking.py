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
from pathlib import Path

import numpy as np
import torch
from hydra import compose, initialize_config_dir
from hydra.utils import instantiate
from omegaconf import OmegaConf

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from data_modules.sequence import SequenceView  # noqa: E402
from tivne.cli import register_defaults  # noqa: E402
from tivne.geometry import invert_pose  # noqa: E402
from tivne.masks.settings import build_provider
from tivne.render.rays import View  # noqa: E402
from tivne.render.renderer import render_image  # noqa: E402
from tivne.slam.run import TrainSettings, build_loop  # noqa: E402
from tivne.slam.tracking.field import frozen, predict_pose  # noqa: E402

register_defaults()  # the config nodes conf/*.yaml compose onto


def pose_error(T: torch.Tensor, ref: torch.Tensor) -> tuple[float, float]:
    """(rotation error degrees, translation error cm) of T against ref."""
    D = invert_pose(ref.double()) @ T.double()
    cos = ((D[:3, :3].trace() - 1) / 2).clamp(-1, 1)
    return math.degrees(float(torch.arccos(cos))), 100 * float(D[:3, 3].norm())


def map_depth_error(loop, view: View) -> float:
    """Median |rendered - observed| depth (cm) at ``view.pose`` over every 4th pixel with depth."""
    with frozen(loop.field):
        _, depth = render_image(loop.field, view, loop.K, loop.mapper.render, stride=4)
    obs = view.depth[::4, ::4]
    ok = (obs > 0) & (depth > 0)
    return 100 * float((depth - obs).abs()[ok].median()) if ok.any() else float("nan")


class GTPoses:
    """A PoseLookup over ground-truth poses (oracle mode: the motion model starts from GT)."""

    def __init__(self, poses: list[torch.Tensor], times: list[float]) -> None:
        self.poses, self.times = poses, times

    def pose(self, frame_id: int) -> torch.Tensor:
        return self.poses[frame_id]

    def recent(self, n: int) -> list[torch.Tensor]:
        return self.poses[-n:]

    def recent_times(self, n: int) -> list[float]:
        return self.times[-n:]


class Probe:
    """Wraps the loop's tracker: tracks, records, and (oracle mode) returns the GT pose."""

    def __init__(self, loop, gt: list[torch.Tensor], oracle: bool, iters: list[int]) -> None:
        self.loop, self.gt, self.oracle, self.iters = loop, gt, oracle, iters
        self.track = loop.tracker.track
        self.rows: list[dict[str, float]] = []

    def __call__(self, index, frame, tau, mask, field, poses, K, last_mapped_tau, generator=None):
        tracker = self.loop.tracker
        if index == 0:
            return self.track(index, frame, tau, mask, field, poses, K, last_mapped_tau, generator)
        gt_k = self.gt[index].to(frame.depth.device)
        lookup = GTPoses([p.to(frame.depth.device) for p in self.gt[:index]], poses.recent_times(index)) if self.oracle else poses
        init = predict_pose([p.float() for p in lookup.recent(2)], tracker.cfg.motion_model)
        row = {"frame": index, "step_deg": pose_error(self.gt[index], self.gt[index - 1])[0], "step_cm": pose_error(self.gt[index], self.gt[index - 1])[1]}
        row["init_deg"], row["init_cm"] = pose_error(init, gt_k)
        row["map_cm"] = map_depth_error(self.loop, View(index, last_mapped_tau, frame.rgb, frame.depth, mask, gt_k.float()))
        result = self.track(index, frame, tau, mask, field, lookup, K, last_mapped_tau, generator)
        cfg = tracker.field_cfg
        try:
            for n in self.iters:
                tracker.field_cfg = dataclasses.replace(cfg, iters=n)
                r_n = self.track(index, frame, tau, mask, field, lookup, K, last_mapped_tau, generator)
                row[f"deg@{n}"], row[f"cm@{n}"] = pose_error(r_n.pose, gt_k)
        finally:
            tracker.field_cfg = cfg
        row["deg"], row["cm"] = pose_error(result.pose, gt_k)
        row["inliers"] = result.field.inlier_ratio if result.field is not None else float("nan")
        self.rows.append(row)
        return dataclasses.replace(result, pose=gt_k.float()) if self.oracle else result


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
    loop = build_loop(settings, view.intrinsics, build_provider(OmegaConf.to_container(cfg.masks.provider, resolve=True)), int(cfg.seed))
    probe = Probe(loop, gt, args.mode == "oracle", [int(x) for x in args.iters.split(",") if x])
    loop.tracker.track = probe
    for frame in frames:
        loop.step(frame)
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
