"""Real RGB-D data, side by side: TivNe and Open3D's dense SLAM on the same frames, in one run.

    python bench/real.py                                   # the shared TUM fr1/rpy tail, all frames
    python bench/real.py --frames 100                      # the first 100 frames
    python bench/real.py --first 200 --frames 150          # frames 200-349: another stretch of the recording
    python bench/real.py --drop 150 199                    # frames 150-199 dropped (a stalled recorder)
    python bench/real.py --starts 0 100 200 --frames 200   # three stretches, each system on each, and their spread
    python bench/real.py --preset 7scenes                  # the shared 7-Scenes redkitchen tail
    python bench/real.py --root path/to/rgbd_dataset_freiburg3_walking_xyz --camera fr3
    python bench/real.py --only tivne tracking.method=field  # one system; extra args: TivNe overrides

Both systems read the frames through TivNe's TUM reader (association, undistortion of colour and
depth onto one K), so they see identical inputs. Each runs in its own process, so its peak RSS is
its own. Open3D is the frame-to-model dense SLAM of ``open3d.t.pipelines.slam`` (TSDF voxel blocks,
projective ICP against the ray-cast model) with its example's settings; it is a bench-only optional
extra: ``pip install open3d-cpu`` (on Debian it needs ``libusb-1.0-0``).

Prints ATE RMSE / mean / max (SE(3)-aligned to ground truth), RPE per frame, s/frame and peak RSS for
both, and their ratios. Also the relative translations over ``MAP_DELTA`` (30) frames against ground truth, before and
after the one linear map that fits them best, and that map's singular values
(``tivne.metrics.trajectory.relative_motion_map``): where both systems share a map far from the identity,
that part of the error is the calibration's or the ground truth's, not either tracker's. Figures are
printed, never asserted.

One stretch's ATE is a weak figure: the tracker's discrete decisions (a reference switch, a frame
refused) turn small differences into millimetres. On the fr1 tail, the robust scales read from 3500
instead of 4096 samples of the same residuals moved the tracking-only ATE 1.250 -> 1.329 cm. ``--starts``
runs both systems on several stretches and prints each, their mean, median and worst, and the ratio of
the means.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
DEFAULT_ROOT = REPO.parent / "shared" / "data" / "tum_fr1_rpy_tail"
sys.path.insert(0, str(REPO))

from bench.peer import MAP_DELTA, figures_line, run_open3d, spawn, trajectory_figures  # noqa: E402

# The shared real tails (../shared/data/README.md beside the checkout): root folder name, camera, its
# intrinsics and, for colour not registered to depth, the colour camera (dataset.colour_camera).
PRESETS = {
    "tum": ("tum_fr1_rpy_tail", "fr1", None, None),
    # The depth camera: the Kinect defaults 7-Scenes documents. The colour camera: not registered (the
    # dataset says so), estimated from the shared tail by `python -m data_modules.inspect ... colour_camera=true
    # max_sampled=40` (colour edges on depth edges; the Kinect's nominal colour camera is 525, 525, 319.5, 239.5).
    "7scenes": ("7scenes_redkitchen_tail", "custom", (585.0, 585.0, 320.0, 240.0), (527.0, 531.0, 315.0, 238.0)),
}


def camera_overrides(camera: str, intrinsics: tuple[float, float, float, float] | None, colour_camera=None) -> list[str]:
    """dataset.* overrides of the camera (a preset name, or custom with fx, fy, cx, cy) and of an unregistered colour camera."""
    out = [f"dataset.camera={camera}"]
    if intrinsics is not None:
        out += [f"dataset.{k}={v}" for k, v in zip(("fx", "fy", "cx", "cy"), intrinsics)]
    if colour_camera is not None:
        out.append(f"dataset.colour_camera=[{','.join(str(v) for v in colour_camera)}]")
    return out


def load_view(root: str, camera: str, frames: int, intrinsics: tuple[float, float, float, float] | None = None, colour_camera=None,
              select: dict | None = None):
    from data_modules.sequence import SequenceView
    from data_modules.tum import TUMSequence

    kwargs = dict(zip(("fx", "fy", "cx", "cy"), intrinsics)) if intrinsics is not None else {}
    seq = TUMSequence(root=root, camera=camera, colour_camera=None if colour_camera is None else list(colour_camera), **kwargs)
    return SequenceView(seq, max_frames=frames or None, **(select or {}))


def selection(args: argparse.Namespace) -> dict:
    """The stretch of the recording both systems see (``data.*`` settings / SequenceView arguments)."""
    return {"first_frame": args.first} | ({"drop_frames": list(args.drop)} if args.drop else {})


def run_tivne(root: str, camera: str, frames: int, overrides: list[str], intrinsics=None, colour_camera=None,
              select: dict | None = None) -> dict[str, float]:
    from hydra import compose, initialize_config_dir

    from data_modules.tables import read_tum_trajectory
    from tivne.cli import register_defaults
    from tivne.slam.run import run
    register_defaults()  # the config nodes conf/*.yaml compose onto

    args = ["dataset=tum", f"dataset.root={root}", *camera_overrides(camera, intrinsics, colour_camera), "trainer.progress_bar=false", "output.image_every=0"]
    if frames:
        args.append(f"data.max_frames={frames}")
    args += [f"data.{key}={value}".replace(" ", "") for key, value in (select or {}).items()]
    with initialize_config_dir(config_dir=str(REPO / "conf"), version_base="1.3"):
        cfg = compose("config", overrides=[*args, *overrides])
    out = Path(tempfile.mkdtemp(prefix="tivne-real-"))
    metrics = run(cfg, out)
    view = load_view(root, camera, frames, intrinsics, colour_camera, select)
    ts, est = read_tum_trajectory(out / "trajectory.txt")
    gt = {float(view.timestamps[i]): view[i].gt_pose for i in range(len(view))}
    keep = [i for i, t in enumerate(ts) if gt.get(float(t)) is not None]
    figures = trajectory_figures(est.numpy()[keep], np.stack([gt[float(ts[i])].double().numpy() for i in keep]))
    keys = ("frames", "s_per_frame", "track_ms_per_frame", "map_ms_per_iter", "final_refine_s", "tracking_lost", "frames_without_tracking")
    return figures | {k: metrics.get(k) for k in keys} | {"run_dir": str(out)}


def child(args: argparse.Namespace, overrides: list[str]) -> None:
    """Run one system in this process and print its figures (plus peak RSS) as one JSON line."""
    intrinsics = tuple(args.intrinsics) if args.intrinsics else None
    colour = tuple(args.colour_camera) if args.colour_camera else None
    if args.only == "open3d":
        figures = run_open3d(load_view(args.root, args.camera, args.frames, intrinsics, colour, selection(args)))
    else:
        figures = run_tivne(args.root, args.camera, args.frames, overrides, intrinsics, colour, selection(args))
    print(figures_line(figures))


def run_child(system: str, args: argparse.Namespace, overrides: list[str]) -> dict[str, float] | None:
    cmd = [sys.executable, __file__, "--child", "--only", system, "--root", args.root, "--camera", args.camera,
           "--frames", str(args.frames), "--first", str(args.first)] + (["--drop", *map(str, args.drop)] if args.drop else [])
    if args.intrinsics:
        cmd += ["--intrinsics", *map(str, args.intrinsics)]
    if args.colour_camera:
        cmd += ["--colour-camera", *map(str, args.colour_camera)]
    figures, why = spawn([*cmd, *overrides], args.threads)
    if figures is None:
        print(f"{system}: failed ({why})", file=sys.stderr)
    return figures


def table(results: dict[str, dict[str, float] | None]) -> str:
    rows = [
        ("ATE RMSE cm", "ate_rmse_m", 100), ("ATE mean cm", "ate_mean_m", 100), ("ATE max cm", "ate_max_m", 100),
        ("RPE trans cm/frame", "rpe_trans_rmse_m", 100), ("RPE rot deg/frame", "rpe_rot_rmse_deg", 1),
        (f"{MAP_DELTA}-frame rel. translation error cm", "map_trans_rmse_m", 100), ("the same after its best linear map, cm", "map_fit_rmse_m", 100),
        ("that map's largest σ", "map_sv_max", 1), ("that map's smallest σ", "map_sv_min", 1),
        ("s/frame", "s_per_frame", 1), ("peak RSS MB", "peak_rss_mb", 1), ("frames", "frames", 1),
    ]
    names = [n for n, r in results.items() if r is not None]
    lines = ["| figure | " + " | ".join(names) + (" | TivNe / Open3D |" if len(names) == 2 else " |"), "|---" * (len(names) + 1 + (len(names) == 2)) + "|"]
    for label, key, scale in rows:
        vals = [results[n].get(key) for n in names]
        cells = ["n/a" if v is None else f"{v * scale:.3f}" for v in vals]
        if len(names) == 2:
            cells.append(f"{vals[0] / vals[1]:.2f}" if None not in vals and vals[1] else "n/a")
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def spread_table(windows: dict[int, dict[str, dict | None]], systems: list[str]) -> str:
    """ATE RMSE cm of each system (columns) on each stretch (rows, by its start), then their mean, median and worst."""
    names = ["TivNe" if s == "tivne" else "Open3D" for s in systems]
    ate = {s: [None if w.get(s) is None else 100 * w[s]["ate_rmse_m"] for w in windows.values()] for s in systems}
    lines = ["| start | " + " | ".join(f"{n} ATE cm" for n in names) + " |", "|---" * (len(names) + 1) + "|"]

    def cell(system: str, figures: dict | None) -> str:
        if figures is None:
            return "failed"
        lost = f" ({figures.get('tracking_lost') or 0} lost)" if system == "tivne" else ""
        return f"{100 * figures['ate_rmse_m']:.3f}{lost}"

    for start, w in windows.items():
        lines.append(f"| {start} | " + " | ".join(cell(s, w.get(s)) for s in systems) + " |")
    for label, fn in (("mean", np.mean), ("median", np.median), ("worst", np.max)):
        cells = [f"{fn([v for v in ate[s] if v is not None]):.3f}" if any(v is not None for v in ate[s]) else "n/a" for s in systems]
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    if len(systems) == 2 and all(v is not None for s in systems for v in ate[s]):
        lines.append(f"\nTivNe / Open3D, ratio of the means: {np.mean(ate[systems[0]]) / np.mean(ate[systems[1]]):.2f}")
    return "\n".join(lines)


def stretches(args: argparse.Namespace, systems: list[str], overrides: list[str]) -> None:
    """Each system on each stretch (``--starts``), one table of their ATE and its spread; all figures in --json."""
    first, windows = args.first, {}
    for start in args.starts:
        args.first = first + start
        windows[start] = {s: run_child(s, args, overrides) for s in systems}
    print(f"\nbench/real.py on {args.root}: stretches of {args.frames or 'all remaining'} frames from frames "
          f"{', '.join(str(first + s) for s in args.starts)}; TivNe overrides: {' '.join(overrides) or 'none'}")
    print(spread_table(windows, systems))
    if args.json:
        Path(args.json).write_text(json.dumps({str(k): v for k, v in windows.items()}, indent=2) + "\n")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--preset", choices=sorted(PRESETS), default=None, help="a shared real tail: its root, camera and intrinsics")
    parser.add_argument("--data-dir", default=str(DEFAULT_ROOT.parent), help="the folder holding the shared tails (for --preset)")
    parser.add_argument("--root", default=str(DEFAULT_ROOT), help="a TUM-layout folder")
    parser.add_argument("--camera", default="fr1")
    parser.add_argument("--intrinsics", type=float, nargs=4, default=None, metavar=("FX", "FY", "CX", "CY"), help="with --camera custom")
    parser.add_argument("--colour-camera", type=float, nargs=4, default=None, metavar=("FX", "FY", "CX", "CY"),
                        help="colour not registered to depth: its camera (dataset.colour_camera)")
    parser.add_argument("--threads", type=int, default=2, help="OpenMP threads of each system's process")
    parser.add_argument("--frames", type=int, default=0, help="first n frames (0 = all)")
    parser.add_argument("--first", type=int, default=0, help="start at this frame of the recording (0-based)")
    parser.add_argument("--drop", type=int, nargs=2, default=None, metavar=("FIRST", "LAST"), help="leave these frames out")
    parser.add_argument("--starts", type=int, nargs="+", default=None, metavar="S",
                        help="several stretches: from frame first + S each, --frames long (0 = to the end)")
    parser.add_argument("--only", choices=("tivne", "open3d"), default=None)
    parser.add_argument("--json", default=None, help="also write the figures here")
    parser.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args, overrides = parser.parse_known_args()
    if args.preset:
        folder, args.camera, args.intrinsics, preset_colour = PRESETS[args.preset]
        args.colour_camera = args.colour_camera or preset_colour
        args.root = str(Path(args.data_dir) / folder)
    if args.child:
        return child(args, overrides)
    systems = [args.only] if args.only else ["tivne", "open3d"]
    if args.starts:
        return stretches(args, systems, overrides)
    results = {s: run_child(s, args, overrides) for s in systems}
    print(f"\nbench/real.py on {args.root} ({args.frames or 'all'} frames from frame {args.first}"
          f"{f', frames {args.drop[0]}-{args.drop[1]} dropped' if args.drop else ''}; "
          f"TivNe overrides: {' '.join(overrides) or 'none'})")
    print(table({"TivNe" if k == "tivne" else "Open3D": v for k, v in results.items()}))
    print(json.dumps(results))
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=2) + "\n")


if __name__ == "__main__":
    main()
