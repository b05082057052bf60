"""Per-object trajectory error of ``objects.track=true`` on the synthetic presets, dataset vs geometric masks.

    python bench/objects.py                        # every rigid preset, 60 frames at 320x240, both sources
    python bench/objects.py --only cube,crossing --sources dataset --jobs 2
    python bench/objects.py --json out.json        # also write the figures

Each (preset, source) runs ``tivne.train`` in its own process with the default config plus
``objects.track=true objects.source=<source> masks=<source>`` (the masks the field and camera use
follow the source), without the final mapping pass and with coarse meshes (neither touches the
online object tracks). Then ``tivne.evaluation.objects.object_section`` scores objects/<id>.txt
against the GT object poses (first-frame aligned ATE and rotation error). Columns per object:
ATE cm / rotation deg (poses); the run's s/frame and the objects' own share of it. Figures are
printed, never asserted.

    python bench/objects.py --gt-cameras --noise-seeds 10,11,12,13,14 --only fast_turn

``--gt-cameras``: the object tracker alone (``tivne.slam.objects.ObjectTracker``) on the GT camera
poses and the dataset's instance masks, no field and no camera tracking: seconds per sequence, the
object tracking's own error. ``--noise-seeds``: sensor-noise draws (``dataset.seed``) of the one
layout (``--scene-seed``, ``dataset.scene_seed``, 1 by default); one row per draw, then the median and the worst over the draws
per object. One draw of a blurred, symmetric object is a lottery ticket (fast_turn's passing
cylinder, tracker alone, 5 draws: 0.26-10.0 cm, 6-54°), so compare such figures over draws.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shutil
import subprocess
import sys
import tempfile
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

RIGID = ("cube", "big_fast", "orbit_ball", "crossing", "three_objects", "fast_turn", "stop_and_go")
SCENE_SEED = 1  # as bench/suite.py: one fixed draw of each preset's layout


def overrides(scene: str, source: str, frames: int, size: tuple[int, int], threads: int, noise: int = SCENE_SEED,
              layout: int = SCENE_SEED) -> list[str]:
    return ["dataset=synthetic", f"dataset.scene={scene}", f"dataset.seed={noise}", f"dataset.scene_seed={layout}",
            f"dataset.num_frames={frames}",
            f"dataset.width={size[0]}", f"dataset.height={size[1]}", "objects.track=true", f"objects.source={source}",
            f"masks={source}", "output.evaluate=false", "mapping.final_iters=0", "mesh.resolution=0.1",
            "trainer.progress_bar=false", "output.image_every=0", f"runtime.threads={threads}"]


def compose_config(args: list[str]):
    """The run config of ``args`` (:func:`overrides`), composed as ``tivne.train`` composes it."""
    from hydra import compose, initialize_config_dir

    from tivne.cli import register_defaults

    register_defaults()  # the config nodes conf/*.yaml compose onto
    with initialize_config_dir(config_dir=str(REPO / "conf"), version_base="1.3"):
        return compose("config", overrides=args)


def child(run_dir: str, args: list[str]) -> None:
    """Run one sequence, then print its object figures as one JSON line."""
    from hydra.utils import instantiate

    from data_modules.sequence import SequenceView
    from tivne.evaluation.objects import object_section
    from tivne.evaluation.run import world_from_slam
    from tivne.slam.outputs import RunDir
    from tivne.slam.run import run

    cfg = compose_config(args)
    metrics = run(cfg, Path(run_dir))
    view = SequenceView(instantiate(cfg.dataset), **dict(cfg.data))
    world, _ = world_from_slam("first_camera", view, None)
    figures = object_section(RunDir(run_dir), view, world)
    keep = ("s_per_frame_after_first", "objects_s_per_frame", "ate_rmse_m", "objects_written", "frames")
    print("FIGURES " + json.dumps(figures | {k: metrics.get(k) for k in keep}))


def tracker_alone(run_dir: str, args: list[str]) -> None:
    """The object tracker alone on the sequence of ``args`` (:func:`overrides`): GT camera poses, the
    dataset's instance masks; then its object figures as one JSON line, as :func:`child`."""
    import time

    import numpy as np
    import torch
    from hydra.utils import instantiate

    from data_modules.sequence import SequenceView
    from tivne.config import ObjectsConfig
    from tivne.evaluation.objects import object_section
    from tivne.slam.objects import ObjectTracker
    from tivne.slam.outputs import RunDir

    cfg = compose_config(args)
    torch.set_num_threads(int(cfg.runtime.threads))
    dataset = instantiate(cfg.dataset)
    tracker = ObjectTracker(ObjectsConfig(track=True), dataset.intrinsics.K())
    seconds = 0.0
    for i in range(len(dataset)):
        frame = dataset[i]
        start = time.perf_counter()
        tracker.step(frame, torch.as_tensor(dataset.camera_pose(i)), float(frame.timestamp), frame.instances)
        seconds += time.perf_counter() - start
    tracker.write(RunDir(run_dir))
    figures = object_section(RunDir(run_dir), SequenceView(dataset), np.eye(4))  # the tracks are in the GT world
    print("FIGURES " + json.dumps(figures | {"objects_s_per_frame": seconds / len(dataset), "frames": len(dataset),
                                            "objects_written": len(tracker.written_tracks())}))


def run_one(scene: str, source: str, noise: int, ns: argparse.Namespace) -> dict | None:
    run_dir = tempfile.mkdtemp(prefix=f"tivne-objects-{scene}-{source}-")
    args = overrides(scene, source, ns.frames, (ns.width, ns.height), ns.threads, noise, ns.scene_seed)
    mode = "--alone" if ns.gt_cameras else "--child"
    proc = subprocess.run([sys.executable, __file__, mode, run_dir, *args], capture_output=True, text=True,
                          env=dict(os.environ, OMP_WAIT_POLICY="PASSIVE"))
    shutil.rmtree(run_dir, ignore_errors=True)  # the figures are in its stdout; the run folder is ~50 MB
    lines = [line for line in proc.stdout.splitlines() if line.startswith("FIGURES ")]
    if proc.returncode != 0 or not lines:
        last = (proc.stderr.strip().splitlines() or ["?"])[-1]
        print(f"{scene}/{source}/{noise}: failed (exit {proc.returncode}): {last}", file=sys.stderr)
        return None
    print(f"done: {scene}/{source}/{noise}", file=sys.stderr, flush=True)
    return json.loads(lines[-1][len("FIGURES "):])


def object_names(r: dict) -> set[str]:
    """The GT object names of one run's figures (``object_<name>_rot_deg`` keys)."""
    return {k[len("object_"): -len("_rot_deg")] for k in r if k.startswith("object_") and k.endswith("_rot_deg")}


def objects_cell(r: dict) -> str:
    cells = []
    for n in sorted(object_names(r)):
        ate, rot = r.get(f"object_{n}_ate_m"), r.get(f"object_{n}_rot_deg")
        cells.append(f"{n} –" if ate is None else f"{n} {100 * ate:.2f}/{rot:.2f} ({r.get(f'object_{n}_poses')})")
    return "; ".join(cells) or "–"


def table(results: dict[tuple[str, str, int], dict | None]) -> str:
    lines = ["| preset | masks | noise seed | per object: ATE cm / rot deg (poses) | tracks written | camera ATE cm | s/frame "
             "| objects s/frame |", "|---|---|---|---|---|---|---|---|"]
    for (scene, source, noise), r in results.items():
        if r is None:
            lines.append(f"| {scene} | {source} | {noise} | failed | | | | |")
            continue
        f = lambda v, s=1.0, d=3: "–" if v is None else f"{v * s:.{d}f}"  # noqa: E731
        lines.append(f"| {scene} | {source} | {noise} | {objects_cell(r)} | {r.get('objects_written')} | "
                     f"{f(r.get('ate_rmse_m'), 100, 3)} | {f(r.get('s_per_frame_after_first'))} | {f(r.get('objects_s_per_frame'))} |")
    return "\n".join(lines)


def spread(results: dict[tuple[str, str, int], dict | None]) -> str:
    """Per preset, masks and object: the median and the worst ATE cm / rot deg over the noise draws
    (an unmatched object counts as the worst)."""
    import statistics

    lines = ["| preset | masks | object | draws | ATE cm median / worst | rot deg median / worst |", "|---|---|---|---|---|---|"]
    for scene, source in dict.fromkeys((a, b) for a, b, _ in results):
        runs = [r for (a, b, _), r in results.items() if (a, b) == (scene, source) and r is not None]
        for name in sorted(set().union(*map(object_names, runs))):
            ate = [math.inf if r.get(f"object_{name}_ate_m") is None else 100 * r[f"object_{name}_ate_m"] for r in runs]
            rot = [math.inf if r.get(f"object_{name}_rot_deg") is None else r[f"object_{name}_rot_deg"] for r in runs]
            cm = lambda v: f"{v:.2f}" if math.isfinite(v) else "unmatched"  # noqa: E731
            lines.append(f"| {scene} | {source} | {name} | {len(runs)} | {cm(statistics.median(ate))} / {cm(max(ate))} | "
                         f"{cm(statistics.median(rot))} / {cm(max(rot))} |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--only", default=",".join(RIGID))
    parser.add_argument("--sources", default="dataset,geometric")
    parser.add_argument("--frames", type=int, default=60)
    parser.add_argument("--width", type=int, default=320)
    parser.add_argument("--height", type=int, default=240)
    parser.add_argument("--jobs", type=int, default=1, help="runs side by side")
    parser.add_argument("--threads", type=int, default=2, help="torch threads per run")
    parser.add_argument("--json", default=None)
    parser.add_argument("--noise-seeds", default=str(SCENE_SEED), help="comma-separated sensor-noise draws (dataset.seed)")
    parser.add_argument("--scene-seed", type=int, default=SCENE_SEED, help="the presets' layout draw (dataset.scene_seed)")
    parser.add_argument("--gt-cameras", action="store_true", help="the object tracker alone on GT cameras (dataset masks)")
    parser.add_argument("--child", nargs=argparse.REMAINDER, help=argparse.SUPPRESS)
    parser.add_argument("--alone", nargs=argparse.REMAINDER, help=argparse.SUPPRESS)
    ns = parser.parse_args()
    if ns.child or ns.alone:
        return (child if ns.child else tracker_alone)((ns.child or ns.alone)[0], (ns.child or ns.alone)[1:])
    sources = ["dataset"] if ns.gt_cameras else ns.sources.split(",")  # geometric masks come from the SLAM run
    todo = [(s, src, int(n)) for s in ns.only.split(",") for src in sources for n in ns.noise_seeds.split(",")]
    with ThreadPoolExecutor(max_workers=ns.jobs) as pool:
        found = list(pool.map(lambda key: run_one(*key, ns), todo))
    results = dict(zip(todo, found))
    mode = " --gt-cameras" if ns.gt_cameras else ""
    print(f"\nbench/objects.py{mode} --frames {ns.frames} --width {ns.width} --height {ns.height} --noise-seeds {ns.noise_seeds} "
          f"--scene-seed {ns.scene_seed}")
    print(table(results))
    if len(ns.noise_seeds.split(",")) > 1:
        print("\n" + spread(results))
    if ns.json:
        Path(ns.json).write_text(json.dumps({f"{a}/{b}/{n}": r for (a, b, n), r in results.items()}, indent=2) + "\n")


if __name__ == "__main__":
    main()
