"""Frame-to-model odometry references, measured (issue 20): does a new reference's depth rendered from
the field track better than the frame's own depth?

    python bench/frame_to_model.py --preset tum                 # the shared fr1/rpy tail, both modes
    python bench/frame_to_model.py --preset 7scenes --frames 100 --modes frame agree

Each mode is one whole SLAM run of TivNe's default (``tracking.overlap=false``, so the field is current
when a reference is made; the poses are the default's either way). Whenever the tracker makes a new
reference, its pyramid is rebuilt from a depth image chosen by the mode:

* ``frame``: the frame's own depth (the default tracker; the control);
* ``agree``: the field's depth rendered at the reference's pose (every pixel, the samples around the
  frame's depth) where it lies within 3 σ_pair of the frame's own, the frame's depth elsewhere;
* ``model``: the field's depth wherever it rendered one.

Prints ATE RMSE, lost frames, seconds per rendered reference, the share of pixels where the field
agrees with the frame and the median of the field's depth minus the frame's (the mean over references).
A diagnostic: it wraps ``Tracker.update_reference`` in this process only. Figures are printed, never
asserted.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import torch

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from bench.real import PRESETS, run_tivne  # noqa: E402
from data_modules.sensor import kinect_depth_sigma  # noqa: E402
from tivne.render.renderer import render_image  # noqa: E402
from tivne.slam import run as slam_run  # noqa: E402
from tivne.slam.tracking import tracker as tracking  # noqa: E402
from tivne.slam.tracking.field import frozen  # noqa: E402
from tivne.utils import RunFailed  # noqa: E402


def reference_depth(rendered: torch.Tensor, frame: torch.Tensor, mode: str) -> tuple[torch.Tensor, float, float]:
    """The depth (H, W) a new reference is built from, the share of the frame's valid pixels where the
    field's ``rendered`` depth (H, W; 0 = none) lies within 3 σ_pair of the ``frame``'s own, and the
    median of rendered − frame depth (metres) where both have one."""
    sigma_pair = math.sqrt(2.0) * kinect_depth_sigma(frame)
    both = (rendered > 0) & (frame > 0)
    agree = both & ((rendered - frame).abs() <= 3.0 * sigma_pair)
    share = float(agree.sum()) / max(int((frame > 0).sum()), 1)
    offset = float((rendered - frame)[both].median()) if bool(both.any()) else math.nan
    use = {"frame": torch.zeros_like(agree), "agree": agree, "model": rendered > 0}[mode]
    return torch.where(use, rendered, frame).to(frame.dtype), share, offset


def measure(root: str, camera: str, frames: int, intrinsics, colour_camera, mode: str) -> dict[str, float]:
    """One SLAM run whose new references take their depth from ``mode`` (see the module docstring)."""
    loops, spent, shares, offsets = [], [], [], []
    build_loop, update_reference = slam_run.build_loop, tracking.Tracker.update_reference

    def keep_loop(*args, **kwargs):
        loops.append(build_loop(*args, **kwargs))
        return loops[-1]

    def update(self, view, K, result, is_keyframe, poses=None):
        switched = update_reference(self, view, K, result, is_keyframe, poses)
        if mode == "frame" or not switched or self.reference is None or self.reference.frame_id != view.frame_id:
            return switched
        start, loop = time.perf_counter(), loops[-1]
        with frozen(loop.field), torch.no_grad():
            _, rendered = render_image(loop.field, view, K, loop.mapper.render)
        depth, share, offset = reference_depth(rendered, view.depth, mode)
        old = self.reference.source
        self.reference.source = tracking.PyramidSource(old.rgb, depth, old.dynamic, old.K)
        self.reference.pyramid = self.reference.source.pyramid(self.recovery)
        spent.append(time.perf_counter() - start)
        shares.append(share)
        offsets.append(100 * offset)
        return switched

    slam_run.build_loop, tracking.Tracker.update_reference = keep_loop, update
    try:
        figures = run_tivne(root, camera, frames, ["tracking.overlap=false"], intrinsics, colour_camera)
    finally:
        slam_run.build_loop, tracking.Tracker.update_reference = build_loop, update_reference
    mean = lambda xs: sum(xs) / len(xs) if xs else math.nan  # noqa: E731
    return {"ate_rmse_cm": 100 * figures["ate_rmse_m"], "lost": figures["tracking_lost"], "rendered_references": len(spent),
            "s_per_rendered_reference": mean(spent), "field_agrees_share": mean(shares),
            "median_field_minus_frame_cm": mean(offsets)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--preset", choices=sorted(PRESETS), default="tum")
    parser.add_argument("--data-dir", default=str(REPO.parent / "shared" / "data"), help="the folder holding the shared tails")
    parser.add_argument("--frames", type=int, default=0, help="first n frames (0 = all)")
    parser.add_argument("--modes", nargs="+", choices=("frame", "agree", "model"), default=["frame", "agree"])
    args = parser.parse_args()
    folder, camera, intrinsics, colour_camera = PRESETS[args.preset]
    for mode in args.modes:
        try:
            figures = measure(str(Path(args.data_dir) / folder), camera, args.frames, intrinsics, colour_camera, mode)
        except RunFailed as err:  # a run that loses most frames stops; that is a figure too
            print(f"{args.preset} {mode}: the run failed: {err}")
            continue
        print(f"{args.preset} {mode}: " + ", ".join(f"{k} {v:.3f}" if isinstance(v, float) else f"{k} {v}" for k, v in figures.items()))


if __name__ == "__main__":
    main()
