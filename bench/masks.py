"""Motion-mask quality (and optionally SLAM ATE) per provider on a synthetic sequence (the moving cube
by default, any preset of the synthetic scene family with --scene).

    python bench/masks.py [--providers dataset,geometric,none] [--frames 60] [--width 160 --height 120]
                          [--scene crossing] [--no-slam] [--maskrcnn-weights PATH] [--set [provider:]key=value ...]

e.g. ``--set geometric:masks.provider.stride=2`` (every 2nd pixel at 160x120 ~ every 8th at 640x480).

Each provider runs inside the real SLAM loop (``tivne.train.run(..., masks=...)``) wrapped in
:class:`tivne.masks.base.RecordingMasks`, which records the mask it returned for every frame; masks are
then compared with the GT masks: per-frame IoU, precision and recall, averaged over all frames and
over frames with t >= 1 s (the second second on). ``--no-slam`` evaluates providers that need no
tracked pose on the frames alone (no ATE). Prints one table; ``--json`` writes the numbers.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from tivne.masks.base import RecordingMasks  # noqa: E402
from tivne.masks.settings import build_provider


def frame_scores(pred: torch.Tensor | None, gt: torch.Tensor) -> tuple[float, float, float]:
    """IoU, precision, recall of one (H, W) bool mask against GT (None = nothing dynamic).

    Conventions: IoU = 1 when both are empty; precision = 1 when nothing is predicted; recall = 1
    when GT is empty.
    """
    p = torch.zeros_like(gt) if pred is None else pred.bool()
    inter = float((p & gt).sum())
    union = float((p | gt).sum())
    n_p, n_g = float(p.sum()), float(gt.sum())
    iou = inter / union if union > 0 else 1.0
    precision = inter / n_p if n_p > 0 else 1.0
    recall = inter / n_g if n_g > 0 else 1.0
    return iou, precision, recall


def summarise(rec: RecordingMasks, t0_after: float = 1.0) -> dict[str, float]:
    rows = []
    t0 = min(rec.timestamps.values())
    for idx in sorted(rec.masks):
        gt = rec.gt[idx]
        if gt is None:
            continue
        rows.append((rec.timestamps[idx] - t0, *frame_scores(rec.masks[idx], gt)))
    a = np.array(rows, dtype=np.float64)
    late = a[a[:, 0] >= t0_after - 1e-9]
    out = {"frames": len(a), "iou": a[:, 1].mean(), "precision": a[:, 2].mean(), "recall": a[:, 3].mean()}
    if len(late):
        out |= {"frames_t1": len(late), "iou_t1": late[:, 1].mean(), "precision_t1": late[:, 2].mean(), "recall_t1": late[:, 3].mean()}
    timings = getattr(rec.inner, "timings_ms", None)
    if timings:
        out["ms_per_frame"] = float(np.mean(timings))
    return out


def compose(name: str, args: argparse.Namespace):
    from hydra import compose as hcompose
    from hydra import initialize_config_dir

    scene = [] if args.scene is None else ["dataset=synthetic", f"dataset.scene={args.scene}"]
    overrides = [
        *scene,
        f"masks={name}",
        f"dataset.width={args.width}",
        f"dataset.height={args.height}",
        f"data.max_frames={args.frames}",
        "output.evaluate=false",
        "output.image_every=0",
        "mesh.resolution=0.1",
        "trainer.progress_bar=false",
        f"runtime.threads={args.threads}",
        *[o.split(":", 1)[1] if ":" in o.split("=", 1)[0] else o for o in args.set
          if ":" not in o.split("=", 1)[0] or o.split(":", 1)[0] == name],
    ]
    if name == "maskrcnn":
        overrides.append(f"masks.provider.weights={args.maskrcnn_weights}")
    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        return hcompose(config_name="config", overrides=overrides)


def run_slam(name: str, args: argparse.Namespace) -> dict[str, float]:
    from omegaconf import OmegaConf

    from tivne.cli import register_defaults
    from tivne.slam.run import run

    register_defaults()  # the config nodes conf/*.yaml compose onto

    cfg = compose(name, args)
    rec = RecordingMasks(build_provider(OmegaConf.to_container(cfg.masks.provider, resolve=True)))
    start = time.perf_counter()
    with tempfile.TemporaryDirectory() as run_dir:
        metrics = run(cfg, run_dir, masks=rec)
    out = summarise(rec)
    out["ate_rmse_m"] = metrics.get("ate_rmse_m")
    out["slam_s"] = time.perf_counter() - start
    return out


def run_frames(name: str, args: argparse.Namespace) -> dict[str, float]:
    from hydra.utils import instantiate
    from omegaconf import OmegaConf

    from data_modules.sequence import SequenceView

    cfg = compose(name, args)
    view = SequenceView(instantiate(cfg.dataset), **OmegaConf.to_container(cfg.data, resolve=True))
    rec = RecordingMasks(build_provider(OmegaConf.to_container(cfg.masks.provider, resolve=True)))
    if rec.needs_tracked_pose:
        raise SystemExit(f"masks={name} needs the SLAM loop; drop --no-slam")
    for i in range(len(view)):
        rec(view[i], None)
    return summarise(rec)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--providers", default="dataset,geometric,none")
    parser.add_argument("--frames", type=int, default=60)
    parser.add_argument("--width", type=int, default=160)
    parser.add_argument("--height", type=int, default=120)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--scene", default=None, help="synthetic preset (dataset=synthetic dataset.scene=SCENE); default dataset=cube")
    parser.add_argument("--no-slam", action="store_true", help="no SLAM (no ATE); pose-free providers only")
    parser.add_argument("--maskrcnn-weights", default=None, help="state dict of maskrcnn_resnet50_fpn (adds maskrcnn)")
    parser.add_argument("--set", action="append", default=[],
                        help="extra Hydra override, repeatable; 'NAME:key=value' applies to provider NAME only")
    parser.add_argument("--json", default=None, help="write the results here")
    args = parser.parse_args(argv)
    names = [n for n in args.providers.split(",") if n]
    if args.maskrcnn_weights and "maskrcnn" not in names:
        try:
            import torchvision  # noqa: F401

            names.append("maskrcnn")
        except Exception as exc:  # noqa: BLE001
            print(f"skipping maskrcnn: torchvision unavailable ({exc})")
    results = {}
    for name in names:
        results[name] = (run_frames if args.no_slam else run_slam)(name, args)
        print(name, json.dumps({k: (round(v, 4) if isinstance(v, float) else v) for k, v in results[name].items()}), flush=True)
    print(f"\n{args.scene or 'cube'}, {args.width}x{args.height}, {args.frames} frames; mean over frames (t>=1s: from the second second on)")
    header = f"{'provider':<10} {'IoU':>6} {'P':>6} {'R':>6} | {'IoU≥1s':>6} {'P≥1s':>6} {'R≥1s':>6} | {'ms/fr':>6} {'ATE cm':>7}"
    print(header)
    for name, r in results.items():
        f = lambda k: "   n/a" if r.get(k) is None or (isinstance(r.get(k), float) and math.isnan(r[k])) else f"{r[k]:6.3f}"  # noqa: E731
        ate = r.get("ate_rmse_m")
        ms = r.get("ms_per_frame")
        print(f"{name:<10} {f('iou')} {f('precision')} {f('recall')} | {f('iou_t1')} {f('precision_t1')} {f('recall_t1')} | "
              f"{'' if ms is None else f'{ms:6.1f}':>6} {'' if ate is None else f'{100 * ate:7.2f}':>7}")
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=2, default=float) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
