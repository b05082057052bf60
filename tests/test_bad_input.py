"""Bad input, table-driven, across every command: what a user sees is exit status 2 (3 for a run
whose result is unusable), exactly one ``error:`` line on stderr, no traceback, and nothing that was
there before is lost or changed (a refused run dir keeps its .hydra/, results and metrics.json).

Each case runs the real command line (``python -m <cli> <args>``) through ``runpy`` in one of two
worker processes, so the interpreter and torch start twice, not once per case; stdout and stderr are
captured at the file-descriptor level. A read-only run directory is made so by its mode bits, or, for
root (whom mode bits do not stop), by a read-only bind mount (skipped where mounting is not
allowed). A full disk is injected in the worker (``patch``): a writer that raises ENOSPC.

``python tests/test_bad_input.py`` prints the table "case | command | exit | message" of what each
case does now.
"""

from __future__ import annotations

import argparse
import contextlib
import hashlib
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "tests" / "data_modules"))
sys.path.insert(0, str(REPO / "tests"))
from cli_worker import run_module  # noqa: E402
from fixtures import make_cofusion, make_folder, make_klg, make_tum, random_pose, write_exr, write_png16  # noqa: E402

SMOKE = ("experiment=smoke", "dataset.width=80", "dataset.height=60", "dataset.cache_dir=null")
MODULES = {"train": "tivne.train", "inspect": "data_modules.inspect", "mesh": "tivne.mesh", "evaluate": "tivne.evaluate", "make_masks": "tivne.make_masks",
           "report": "tivne.report", "collect": "tivne.collect"}


@dataclass(frozen=True)
class Case:
    """One command with bad input. ``args`` may name ``{d}``, the case's own folder; ``setup``
    builds its inputs there first; ``message``: a substring of the error line (or alternatives);
    ``patch``: a failure injected in the worker (see :data:`PATCHES`); ``read_only``: ``{d}/run``
    is made read-only before the command runs."""

    name: str
    cli: str
    args: tuple[str, ...]
    message: str | tuple[str, ...]
    code: int = 2
    setup: Callable[[Path], None] | None = None
    patch: str | None = None
    read_only: bool = False


# ------------------------------------------------------------------------------------ setups
TEMPLATE: dict[str, Path] = {}  # "base": the worker's folder; "run": its finished run


def finished_run(run: Path, complete: bool = True) -> None:
    """A copy of a finished tiny run (made once per worker with the real CLI); ``complete=False``
    marks it as interrupted."""
    if "run" not in TEMPLATE:
        template = TEMPLATE["base"] / "template"
        code, _, err = invoke("train", [*SMOKE, f"hydra.run.dir={template}"])
        assert code == 0, err
        TEMPLATE["run"] = template
    shutil.copytree(TEMPLATE["run"], run)
    if not complete:
        metrics = json.loads((run / "metrics.json").read_text())
        (run / "metrics.json").write_text(json.dumps(metrics | {"complete": False}))


def interrupted_run(d: Path) -> None:
    finished_run(d / "run", complete=False)


def run_then(change: Callable[[Path], None], complete: bool = True) -> Callable[[Path], None]:
    def setup(d: Path) -> None:
        finished_run(d / "run", complete)
        change(d / "run")
    return setup


def truncate_checkpoint(run: Path) -> None:
    ckpt = run / "checkpoints" / "slam.pt"
    ckpt.write_bytes(ckpt.read_bytes()[: ckpt.stat().st_size // 2])


def garbage_checkpoint(run: Path) -> None:
    (run / "checkpoints" / "slam.pt").write_bytes(b"this is not a checkpoint\n" * 40)


def folder(change: Callable[[Path], None] | None = None, **kwargs) -> Callable[[Path], None]:
    """A 3-frame folder-layout sequence in ``d/seq`` (then ``change(seq)``)."""
    def setup(d: Path) -> None:
        make_folder(d / "seq", masks=False, **kwargs)
        if change is not None:
            change(d / "seq")
    return setup


def empty_folder(d: Path) -> None:
    for sub in ("rgb", "depth"):
        (d / "seq" / sub).mkdir(parents=True)
    (d / "seq" / "intrinsics.txt").write_text("20 21 15.5 11.5\n")


def nan_depth_cofusion(d: Path) -> None:
    """Co-Fusion frames whose EXR depth is NaN everywhere."""
    import numpy as np

    make_cofusion(d / "seq", n=5, masks=None)
    for exr in (d / "seq" / "depth_noise").glob("*.exr"):
        write_exr(exr, {"Y": np.full((24, 32), np.nan, np.float32)})


def truncated_klg(d: Path) -> None:
    make_klg(d / "log.klg", modes=(("raw", "raw"),) * 3)
    data = (d / "log.klg").read_bytes()
    (d / "log.klg").write_bytes(data[:-500])


def tum_with(change: Callable[[Path], None]) -> Callable[[Path], None]:
    def setup(d: Path) -> None:
        import numpy as np

        t0 = 1341846313.5
        make_tum(d / "seq", n=3, depth_offsets=(0.0,), gt=[(t0 + k / 30, random_pose(np.random.default_rng(k))) for k in range(3)])
        change(d / "seq")
    return setup


def swap_rgb_lines(seq: Path) -> None:
    lines = (seq / "rgb.txt").read_text().splitlines()
    lines[3], lines[4] = lines[4], lines[3]
    (seq / "rgb.txt").write_text("\n".join(lines) + "\n")


def corrupt_groundtruth(seq: Path) -> None:
    with open(seq / "groundtruth.txt", "a") as fh:
        fh.write("1341846313.6 1.0 2.0 three 0 0 0 1\n")


def write_file(rel: str, data: bytes | str) -> Callable[[Path], None]:
    def change(root: Path) -> None:
        (root / rel).write_bytes(data.encode() if isinstance(data, str) else data)
    return change


def remove(rel: str) -> Callable[[Path], None]:
    def change(root: Path) -> None:
        p = root / rel
        shutil.rmtree(p) if p.is_dir() else p.unlink()
    return change


def small_depth(seq: Path) -> None:
    import numpy as np

    write_png16(seq / "depth" / "1.png", np.full((12, 16), 1000, np.uint16))


def a_file(d: Path) -> None:
    (d / "masks").write_text("a file where the output folder should be\n")


def empty_dir(name: str) -> Callable[[Path], None]:
    return lambda d: (d / name).mkdir()


def saved_config(change: Callable[[dict, Path], None], complete: bool = True) -> Callable[[Path], None]:
    """A finished run whose .hydra/config.yaml is then changed by ``change(config, d)``, next to
    ``d/precious.txt``: the file a hostile config targets (the table checks it is left as it was)."""
    import yaml

    def edit(run: Path) -> None:
        (run.parent / "precious.txt").write_text("keep me\n")
        path = run / ".hydra" / "config.yaml"
        config = yaml.safe_load(path.read_text())
        change(config, run.parent)
        path.write_text(yaml.safe_dump(config))
    return run_then(edit, complete)


def open_for_writing(config: dict, d: Path) -> None:
    config["dataset"] = {"_target_": "builtins.open", "_args_": [str(d / "precious.txt"), "w"]}


def nested_open(config: dict, d: Path) -> None:
    config["dataset"] = {"_target_": "data_modules.folder.FolderSequence", "root": str(d),
                         "intrinsics": {"_target_": "builtins.open", "_args_": [str(d / "precious.txt"), "w"]}}


def fractional_stride(config: dict, d: Path) -> None:
    config["data"]["stride"] = 1.5


HOLDERS: list = []  # processes holding a run folder's lock, ended after the cases


def _hold(run: str, held) -> None:
    from tivne.runlock import acquire

    acquire(run)
    held.set()
    time.sleep(600)


def held_by_another_run(d: Path) -> None:
    """``d/run`` locked by a live process (the run folder of a run still going), forked from the
    worker so that it does not import torch and Lightning again."""
    import multiprocessing

    (d / "run").mkdir()
    ctx = multiprocessing.get_context("fork")
    held = ctx.Event()
    proc = ctx.Process(target=_hold, args=(str(d / "run"), held), daemon=True)
    proc.start()
    HOLDERS.append(proc)
    assert held.wait(60), "the holder did not take the lock"


def sweep_dir(d: Path) -> None:
    (d / "sweep").mkdir()


# ------------------------------------------------------------------------------------- cases
TRAIN_RUN = ("hydra.run.dir={d}/run",)
KLG = ("dataset=teddy", "dataset.root={d}/log.klg", "dataset.width=32", "dataset.height=24", "dataset.cx=15.5", "dataset.cy=11.5")
FOLDER = ("dataset=folder", "dataset.root={d}/seq", "masks=none")
MESH_RUN, EVAL_RUN = ("run_dir={d}/run",), ("run_dir={d}/run",)
READ_ONLY_ERRORS = ("Permission denied", "Read-only file system")
READ_ONLY = tuple("run: " + m for m in READ_ONLY_ERRORS)
TINY = ("dataset.num_frames=3", "dataset.width=80", "dataset.height=60", "dataset.cache_dir=null")

CASES: tuple[Case, ...] = (
    # train: settings (one line naming the key, before any data is read)
    Case("non-numeric setting", "train", (*SMOKE, "field_tracking.iters=abc", *TRAIN_RUN), "field_tracking.iters='abc': must be an integer"),
    Case("setting out of range", "train", (*SMOKE, "mapping.lr_pose=-1", *TRAIN_RUN), "mapping.lr_pose=-1.0: must be > 0"),
    Case("NaN setting", "train", (*SMOKE, "render.truncation=nan", *TRAIN_RUN), "render.truncation=nan: must be a finite number"),
    Case("unknown choice", "train", (*SMOKE, "tracking.method=magic", *TRAIN_RUN), "tracking.method='magic': must be one of"),
    Case("unknown setting", "train", (*SMOKE, "+mapping.speed=2", *TRAIN_RUN), "mapping.speed: unknown setting"),
    Case("negative checkpoint_every", "train", (*SMOKE, "output.checkpoint_every=-1", *TRAIN_RUN), "output.checkpoint_every=-1: must be >= 0"),
    Case("resume not a boolean", "train", (*SMOKE, "resume=maybe", *TRAIN_RUN), "resume='maybe': must be a boolean"),
    Case("resume and overwrite", "train", (*SMOKE, "resume=true", "overwrite=true", *TRAIN_RUN), "resume=true and overwrite=true: choose one"),
    Case("CUDA on a CPU-only torch", "train", (*SMOKE, "trainer.accelerator=cuda", *TRAIN_RUN), "CUDA is not available"),
    Case("mesh time outside the sequence", "train", (*SMOKE, "mesh.times=[99]", *TRAIN_RUN), "outside the recorded range"),
    Case("stride 0", "train", (*SMOKE, "data.stride=0", *TRAIN_RUN), "data.stride=0: must be >= 1"),
    Case("fractional stride", "train", (*SMOKE, "data.stride=1.5", *TRAIN_RUN), "data.stride=1.5: must be an integer >= 1"),
    Case("first frame past the end", "train", (*SMOKE, "data.first_frame=100000", *TRAIN_RUN), "data.first_frame: must be below"),
    Case("NaN depth_max", "train", (*SMOKE, "data.depth_max=nan", *TRAIN_RUN), "data.depth_max=nan: must be a finite number"),
    Case("resize with one number", "train", (*SMOKE, "data.resize=[80]", *TRAIN_RUN), "data.resize=[80]: must be [width, height]"),
    Case("depth_max below depth_min", "train", (*SMOKE, "data.depth_min=2", "data.depth_max=1", *TRAIN_RUN), "must be > data.depth_min"),
    Case("unknown data key", "train", (*SMOKE, "+data.strides=2", *TRAIN_RUN), "data.strides: unknown setting"),
    Case("unknown added key", "train", (*SMOKE, "+foo=bar", *TRAIN_RUN), "foo: unknown setting"),
    Case("misspelt resume", "train", (*SMOKE, "+resmue=true", *TRAIN_RUN), "resmue: unknown setting (did you mean resume?"),
    Case("unparsable override", "train", (*SMOKE, "hydra.run.dir={d}/runs/a=b"), "not a valid override"),
    Case("dataset target not a reader", "train", (*SMOKE, "dataset._target_=builtins.open", *TRAIN_RUN), "dataset._target_='builtins.open': not one of"),
    Case("dataset _args_", "train", (*SMOKE, "+dataset._args_=[x]", *TRAIN_RUN), "dataset._args_: not allowed"),
    Case("mask provider not TivNe's", "train", (*SMOKE, "masks.provider._target_=os.system", *TRAIN_RUN), "masks.provider._target_='os.system'"),
    Case("negative max_time_diff", "train", ("experiment=smoke", "dataset=tum", "dataset.root={d}/seq", "dataset.max_time_diff=-1", *TRAIN_RUN),
         "dataset.max_time_diff=-1.0: must be >= 0"),
    Case("unknown reader argument", "train", (*SMOKE, "+dataset.speed=2", *TRAIN_RUN), "dataset.speed: unknown setting"),
    Case("reader argument not a number", "train", (*SMOKE, "dataset.num_frames=abc", *TRAIN_RUN), "dataset.num_frames='abc': must be an integer"),
    Case("depth_scale 0", "train", ("experiment=smoke", *FOLDER, "dataset.depth_scale=0", *TRAIN_RUN), "dataset.depth_scale=0.0: must be > 0",
         setup=folder()),
    Case("frames too large", "train", (*SMOKE, "data.resize=[8000,6000]", *TRAIN_RUN), "frames of 8000x6000 (48.0 Mpx)"),
    Case("map beyond the memory", "train", (*SMOKE, "field.max_capacity=1000000000000", *TRAIN_RUN), "field.max_capacity: the run needs about"),
    Case("zero frames", "train", (*SMOKE, "dataset.num_frames=0", *TRAIN_RUN), "num_frames"),
    # train: data
    Case("dataset root not given", "train", ("experiment=smoke", "dataset=folder", *TRAIN_RUN), "missing mandatory config value 'dataset.root'"),
    Case("dataset folder missing", "train", ("experiment=smoke", *FOLDER, *TRAIN_RUN), "seq: ", setup=None),
    Case("empty image folders", "train", ("experiment=smoke", *FOLDER, *TRAIN_RUN), "no .png/.jpg colour images", setup=empty_folder),
    Case("depth image missing", "train", ("experiment=smoke", *FOLDER, *TRAIN_RUN), "depth/1.png: missing", setup=folder(remove("depth/1.png"))),
    Case("corrupt colour image", "train", ("experiment=smoke", *FOLDER, *TRAIN_RUN), "rgb/1.png", setup=folder(write_file("rgb/1.png", b"\x89PNG garbage"))),
    Case("depth of another size", "train", ("experiment=smoke", *FOLDER, *TRAIN_RUN), "depth/1.png", setup=folder(small_depth)),
    Case("corrupt calibration", "train", ("experiment=smoke", *FOLDER, *TRAIN_RUN), "intrinsics.txt", setup=folder(write_file("intrinsics.txt", "20 abc 15.5 11.5\n"))),
    Case("calibration missing", "train", ("experiment=smoke", *FOLDER, *TRAIN_RUN), "intrinsics.txt: not found", setup=folder(remove("intrinsics.txt"))),
    Case("non-monotonic timestamps", "train", ("experiment=smoke", *FOLDER, *TRAIN_RUN), "timestamps.txt", setup=folder(timestamps_txt=[0.0, 0.2, 0.1])),
    Case("NaN depth everywhere", "train", ("experiment=smoke", "dataset=room4", "dataset.root={d}/seq", "masks=none", *TRAIN_RUN), "could not be tracked", code=3, setup=nan_depth_cofusion),
    Case("truncated KLG log", "train", ("experiment=smoke", *KLG, "masks=none", *TRAIN_RUN), "log.klg: frame 2: colour payload truncated", setup=truncated_klg),
    Case("mask folder missing", "train", (*SMOKE, "masks=folder", "masks.provider.root={d}/masks", *TRAIN_RUN), "masks"),
    # train: the run directory
    Case("run dir with results", "train", (*SMOKE, *TRAIN_RUN), "already holds results", setup=lambda d: finished_run(d / "run")),
    Case("resume with another config", "train", (*SMOKE, "field_tracking.iters=5", "resume=true", *TRAIN_RUN), "different config: field_tracking.iters (3 -> 5)", setup=interrupted_run),
    Case("resume without a checkpoint", "train", (*SMOKE, "resume=true", *TRAIN_RUN), "nothing to resume"),
    Case("resume a complete run", "train", (*SMOKE, "resume=true", *TRAIN_RUN), "the run is complete", setup=lambda d: finished_run(d / "run")),
    Case("resume a truncated checkpoint", "train", (*SMOKE, "resume=true", *TRAIN_RUN), "not a readable TivNe checkpoint", setup=run_then(truncate_checkpoint, complete=False)),
    Case("full disk at the checkpoint", "train", (*SMOKE, *TRAIN_RUN), "run/checkpoints/slam.pt: No space left on device", patch="torch.save"),
    Case("read-only run dir", "train", (*SMOKE, *TRAIN_RUN), READ_ONLY, setup=empty_dir("run"), read_only=True),
    Case("new run dir in a read-only folder", "train", (*SMOKE, "hydra.run.dir={d}/run/new"), READ_ONLY, setup=empty_dir("run"), read_only=True),
    Case("resume an interrupted run without a checkpoint", "train", (*SMOKE, "resume=true", *TRAIN_RUN), "overwrite=true starts it again from frame 0",
         setup=run_then(remove("checkpoints"), complete=False)),
    Case("restart an interrupted run without a checkpoint", "train", (*SMOKE, *TRAIN_RUN), "no checkpoint to resume from; overwrite=true",
         setup=run_then(remove("checkpoints"), complete=False)),
    Case("run dir held by another run", "train", (*SMOKE, *TRAIN_RUN), "is writing into this folder", setup=held_by_another_run),
    Case("resume with a hostile run config", "train", (*SMOKE, "resume=true", *TRAIN_RUN), "resume=true with a different config",
         setup=saved_config(open_for_writing, complete=False)),
    # inspect
    Case("inspect: unknown format", "inspect", (*TINY, "format=xml"), "format: must be 'text' or 'json'"),
    Case("inspect: root not given", "inspect", ("dataset=folder",), "missing mandatory config value 'dataset.root'"),
    Case("inspect: truncated KLG log", "inspect", KLG, "log.klg: frame 2: colour payload truncated", setup=truncated_klg),
    Case("inspect: non-monotonic rgb.txt", "inspect", ("dataset=tum", "dataset.root={d}/seq"), "rgb.txt", setup=tum_with(swap_rgb_lines)),
    Case("inspect: corrupt groundtruth.txt", "inspect", ("dataset=tum", "dataset.root={d}/seq"), "groundtruth.txt", setup=tum_with(corrupt_groundtruth)),
    Case("inspect: corrupt calibration.txt", "inspect", ("dataset=room4", "dataset.root={d}/seq"), "calibration.txt", setup=lambda d: make_cofusion(d / "seq", n=2, calib="20 21 abc")),
    Case("inspect: GT out into a missing folder", "inspect", (*TINY, "gt_out={d}/no/gt.txt"), "no/gt.txt: output folder does not exist"),
    Case("inspect: GT out without ground truth", "inspect", ("dataset=folder", "dataset.root={d}/seq", "gt_out={d}/gt.txt"), "ground", setup=folder()),
    Case("inspect: GT out into a read-only folder", "inspect", (*TINY, "gt_out={d}/run/gt.txt"), tuple("run/gt.txt: " + m for m in READ_ONLY_ERRORS),
         setup=empty_dir("run"), read_only=True),
    Case("inspect: max_frames 0", "inspect", (*TINY, "data.max_frames=0"), "data.max_frames: must be >= 1"),
    Case("inspect: sheet not a PNG", "inspect", (*TINY, "sheet_out={d}/sheet.xyz"), "sheet_out: 'sheet.xyz': must be a .png path"),
    Case("inspect: fractional stride", "inspect", (*TINY, "data.stride=1.5"), "data.stride: must be an integer >= 1, got 1.5"),
    Case("inspect: NaN depth_max", "inspect", (*TINY, "data.depth_max=nan"), "data.depth_max: must be a finite number"),
    Case("inspect: negative max_time_diff", "inspect", ("dataset=tum", "dataset.root={d}/seq", "dataset.max_time_diff=-1"),
         "dataset.max_time_diff: must be a finite number >= 0", setup=tum_with(lambda seq: None)),
    Case("inspect: sheet_frames 0", "inspect", (*TINY, "sheet_frames=0"), "sheet_frames: must be an integer >= 1"),
    Case("inspect: unparsable override", "inspect", (*TINY, "sheet_out={d}/a=b.png"), "not a valid override"),
    # mesh
    Case("mesh: run_dir not given", "mesh", (), "missing mandatory config value 'run_dir'"),
    Case("mesh: run dir missing", "mesh", MESH_RUN, "run: run directory not found"),
    Case("mesh: no checkpoint", "mesh", MESH_RUN, "slam.pt: checkpoint not found", setup=run_then(remove("checkpoints"))),
    Case("mesh: corrupt checkpoint", "mesh", MESH_RUN, "not a readable TivNe checkpoint", setup=run_then(garbage_checkpoint)),
    Case("mesh: truncated checkpoint", "mesh", MESH_RUN, "not a readable TivNe checkpoint", setup=run_then(truncate_checkpoint)),
    Case("mesh: time outside the run", "mesh", (*MESH_RUN, "mesh.times=[99]"), "outside the recorded range", setup=interrupted_run),
    Case("mesh: CUDA on a CPU-only torch", "mesh", (*MESH_RUN, "device=cuda"), "CUDA is not available", setup=interrupted_run),
    Case("mesh: resolution 0", "mesh", (*MESH_RUN, "mesh.resolution=0"), "mesh.resolution=0.0: must be > 0", setup=interrupted_run),
    Case("mesh: every 0", "mesh", (*MESH_RUN, "every=0"), "every", setup=interrupted_run),
    Case("mesh: full disk", "mesh", MESH_RUN, "No space left on device", setup=run_then(remove("meshes")), patch="write"),
    Case("mesh: read-only run dir", "mesh", MESH_RUN, READ_ONLY, setup=run_then(remove("meshes")), read_only=True),
    Case("mesh: unknown added key", "mesh", (*MESH_RUN, "+evry=2"), "evry: unknown setting (did you mean every?", setup=interrupted_run),
    Case("mesh: unparsable override", "mesh", (*MESH_RUN, "device=cuda=1"), "not a valid override", setup=interrupted_run),
    # evaluate
    Case("evaluate: read-only run dir", "evaluate", EVAL_RUN, READ_ONLY,
         setup=interrupted_run, read_only=True),
    Case("evaluate: run dir missing", "evaluate", EVAL_RUN, "run: run directory not found"),
    Case("evaluate: no trajectory", "evaluate", EVAL_RUN, "trajectory.txt: not found", setup=run_then(remove("trajectory.txt"))),
    Case("evaluate: no run config", "evaluate", EVAL_RUN, "config.yaml: run config not found", setup=run_then(remove(".hydra"))),
    Case("evaluate: corrupt trajectory", "evaluate", EVAL_RUN, "trajectory.txt", setup=run_then(write_file("trajectory.txt", "0.0 1 2 three 0 0 0 1\n"))),
    Case("evaluate: corrupt checkpoint", "evaluate", EVAL_RUN, "not a readable TivNe checkpoint", setup=run_then(garbage_checkpoint)),
    Case("evaluate: time outside the run", "evaluate", (*EVAL_RUN, "mesh.times=[99]"), "outside the recorded range", setup=interrupted_run),
    Case("evaluate: unknown frame", "evaluate", (*EVAL_RUN, "frame=foo"), "frame='foo': must be one of", setup=interrupted_run),
    Case("evaluate: negative threshold", "evaluate", (*EVAL_RUN, "settings.threshold_m=-1"), "settings.threshold_m=-1", setup=interrupted_run),
    Case("evaluate: hostile run config", "evaluate", EVAL_RUN, "dataset._target_='builtins.open': not one of TivNe's own",
         setup=saved_config(open_for_writing)),
    Case("evaluate: hostile target inside a reader", "evaluate", EVAL_RUN, "dataset.intrinsics._target_='builtins.open'",
         setup=saved_config(nested_open)),
    Case("evaluate: run config with a fractional stride", "evaluate", EVAL_RUN, "data.stride=1.5", setup=saved_config(fractional_stride)),
    Case("evaluate: unknown added key", "evaluate", (*EVAL_RUN, "+frames=ate"), "frames: unknown setting (did you mean frame?",
         setup=interrupted_run),
    # report
    Case("report: hostile run config", "report", EVAL_RUN, "dataset._target_='builtins.open': not one of TivNe's own",
         setup=saved_config(open_for_writing)),
    Case("report: hostile target inside a reader", "report", EVAL_RUN, "dataset.intrinsics._target_='builtins.open'", setup=saved_config(nested_open)),
    Case("report: run dir missing", "report", EVAL_RUN, "run: run directory not found"),
    Case("report: negative frames", "report", (*EVAL_RUN, "report.frames=-1"), "report.frames=-1: must be >= 0", setup=interrupted_run),
    Case("report: unknown added key", "report", (*EVAL_RUN, "+reprot.frames=2"), "reprot: unknown setting (did you mean report?", setup=interrupted_run),
    Case("report: unparsable override", "report", (*EVAL_RUN, "report.frames=a=b"), "not a valid override", setup=interrupted_run),
    # collect
    Case("collect: folder missing", "collect", ("{d}/none",), "none: no such run or sweep directory"),
    Case("collect: no runs in the folder", "collect", ("{d}/sweep",), "no run directories", setup=sweep_dir),
    # make_masks
    Case("make_masks: provider needs poses", "make_masks", (*TINY, "masks=geometric", "out={d}/masks"), "needs the tracked pose"),
    Case("make_masks: out not given", "make_masks", (*TINY, "masks=none"), "missing mandatory config value 'out'"),
    Case("make_masks: out is a file", "make_masks", (*TINY, "masks=none", "out={d}/masks"), "masks: File exists", setup=a_file),
    Case("make_masks: out in a read-only folder", "make_masks", (*TINY, "masks=none", "out={d}/run/masks"), tuple("run/masks: " + m for m in READ_ONLY_ERRORS),
         setup=empty_dir("run"), read_only=True),
    Case("make_masks: Mask R-CNN weights missing", "make_masks", (*TINY, "masks=maskrcnn", "masks.provider.weights={d}/none.pth", "out={d}/masks"), "none.pth"),
    Case("make_masks: dataset root missing", "make_masks", ("dataset=folder", "dataset.root={d}/seq", "masks=none", "out={d}/masks"), "seq"),
    Case("make_masks: fractional stride", "make_masks", (*TINY, "masks=none", "data.stride=1.5", "out={d}/masks"), "data.stride=1.5"),
    Case("make_masks: provider not TivNe's", "make_masks", (*TINY, "masks.provider._target_=builtins.exec", "out={d}/masks"),
         "masks.provider._target_='builtins.exec'"),
    Case("make_masks: unknown added key", "make_masks", (*TINY, "masks=none", "+ovewrite=true", "out={d}/masks"), "ovewrite: unknown setting"),
)


# ----------------------------------------------------------------------------------- running
def full_disk(target: str):
    """A writer that fails as a full disk does: ``torch.save`` or every file write."""
    from unittest import mock

    error = OSError(28, "No space left on device")
    if target == "torch.save":
        return mock.patch("torch.save", side_effect=error)

    fdopen = os.fdopen

    class FullFile:
        def __init__(self, fd: int, mode: str) -> None:
            self.fh = fdopen(fd, mode)

        def __enter__(self):
            return self

        def __exit__(self, *exc) -> None:
            self.fh.close()

        def write(self, data) -> int:
            raise error

    return mock.patch("data_modules.io.os.fdopen", FullFile)


PATCHES = {"torch.save": lambda: full_disk("torch.save"), "write": lambda: full_disk("write")}


def invoke(cli: str, args: list[str], patch: str | None = None) -> tuple[int, str, str]:
    """``python -m <cli> <args>`` in this process: (exit status, stdout, stderr)."""
    return run_module(MODULES[cli], args, PATCHES[patch]() if patch else None)


@contextlib.contextmanager
def read_only(folder: Path):
    """``folder`` read-only within the block: mode bits, or for root a read-only bind mount.
    Yields False where neither is possible (root without the right to mount)."""
    if os.geteuid() != 0:
        paths = [folder, *folder.rglob("*")]
        for p in paths:
            p.chmod(0o555 if p.is_dir() else 0o444)
        try:
            yield True
        finally:
            for p in paths:
                p.chmod(0o755 if p.is_dir() else 0o644)
        return
    mount = subprocess.run(["mount", "--bind", str(folder), str(folder)], capture_output=True)
    if mount.returncode != 0:
        yield False
        return
    try:
        ok = subprocess.run(["mount", "-o", "remount,bind,ro", str(folder)], capture_output=True).returncode == 0
        yield ok
    finally:
        subprocess.run(["umount", str(folder)], capture_output=True)


def snapshot(folder: Path) -> dict[str, str]:
    return {str(p.relative_to(folder)): hashlib.sha1(p.read_bytes()).hexdigest() for p in sorted(folder.rglob("*")) if p.is_file()}


def run_case(case: Case, base: Path) -> dict:
    """Set the case up in its own folder, run it, and report what it did and what it changed."""
    d = Path(tempfile.mkdtemp(prefix="case-", dir=base))
    if case.setup is not None:
        case.setup(d)
    args = [a.replace("{d}", str(d)) for a in case.args]
    had_run = (d / "run").is_dir()
    before = snapshot(d)
    start = time.monotonic()
    with read_only(d / "run") if case.read_only else contextlib.nullcontext(True) as possible:
        code, stdout, stderr = invoke(case.cli, args, case.patch) if possible else (None, "", "")
    after = snapshot(d)
    lost = sorted(k for k in before if after.get(k) != before[k])
    added = sorted(k for k in after if k not in before and (had_run and k.startswith("run/")))
    return {"name": case.name, "code": code, "stdout": stdout, "stderr": stderr.replace(str(d) + "/", "").replace(str(d), "."),
            "lost": lost, "added": added, "tmp": sorted(k for k in after if k.endswith(".tmp")), "s": time.monotonic() - start}


def run_cases(names: list[str], base: Path) -> list[dict]:
    TEMPLATE["base"] = base
    by_name = {c.name: c for c in CASES}
    try:
        return [run_case(by_name[n], base) for n in names]
    finally:
        for proc in HOLDERS:
            proc.kill()
            proc.join()


def run_all(base: Path, workers: int = 2) -> dict[str, dict]:
    """Every case, split over ``workers`` processes; {case name: result}."""
    names = [c.name for c in CASES]
    env = dict(os.environ, PYTHONPATH=str(REPO), OMP_WAIT_POLICY="PASSIVE", OMP_NUM_THREADS="1", PYTHONUNBUFFERED="1")
    procs = []
    for i in range(workers):
        chunk, out = names[i::workers], base / f"worker{i}.json"
        (base / f"w{i}").mkdir(parents=True, exist_ok=True)
        cmd = [sys.executable, __file__, "--worker", str(base / f"w{i}"), "--out", str(out), "--cases", json.dumps(chunk)]
        procs.append((subprocess.Popen(cmd, cwd=base, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True), out))
    results: dict[str, dict] = {}
    for proc, out in procs:
        _, err = proc.communicate(timeout=900)
        assert proc.returncode == 0, err[-3000:]
        results.update({r["name"]: r for r in json.loads(out.read_text())})
    return results


def error_lines(stderr: str) -> list[str]:
    return [line for line in stderr.splitlines() if line.startswith("error:")]


# --------------------------------------------------------------------------------------- tests
@pytest.fixture(scope="module")
def results(tmp_path_factory) -> dict[str, dict]:
    return run_all(tmp_path_factory.mktemp("bad_input"))


def test_there_are_enough_cases_over_every_command():
    assert len(CASES) >= 90 and len({c.name for c in CASES}) == len(CASES)
    assert {c.cli for c in CASES} == set(MODULES)


@pytest.mark.parametrize("case", CASES, ids=[c.name for c in CASES])
def test_bad_input_is_one_line(results, case):
    import torch

    if case.message == "CUDA is not available" and torch.cuda.is_available():
        pytest.skip("this torch has CUDA")
    r = results[case.name]
    if r["code"] is None:
        pytest.skip("no way to make a folder read-only here (root without the right to mount)")
    assert "Traceback" not in r["stderr"], r["stderr"][-3000:]
    errors = error_lines(r["stderr"])
    assert len(errors) == 1, r["stderr"][-3000:]
    assert r["code"] == case.code, r["stderr"][-3000:]
    messages = (case.message,) if isinstance(case.message, str) else case.message
    assert any(m in errors[0] for m in messages), errors[0]
    assert r["lost"] == [] and r["added"] == [] and r["tmp"] == [], r


def markdown_table(results: dict[str, dict]) -> str:
    """case | command | exit | message, one row per case."""
    rows = ["| case | command | exit | message |", "|---|---|---|---|"]
    for c in CASES:
        r = results[c.name]
        command = f"python -m {MODULES[c.cli]} " + " ".join(a.replace("{d}/", "") for a in c.args)
        message = (error_lines(r["stderr"]) or [r["stderr"].strip().splitlines()[-1] if r["stderr"].strip() else ""])[0]
        rows.append(f"| {c.name} | `{command.strip()}` | {r['code']} | `{message}` |")
    return "\n".join(rows)


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--worker", type=Path, help="run the --cases in this process, in this folder")
    parser.add_argument("--cases", default="[]")
    parser.add_argument("--out", type=Path)
    opts = parser.parse_args()
    if opts.worker:
        opts.out.write_text(json.dumps(run_cases(json.loads(opts.cases), opts.worker)))
    else:
        with tempfile.TemporaryDirectory(prefix="tivne-bad-input-") as tmp:
            print(markdown_table(run_all(Path(tmp))))
