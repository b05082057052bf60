"""The report's figures, drawn with matplotlib's object API on its Agg canvas (no pyplot state, no
display), each saved as one PNG."""

from __future__ import annotations

import fnmatch
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from data_modules.io import atomic_write
from tivne.reporting.renders import FramePair
from tivne.reporting.trajectory import TrajectoryErrors

# Panels of the per-frame curves: (title, tag patterns, log scale). A panel shows only if some tag exists.
CURVE_PANELS: tuple[tuple[str, tuple[str, ...], bool], ...] = (
    ("mapping loss", ("map/loss", "map/loss_*"), True),
    ("tracking loss (field tracker)", ("track/loss", "track/loss_*"), True),
    ("odometry", ("track/odo_inlier_ratio", "track/odo_overlap"), False),
    ("pose jump from the motion model [m]", ("track/jump_m",), False),
    ("seconds per frame", ("perf/s_per_frame",), False),
    ("voxels", ("map/voxels",), False),
)
SKIPPED_CURVES = ("map/skipped_steps", "map/steps", "map/explained")


def save_figure(fig: Figure, path: Path) -> Path:
    """Write ``fig`` as a PNG atomically (a half-written image never stands in for a figure)."""
    return atomic_write(path, lambda tmp: fig.savefig(tmp, format="png", dpi=100, bbox_inches="tight"))


def trajectory_figure(positions: dict[str, np.ndarray], axes: np.ndarray) -> Figure:
    """Top and side views of trajectories.

    Args:
        positions: {label: (N, 3) positions} (e.g. ground truth and the aligned estimate).
        axes: (3, 3) rows: horizontal 1, horizontal 2, up (:func:`tivne.reporting.trajectory.plot_axes`).
    """
    fig = Figure(figsize=(11, 4.8))
    top, side = fig.subplots(1, 2)
    for label, xyz in positions.items():
        local = np.asarray(xyz) @ axes.T
        style = "--" if label.startswith("ground") else "-"
        top.plot(local[:, 0], local[:, 1], style, label=label)
        side.plot(local[:, 0], local[:, 2], style, label=label)
        top.plot(local[:1, 0], local[:1, 1], "k.", markersize=8)
    for ax, title, ylabel in ((top, "top view", "horizontal 2 [m]"), (side, "side view", "up [m]")):
        ax.set_title(title)
        ax.set_xlabel("horizontal 1 (main direction of motion) [m]")
        ax.set_ylabel(ylabel)
        ax.set_aspect("equal", adjustable="datalim")
        ax.grid(alpha=0.3)
        ax.legend(loc="best", fontsize=8)
    return fig


def error_figure(errors: TrajectoryErrors) -> Figure:
    """Translation [cm] and rotation [deg] error of the aligned estimate over time."""
    fig = Figure(figsize=(11, 5))
    trans, rot = fig.subplots(2, 1, sharex=True)
    trans.plot(errors.times, 100 * errors.translation_m, "-", color="C3")
    rmse = 100 * float(np.sqrt(np.mean(errors.translation_m**2)))
    trans.axhline(rmse, color="k", lw=0.8, ls=":", label=f"RMSE {rmse:.3g} cm")
    trans.set_ylabel("translation error [cm]")
    trans.legend(loc="upper left", fontsize=8)
    rot.plot(errors.times, errors.rotation_deg, "-", color="C0")
    rot.set_ylabel("rotation error [deg]\n(orientations aligned)")
    rot.set_xlabel("time since the first frame [s]")
    for ax in (trans, rot):
        ax.grid(alpha=0.3)
    return fig


def curve_panels(scalars: dict[str, tuple[np.ndarray, np.ndarray]]) -> list[tuple[str, list[str], bool]]:
    """The :data:`CURVE_PANELS` that have data, with their tags."""
    panels = []
    for title, patterns, log in CURVE_PANELS:
        tags = [t for t in sorted(scalars) if t not in SKIPPED_CURVES and any(fnmatch.fnmatchcase(t, p) for p in patterns)]
        if tags:
            panels.append((title, tags, log))
    return panels


def curves_figure(scalars: dict[str, tuple[np.ndarray, np.ndarray]]) -> Figure | None:
    """Per-frame losses and timing from TensorBoard (tag -> (steps, values)); None without any."""
    panels = curve_panels(scalars)
    if not panels:
        return None
    cols = 2
    rows = -(-len(panels) // cols)
    fig = Figure(figsize=(11, 3.2 * rows))
    grid = np.atleast_1d(fig.subplots(rows, cols, squeeze=False)).ravel()
    for ax, (title, tags, log) in zip(grid, panels):
        for tag in tags:
            steps, values = scalars[tag]
            positive = values > 0
            ax.plot(steps[positive] if log else steps, values[positive] if log else values, lw=1, label=tag)
        ax.set_title(title, fontsize=10)
        ax.set_xlabel("frame")
        if log:
            ax.set_yscale("log")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, loc="best")
    for ax in grid[len(panels):]:
        ax.set_visible(False)
    fig.tight_layout()
    return fig


def contact_sheet(pairs: Sequence[FramePair], max_error_m: float = 0.05) -> Figure:
    """A row per frame: observed colour | rendered colour | observed depth | rendered depth |
    |depth error| (pixels with both depths; ``max_error_m`` = the top of the colour scale)."""
    titles = ("observed (GT)", "rendered", "observed depth", "rendered depth", f"|depth error| (0 to {100 * max_error_m:g} cm)")
    h, w = pairs[0].observed_depth.shape
    fig = Figure(figsize=(2.3 * len(titles) * w / max(h, 1) * 0.75 + 1, 2.0 * len(pairs) + 0.6))
    grid = fig.subplots(len(pairs), len(titles), squeeze=False)
    for row, pair in zip(grid, pairs):
        dmax = float(pair.observed_depth.max()) or 1.0
        both = (pair.observed_depth > 0) & (pair.rendered_depth > 0)
        error = np.where(both, np.abs(pair.rendered_depth - pair.observed_depth), np.nan)
        images = (pair.observed_rgb, pair.rendered_rgb, pair.observed_depth, pair.rendered_depth, error)
        styles = ({}, {}, dict(cmap="viridis", vmin=0, vmax=dmax), dict(cmap="viridis", vmin=0, vmax=dmax),
                  dict(cmap="magma", vmin=0, vmax=max_error_m))
        for ax, image, style in zip(row, images, styles):
            ax.imshow(np.clip(image, 0, 1) if image.ndim == 3 else image, interpolation="nearest", **style)
            ax.set_xticks([])
            ax.set_yticks([])
        row[0].set_ylabel(f"frame {pair.frame}\n{pair.time_s:.2f} s", fontsize=9)
    for ax, title in zip(grid[0], titles):
        ax.set_title(title, fontsize=9)
    fig.tight_layout()
    return fig


def image_grid(images: Sequence[tuple[str, np.ndarray]], cols: int = 2) -> Figure:
    """Images (H, W, 3) in [0, 1] with their titles, ``cols`` per row."""
    rows = -(-len(images) // cols)
    h, w = images[0][1].shape[:2]
    fig = Figure(figsize=(5.5 * cols, 5.5 * rows * h / w + 0.4))
    grid = np.atleast_1d(fig.subplots(rows, cols, squeeze=False)).ravel()
    for ax, (title, image) in zip(grid, images):
        ax.imshow(image, interpolation="nearest")
        ax.set_title(title, fontsize=10)
        ax.set_xticks([])
        ax.set_yticks([])
    for ax in grid[len(images):]:
        ax.set_visible(False)
    fig.tight_layout()
    return fig
