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
"""

from __future__ import annotations

import argparse
import json
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


def overrides(scene: str, source: str, frames: int, size: tuple[int, int], threads: int) -> list[str]:
    return ["dataset=synthetic", f"dataset.scene={scene}", f"dataset.seed={SCENE_SEED}", f"dataset.num_frames={frames}",
            f"dataset.width={size[0]}", f"dataset.height={size[1]}", "objects.track=true", f"objects.source={source}",
            f"masks={source}", "output.evaluate=false", "mapping.final_iters=0", "mesh.resolution=0.1",
            "trainer.progress_bar=false", "output.image_every=0", f"runtime.threads={threads}"]


def child(run_dir: str, args: list[str]) -> None:
    """Run one sequence, then print its object figures as one JSON line."""
    from hydra import compose, initialize_config_dir
    from hydra.utils import instantiate

    from data_modules.sequence import SequenceView
    from tivne.cli import register_defaults
    from tivne.evaluation.objects import object_section
    from tivne.evaluation.run import world_from_slam
    from tivne.slam.outputs import RunDir
    from tivne.slam.run import run

    register_defaults()  # the config nodes conf/*.yaml compose onto

    with initialize_config_dir(config_dir=str(REPO / "conf"), version_base="1.3"):
        cfg = compose("config", overrides=args)
    metrics = run(cfg, Path(run_dir))
    view = SequenceView(instantiate(cfg.dataset), **dict(cfg.data))
    world, _ = world_from_slam("first_camera", view, None)
    figures = object_section(RunDir(run_dir), view, world)
    keep = ("s_per_frame_after_first", "objects_s_per_frame", "ate_rmse_m", "objects_written", "frames")
    print("FIGURES " + json.dumps(figures | {k: metrics.get(k) for k in keep}))


def run_one(scene: str, source: str, ns: argparse.Namespace) -> dict | None:
    run_dir = tempfile.mkdtemp(prefix=f"tivne-objects-{scene}-{source}-")
    args = overrides(scene, source, ns.frames, (ns.width, ns.height), ns.threads)
    proc = subprocess.run([sys.executable, __file__, "--child", run_dir, *args], capture_output=True, text=True,
                          env=dict(os.environ, OMP_WAIT_POLICY="PASSIVE"))
    shutil.rmtree(run_dir, ignore_errors=True)  # the figures are in its stdout; the run folder is ~50 MB
    lines = [line for line in proc.stdout.splitlines() if line.startswith("FIGURES ")]
    if proc.returncode != 0 or not lines:
        print(f"{scene}/{source}: failed (exit {proc.returncode}): {(proc.stderr.strip().splitlines() or ['?'])[-1]}", file=sys.stderr)
        return None
    print(f"done: {scene}/{source}", file=sys.stderr, flush=True)
    return json.loads(lines[-1][len("FIGURES "):])


def objects_cell(r: dict) -> str:
    names = sorted(k[len("object_"): -len("_rot_deg")] for k in r if k.startswith("object_") and k.endswith("_rot_deg"))
    cells = []
    for n in names:
        ate, rot = r.get(f"object_{n}_ate_m"), r.get(f"object_{n}_rot_deg")
        cells.append(f"{n} –" if ate is None else f"{n} {100 * ate:.2f}/{rot:.2f} ({r.get(f'object_{n}_poses')})")
    return "; ".join(cells) or "–"


def table(results: dict[tuple[str, str], dict | None]) -> str:
    lines = ["| preset | masks | per object: ATE cm / rot deg (poses) | tracks written | camera ATE cm | s/frame | objects s/frame |",
             "|---|---|---|---|---|---|---|"]
    for (scene, source), r in results.items():
        if r is None:
            lines.append(f"| {scene} | {source} | failed | | | | |")
            continue
        f = lambda v, s=1.0, d=3: "–" if v is None else f"{v * s:.{d}f}"  # noqa: E731
        lines.append(f"| {scene} | {source} | {objects_cell(r)} | {r.get('objects_written')} | {f(r.get('ate_rmse_m'), 100, 3)} | "
                     f"{f(r.get('s_per_frame_after_first'))} | {f(r.get('objects_s_per_frame'))} |")
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
    parser.add_argument("--child", nargs=argparse.REMAINDER, help=argparse.SUPPRESS)
    ns = parser.parse_args()
    if ns.child:
        return child(ns.child[0], ns.child[1:])
    todo = [(s, src) for s in ns.only.split(",") for src in ns.sources.split(",")]
    with ThreadPoolExecutor(max_workers=ns.jobs) as pool:
        found = list(pool.map(lambda key: run_one(*key, ns), todo))
    results = dict(zip(todo, found))
    print(f"\nbench/objects.py --frames {ns.frames} --width {ns.width} --height {ns.height}")
    print(table(results))
    if ns.json:
        Path(ns.json).write_text(json.dumps({f"{a}/{b}": r for (a, b), r in results.items()}, indent=2) + "\n")


if __name__ == "__main__":
    main()
