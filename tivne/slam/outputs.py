"""The run directory: every path of a run's results and every writer, in one place.

    run_dir/
      .hydra/                    the composed config (written by Hydra)
      trajectory.txt             TUM format, rewritten every ``output.save_every`` frames
      metrics.json               flat snake_case keys with units (merged, never truncated)
      checkpoints/slam.pt        the field, its construction arguments and the trajectory
      meshes/mesh_t<t>.ply       meshes at chosen timestamps (seconds, 3 decimals)
      objects/<id>.txt           TUM format, one moving object's object-to-world poses (``objects.track``)
      renders/frame<k>_<x>.png   rendered vs observed images
      tb/                        TensorBoard events (per-frame scalars, images, the meshes and
                                 the final metrics as hparams)
      report.html, report/       python -m tivne.report: the page and its PNGs

Every write is atomic (:func:`data_modules.io.atomic_write`): a reader sees the old file or the
new one, and a failed write leaves neither half a file nor a temporary behind.

A run directory that already holds results is refused unless the run resumes it (same config) or
overwrites it (:meth:`RunDir.clear_results` first, so no stale mesh, render or metric mixes in):
:func:`check_run_dir`. Refusals are :class:`RunDirError`, one line naming the folder.
"""

from __future__ import annotations

import errno
import json
import math
import os
import shutil
import sys
import tempfile
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import torch
import trimesh

from data_modules.frame import DatasetError
from data_modules.io import atomic_write
from data_modules.tables import write_tum_trajectory

# Config keys that may differ when a run is resumed: where it runs, how the folder is treated and
# whether a viewer watches it (viewer=rerun only reads the run).
RESUME_IGNORED_KEYS = ("hydra", "resume", "overwrite", "viewer")


class RunDirError(DatasetError):
    """A run directory that cannot be used as asked (``str()`` is one line naming it)."""


def jsonable(value: Any) -> Any:
    """numpy scalars -> python; NaN / inf -> None (JSON has neither)."""
    if isinstance(value, (np.floating, np.integer, np.bool_)):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


class RunDir:
    """Paths and writers of one run directory (see the module docstring for the layout)."""

    TRAJECTORY = "trajectory.txt"
    METRICS = "metrics.json"
    CHECKPOINT = "checkpoints/slam.pt"
    MESHES = "meshes"
    OBJECTS = "objects"
    RENDERS = "renders"
    TENSORBOARD = "tb"
    REPORT = "report.html"
    REPORT_IMAGES = "report"

    def __init__(self, root: str | Path) -> None:
        self.root = Path(root)

    @property
    def trajectory(self) -> Path:
        return self.root / self.TRAJECTORY

    @property
    def metrics(self) -> Path:
        return self.root / self.METRICS

    @property
    def checkpoint(self) -> Path:
        return self.root / self.CHECKPOINT

    @property
    def config(self) -> Path:
        return self.root / ".hydra" / "config.yaml"

    @property
    def overrides(self) -> Path:
        """The command-line overrides of the run (written by Hydra)."""
        return self.root / ".hydra" / "overrides.yaml"

    @property
    def report(self) -> Path:
        return self.root / self.REPORT

    def results(self) -> list[Path]:
        """The results this folder holds already (trajectory, metrics, checkpoints, meshes,
        renders); .hydra/, logs and TensorBoard events alone are not results."""
        found = [p for p in (self.trajectory, self.metrics) if p.exists()]
        for folder in (self.checkpoint.parent, self.root / self.MESHES, self.root / self.RENDERS, self.root / self.OBJECTS):
            if folder.is_dir() and any(folder.iterdir()):
                found.append(folder)
        return found

    def clear_results(self) -> list[Path]:
        """Delete every result (and the TensorBoard events) for ``overwrite=true``; returns what went."""
        gone = [*self.results(), self.root / self.TENSORBOARD, self.metrics.with_name(self.METRICS + ".corrupt")]
        gone = [p for p in gone if p.exists()]
        for p in gone:
            shutil.rmtree(p) if p.is_dir() else p.unlink()
        return gone

    def check_writable(self) -> None:
        """Raise the OSError (EROFS, EACCES, ...) naming the folder when a file cannot be created in
        it or in one of its existing result folders, or, for a folder still to be made, in its
        nearest existing parent (ask the file system, not the mode bits: root writes whatever they say)."""
        parent = self.root.absolute()
        while not parent.exists() and parent != parent.parent:
            parent = parent.parent
        for folder in (parent, self.checkpoint.parent, self.root / self.MESHES, self.root / self.RENDERS):
            if not folder.is_dir():
                continue
            try:
                with tempfile.TemporaryFile(dir=folder, prefix=".write-test."):
                    pass
            except OSError as exc:
                code = exc.errno or errno.EACCES
                raise OSError(code, exc.strerror or os.strerror(code), str(folder)) from None

    def mesh_path(self, timestamp: float) -> Path:
        """meshes/mesh_t{t:.3f}.ply for a mesh at ``timestamp`` seconds."""
        return self.root / self.MESHES / f"mesh_t{timestamp:.3f}.ply"

    def object_path(self, object_id: int) -> Path:
        """objects/<id>.txt: the TUM trajectory (object-to-world) of tracked object ``object_id``."""
        return self.root / self.OBJECTS / f"{int(object_id)}.txt"

    def object_paths(self) -> dict[int, Path]:
        """{id: objects/<id>.txt} of the object trajectories the run wrote."""
        folder = self.root / self.OBJECTS
        found = folder.glob("*.txt") if folder.is_dir() else []
        return {int(p.stem): p for p in sorted(found) if p.stem.isdigit()}

    def render_path(self, frame_id: int, name: str) -> Path:
        return self.root / self.RENDERS / f"frame{frame_id:05d}_{name}.png"

    # ---- writers -------------------------------------------------------------------------------
    def write_trajectory(self, timestamps: list[float], poses: torch.Tensor) -> Path:
        """(N,) seconds and (N, 4, 4) c2w poses -> trajectory.txt."""
        write_tum_trajectory(self.trajectory, timestamps, poses)
        return self.trajectory

    def read_metrics(self) -> dict[str, Any]:
        """metrics.json's content ({} when absent). An unreadable file is moved aside to
        ``metrics.json.corrupt`` (with a warning) rather than lost or overwritten."""
        path = self.metrics
        if not path.is_file():
            return {}
        try:
            current = json.loads(path.read_text())
            if not isinstance(current, dict):
                raise ValueError("not a JSON object")
            return current
        except ValueError:
            path.replace(path.with_name(path.name + ".corrupt"))
            print(f"warning: {path}: not a JSON object; kept as {path.name}.corrupt", file=sys.stderr)
            return {}

    def read_metrics_quietly(self) -> dict[str, Any]:
        """metrics.json's content, {} when absent or unreadable (nothing is moved)."""
        try:
            current = json.loads(self.metrics.read_text())
        except (OSError, ValueError):
            return {}
        return current if isinstance(current, dict) else {}

    def merge_metrics(self, metrics: dict[str, Any]) -> dict[str, Any]:
        """Merge ``metrics`` into metrics.json and return the merged content.

        Keys not in ``metrics`` are kept, except a stale ``<stem>_reason`` whose metrics ``<stem>_*``
        (or ``<stem>`` itself: ``ssim_reason``) are now computed. Values go through :func:`jsonable`
        (NaN -> null).
        """
        current = self.read_metrics()
        metrics = {k: jsonable(v) for k, v in metrics.items()}
        computed = [k for k, v in metrics.items() if v is not None and not k.endswith("_reason")]
        for key in [k for k in current if k.endswith("_reason") and k not in metrics]:
            stem = key[: -len("reason")]
            if any(k.startswith(stem) or k == stem[:-1] for k in computed):
                del current[key]
        current.update(metrics)
        atomic_write(self.metrics, json.dumps(current, indent=2, sort_keys=True) + "\n")
        return current

    def write_image(self, path: Path, rgb: np.ndarray) -> Path:
        """(H, W, 3) uint8 RGB -> PNG at ``path``."""
        import cv2

        ok, buf = cv2.imencode(".png", np.ascontiguousarray(rgb[..., ::-1]))
        if not ok:
            raise OSError(f"{path}: could not encode the image")
        return atomic_write(path, buf.tobytes())


def check_run_dir(run: RunDir, resume: bool, overwrite: bool, saved: Mapping[str, Any] | None = None,
                  current: Mapping[str, Any] | None = None) -> None:
    """The rules for starting ``tivne.train`` in ``run``; raises :class:`RunDirError` or OSError.

    A folder holding results is refused unless ``resume`` or ``overwrite``; ``resume`` needs a
    checkpoint, a run that is not complete, and (when both are given) a ``current`` config equal to
    the ``saved`` one but for :data:`RESUME_IGNORED_KEYS`. Every existing folder must be writable.
    Nothing is changed on disk (``overwrite`` clears later, once the run is sure to start).
    """
    if run.root.exists() and not run.root.is_dir():
        raise RunDirError(run.root, "run directory is a file")
    run.check_writable()
    if resume:
        if not run.checkpoint.is_file() and run.results():  # e.g. a second SIGINT: stopped before any checkpoint
            raise RunDirError(run.checkpoint, "not found: the run stopped before its first checkpoint, so it cannot be resumed; "
                                              "overwrite=true starts it again from frame 0")
        if not run.checkpoint.is_file():
            raise RunDirError(run.checkpoint, "nothing to resume (no checkpoint; run without resume=true)")
        if run.read_metrics_quietly().get("complete") is True:
            raise RunDirError(run.root, "the run is complete; nothing to resume (overwrite=true runs it again)")
        if saved is not None and current is not None:
            differ = config_differences(saved, current)
            if differ:
                raise RunDirError(run.config, "resume=true with a different config: " + describe_differences(differ))
        return
    held = run.results()
    if held and not overwrite:
        names = ", ".join(p.name + ("/" if p.is_dir() else "") for p in held)
        raise RunDirError(run.root, f"already holds results ({names}); {way_on(run)}")


def way_on(run: RunDir) -> str:
    """What a user can do with a folder holding results: resume only where there is something to
    resume (a checkpoint of a run that is not complete), never advice that leads back here."""
    if run.checkpoint.is_file() and run.read_metrics_quietly().get("complete") is not True:
        return "resume=true continues the run, overwrite=true replaces them"
    if run.checkpoint.is_file():
        return "the run is complete; overwrite=true replaces its results"
    return "no checkpoint to resume from; overwrite=true replaces them"


def flatten(tree: Mapping[str, Any], prefix: str = "") -> dict[str, Any]:
    """{"a": {"b": 1}} -> {"a.b": 1}."""
    flat: dict[str, Any] = {}
    for key, value in tree.items():
        name = f"{prefix}{key}"
        if isinstance(value, Mapping) and value:
            flat.update(flatten(value, name + "."))
        else:
            flat[name] = value
    return flat


def config_differences(saved: Mapping[str, Any], current: Mapping[str, Any]) -> list[tuple[str, Any, Any]]:
    """(key, saved value, current value) of every key whose value differs (a missing key is None),
    sorted, except :data:`RESUME_IGNORED_KEYS`."""
    a, b = flatten(saved), flatten(current)
    keys = sorted(k for k in set(a) | set(b) if k.split(".")[0] not in RESUME_IGNORED_KEYS)
    return [(k, a.get(k), b.get(k)) for k in keys if a.get(k) != b.get(k)]


def describe_differences(differ: list[tuple[str, Any, Any]], limit: int = 5) -> str:
    """``key (saved -> now), ...`` for an error line (the first ``limit`` keys and a count)."""
    text = ", ".join(f"{k} ({a!r} -> {b!r})" for k, a, b in differ[:limit])
    return text + (f" and {len(differ) - limit} more" if len(differ) > limit else "")


def image_panels(rgb: torch.Tensor, depth: torch.Tensor, rgb_obs: torch.Tensor, depth_obs: torch.Tensor) -> dict[str, np.ndarray]:
    """Side-by-side observed | rendered panels as (H, 2W, 3) uint8 images, plus |depth error|.

    Args:
        rgb, depth: rendered (H, W, 3), (H, W); rgb_obs, depth_obs: observed, same sizes.
    Returns:
        {"rgb", "depth" (scaled to the observed maximum), "depth_error" (5 cm = white)}.
    """
    dmax = float(depth_obs.max().clamp_min(1e-3))
    err = (depth - depth_obs).abs() * (depth_obs > 0)

    def to8(x: torch.Tensor) -> np.ndarray:
        return (x.clamp(0, 1) * 255).byte().cpu().numpy()

    def gray(x: torch.Tensor) -> torch.Tensor:
        return x[..., None].expand(*x.shape, 3)

    return {
        "rgb": to8(torch.cat([rgb_obs, rgb], dim=1)),
        "depth": to8(gray(torch.cat([depth_obs, depth], dim=1) / dmax)),
        "depth_error": to8(gray(err / 0.05)),
    }


# A TensorBoard mesh is a preview: a larger mesh is thinned to every k-th face (the PLY keeps them all).
TENSORBOARD_MESH_FACES = 100_000


def tensorboard_mesh(writer: Any, tag: str, mesh: trimesh.Trimesh, step: int) -> None:
    """Add ``mesh`` to a TensorBoard ``SummaryWriter``; a failure is a warning, never a failed run."""
    if len(mesh.faces) == 0:
        return
    try:
        faces = np.asarray(mesh.faces)[:: max(1, -(-len(mesh.faces) // TENSORBOARD_MESH_FACES))]
        colors = np.asarray(mesh.visual.vertex_colors)[:, :3] if mesh.visual.kind == "vertex" else None
        writer.add_mesh(
            tag,
            vertices=torch.as_tensor(np.asarray(mesh.vertices), dtype=torch.float32)[None],
            faces=torch.as_tensor(faces, dtype=torch.int32)[None],
            colors=None if colors is None else torch.as_tensor(colors, dtype=torch.uint8)[None],
            global_step=step,
        )
    except Exception as exc:  # noqa: BLE001 -- an optional view of the results
        print(f"warning: TensorBoard: mesh {tag} not logged ({type(exc).__name__}: {exc})", file=sys.stderr)


def tensorboard_hparams(logger: Any, hparams: Mapping[str, Any], metrics: Mapping[str, Any]) -> None:
    """The run's settings as TensorBoard hparams with its final numeric metrics (as ``final/<key>``),
    through a Lightning logger; a failure is a warning, never a failed run."""
    numbers = {
        f"final/{k}": float(v) for k, v in metrics.items()
        if isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)
    }
    try:
        logger.log_hyperparams(dict(hparams), metrics=numbers)
        logger.finalize("success")
    except Exception as exc:  # noqa: BLE001 -- an optional view of the results
        print(f"warning: TensorBoard: hparams not logged ({type(exc).__name__}: {exc})", file=sys.stderr)
