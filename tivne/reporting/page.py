"""The run report: ``report.html`` in the run dir and its PNGs in ``report/``, built only from what the
run saved (trajectory.txt, tb/ events, the checkpoint, meshes/, renders/, metrics.json) and, for
ground truth and observed frames, the run's sequence.

Every section that lacks its inputs (no GT, an interrupted run without meshes, no events) says so
in a line instead of an image, so a report can always be written.
"""

from __future__ import annotations

import html
import json
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import trimesh

from data_modules.io import atomic_write
from data_modules.sequence import SequenceView
from data_modules.tables import read_tum_trajectory
from tivne.config import RenderConfig, ReportConfig
from tivne.evaluation.run import gt_trajectory
from tivne.reporting.events import read_scalars
from tivne.reporting.figures import contact_sheet, curves_figure, error_figure, image_grid, save_figure, trajectory_figure
from tivne.reporting.raster import look_at, pinhole, rasterize
from tivne.reporting.renders import render_pairs
from tivne.reporting.runs import format_value, read_overrides
from tivne.reporting.trajectory import plot_axes, trajectory_errors
from tivne.slam.checkpoint import load_checkpoint
from tivne.slam.outputs import RunDir

FOV_DEG = 60.0  # mesh snapshots: about a Kinect's horizontal field of view
OVERVIEW_ELEVATION_DEG = 40.0


@dataclass
class Section:
    """A titled part of the page: HTML body and the image files it shows."""

    title: str
    body: str
    images: list[Path] = field(default_factory=list)


def note(text: str) -> str:
    return f'<p class="note">{html.escape(text)}</p>'


def figure_html(root: Path, image: Path, caption: str) -> str:
    src = html.escape(image.relative_to(root).as_posix(), quote=True)
    return f'<figure><img src="{src}" alt="{html.escape(caption, quote=True)}"><figcaption>{html.escape(caption)}</figcaption></figure>'


def estimated_poses(run: RunDir) -> tuple[np.ndarray, np.ndarray] | None:
    """(timestamps (N,), c2w poses (N, 4, 4)) from trajectory.txt, or None without it."""
    if not run.trajectory.is_file():
        return None
    ts, poses = read_tum_trajectory(run.trajectory)
    return np.asarray(ts, dtype=np.float64), poses.numpy()


def trajectory_section(run: RunDir, view: SequenceView | None, out: Path) -> Section:
    """The trajectory against GT (top and side views) and its translation / rotation error over time."""
    section = Section("Trajectory", "")
    est = estimated_poses(run)
    if est is None:
        section.body = note(f"no {RunDir.TRAJECTORY}")
        return section
    ts, poses = est
    ts_gt, gt = gt_trajectory(view) if view is not None else (np.zeros(0), np.zeros((0, 4, 4)))
    errors, reason = trajectory_errors(ts, poses, ts_gt, gt) if len(ts_gt) else (None, "no ground-truth poses for this run")
    if errors is None:
        fig = trajectory_figure({"estimate (SLAM frame)": poses[:, :3, 3]}, plot_axes(poses))
        section.images.append(save_figure(fig, out / "trajectory.png"))
        section.body = figure_html(run.root, section.images[0], "estimated trajectory (no ground truth)") + note(reason or "")
        return section
    fig = trajectory_figure({"ground truth": errors.reference, "estimate (SE(3)-aligned)": errors.estimated}, plot_axes(errors.reference_poses))
    section.images.append(save_figure(fig, out / "trajectory.png"))
    section.images.append(save_figure(error_figure(errors), out / "trajectory_error.png"))
    section.body = figure_html(run.root, section.images[0], "trajectory vs ground truth (start: black dot)") + figure_html(
        run.root, section.images[1], f"error over time ({len(errors.times)} frames, aligned as the ATE)"
    )
    return section


def curves_section(run: RunDir, out: Path) -> Section:
    """Per-frame loss, tracking and timing curves from the TensorBoard events."""
    section = Section("Per-frame curves", "")
    fig = curves_figure(read_scalars(run.root / RunDir.TENSORBOARD))
    if fig is None:
        section.body = note(f"no scalars in {RunDir.TENSORBOARD}/")
        return section
    section.images.append(save_figure(fig, out / "curves.png"))
    section.body = figure_html(run.root, section.images[0], "per-frame scalars (TensorBoard tags)")
    return section


def renders_section(run: RunDir, view: SequenceView | None, render: RenderConfig, settings: ReportConfig, out: Path) -> Section:
    """Frames re-rendered from the checkpoint beside the sensor's, and the run's own render panels."""
    section = Section("Renders", "")
    parts = []
    if settings.frames == 0:
        parts.append(note("report.frames=0: no re-rendered frames"))
    elif view is None or not run.checkpoint.is_file():
        parts.append(note("no re-rendered frames: " + ("the sequence is not available" if view is None else f"no {RunDir.CHECKPOINT}")))
    else:
        field_, meta = load_checkpoint(run.checkpoint)
        pairs = render_pairs(field_, meta, view, render, settings.frames, settings.render_stride)
        if pairs:
            section.images.append(save_figure(contact_sheet(pairs), out / "renders.png"))
            parts.append(figure_html(run.root, section.images[-1], "observed vs rendered at the estimated poses"))
    saved = sorted((run.root / RunDir.RENDERS).glob("*.png"))
    parts += [figure_html(run.root, p, f"{p.stem} (observed | rendered, written by the run)") for p in saved]
    section.images += saved
    section.body = "".join(parts)
    return section


def snapshot_cameras(vertices: np.ndarray, first_pose: np.ndarray) -> list[tuple[str, np.ndarray]]:
    """Two viewpoints for a mesh (SLAM frame): the first camera's and an overview from above and
    behind it that frames the whole mesh. Returns [(name, w2c (4, 4))]."""
    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    centre, radius = (lo + hi) / 2, max(float(np.linalg.norm(hi - lo)) / 2, 1e-3)
    up = -first_pose[:3, 1]  # OpenCV: the camera's y points down
    ahead = first_pose[:3, 2] - (first_pose[:3, 2] @ up) * up
    ahead = ahead / np.linalg.norm(ahead) if np.linalg.norm(ahead) > 1e-6 else np.cross(up, [1.0, 0, 0])
    distance = 1.1 * radius / np.tan(np.radians(FOV_DEG) / 2)
    elevation = np.radians(OVERVIEW_ELEVATION_DEG)
    eye = centre - distance * np.cos(elevation) * ahead + distance * np.sin(elevation) * up
    return [("first camera", np.linalg.inv(first_pose)), ("overview", look_at(eye, centre, up))]


def mesh_snapshot(mesh: trimesh.Trimesh, first_pose: np.ndarray, settings: ReportConfig) -> list[tuple[str, np.ndarray]]:
    """[(viewpoint name, (H, W, 3) image)] of ``mesh`` from :func:`snapshot_cameras`."""
    faces = np.asarray(mesh.faces)[:: max(1, -(-len(mesh.faces) // settings.mesh_faces))]
    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    colors = np.asarray(mesh.visual.vertex_colors)[:, :3] / 255.0 if mesh.visual.kind == "vertex" else np.full((len(vertices), 3), 0.7)
    width, height = settings.mesh_width, settings.mesh_width * 3 // 4
    K = pinhole(width, height, FOV_DEG)
    return [(name, rasterize(vertices, faces, colors, K, w2c, width, height)) for name, w2c in snapshot_cameras(vertices, first_pose)]


def meshes_section(run: RunDir, settings: ReportConfig, out: Path) -> Section:
    """Each saved mesh (meshes/mesh_t<t>.ply) from two viewpoints, rasterised on the CPU."""
    section = Section("Meshes", "")
    paths = sorted((run.root / RunDir.MESHES).glob("mesh_t*.ply"))
    if not paths:
        section.body = note(f"no meshes in {RunDir.MESHES}/ (an interrupted run writes none; python -m tivne.mesh makes them)")
        return section
    est = estimated_poses(run)
    first_pose = est[1][0] if est is not None else np.eye(4)
    parts = []
    for path in paths:
        mesh = trimesh.load(path, force="mesh", process=False)
        if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
            parts.append(note(f"{path.name}: empty mesh"))
            continue
        views = mesh_snapshot(mesh, first_pose, settings)
        image = save_figure(image_grid([(f"{path.stem}: {name}", img) for name, img in views]), out / f"{path.stem}.png")
        section.images.append(image)
        parts.append(figure_html(run.root, image, f"{path.name} ({len(mesh.faces)} faces), from the first camera and from above"))
    section.body = "".join(parts)
    return section


def metrics_section(metrics: dict[str, Any]) -> Section:
    """Every metrics.json key and value."""
    if not metrics:
        return Section("Metrics", note(f"no {RunDir.METRICS}"))
    rows = "".join(f"<tr><td>{html.escape(k)}</td><td>{html.escape(format_value(v))}</td></tr>" for k, v in sorted(metrics.items()))
    return Section("Metrics", f"<table><tr><th>key</th><th>value</th></tr>{rows}</table>")


STYLE = """body{font-family:sans-serif;max-width:1200px;margin:2em auto;padding:0 1em}
img{max-width:100%}figure{margin:1em 0}figcaption{color:#555;font-size:90%}
table{border-collapse:collapse;font-size:90%}td,th{border:1px solid #ccc;padding:2px 8px;text-align:left}
.note{color:#a60}code{background:#f4f4f4;padding:1px 4px}"""


def page_html(run: RunDir, sections: Sequence[Section], metrics: dict[str, Any]) -> str:
    """The whole page: a header (run, overrides, status line) and the sections."""
    overrides = " ".join(f"{k}={v}" for k, v in read_overrides(run.root).items()) or "(none)"
    keys = ("complete", "frames", "ate_rmse_m", "object_chamfer_mean_m", "psnr_db", "s_per_frame")
    headline = ", ".join(f"{k} {format_value(metrics.get(k))}" for k in keys if k in metrics)
    body = "".join(f"<h2>{html.escape(s.title)}</h2>{s.body}" for s in sections)
    return (
        f"<!DOCTYPE html><html><head><meta charset=\"utf-8\"><title>TivNe run {html.escape(run.root.name)}</title>"
        f"<style>{STYLE}</style></head><body><h1>TivNe run <code>{html.escape(run.root.name)}</code></h1>"
        f"<p>overrides: <code>{html.escape(overrides)}</code></p><p>{html.escape(headline)}</p>{body}</body></html>\n"
    )


def write_report(run_dir: str | Path, view: SequenceView | None, render: RenderConfig, settings: ReportConfig) -> tuple[Path, list[Path]]:
    """Write run_dir/report.html and run_dir/report/*.png.

    Args:
        view: the sequence the run processed (ground truth and observed frames), or None (the
            report then has no GT comparison and no re-rendered frames).
        render: the run's render settings (for re-rendering); settings: :class:`ReportConfig`.
    Returns:
        the page and every image it shows.
    Raises:
        FileNotFoundError: no run directory.
    """
    run = RunDir(run_dir)
    if not run.root.is_dir():
        raise FileNotFoundError(f"{run.root}: run directory not found")
    out = run.root / RunDir.REPORT_IMAGES
    metrics = run.read_metrics()
    sections = [
        trajectory_section(run, view, out),
        curves_section(run, out),
        renders_section(run, view, render, settings, out),
        meshes_section(run, settings, out),
        metrics_section(metrics),
    ]
    atomic_write(run.report, page_html(run, sections, metrics))
    return run.report, [image for s in sections for image in s.images]


def report_summary(page: Path, images: Sequence[Path]) -> str:
    """What the command prints: the page and its images, as JSON."""
    return json.dumps({"report": str(page), "images": [str(p) for p in images]}, indent=2)
