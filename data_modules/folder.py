"""A simple folder layout for your own recordings (documented in docs/datasets.md)::

    <root>/rgb/<stem>.png|.jpg        colour, 8-bit (16-bit accepted)
    <root>/depth/<stem>.png           16-bit depth, metres = value / depth_scale (1000 = mm), 0 = invalid
    <root>/masks/<stem>.png           optional, nonzero = dynamic
    <root>/timestamps.txt             optional, one timestamp [s] per frame in frame order
    <root>/poses.txt                  optional, TUM "timestamp tx ty tz qx qy qz qw", camera-to-world
    <root>/intrinsics.txt|.json       "fx fy cx cy [width height]" or {"fx":..,"fy":..,"cx":..,"cy":..}

Frames are the colour files, paired with the depth (and mask) file of the same stem. Order and
timestamps (``timestamps_from``):

* ``auto`` (default): ``timestamps.txt`` if it exists; else the file names if every stem is a
  decimal number with a '.' (e.g. ``1341846313.553992.png``); else ``frame index / fps``.
* ``file`` / ``names`` / ``fps``: force one source.

Frames are sorted by name-timestamp when names are timestamps, else by the natural order of the
stems (``2.png`` before ``10.png``). Poses are matched to frame timestamps as for TUM
(:func:`data_modules.poses.interpolate_poses`): SLERP between the bracketing poses, a frame within
0.1 ms of a pose takes it (rounded file times), nothing outside the poses' time span or across a gap
longer than ``pose_max_gap`` (those frames get ``gt_pose=None``; ``gt_valid`` flags them).
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import torch

from data_modules.frame import DatasetError, Frame, Intrinsics, intrinsics_from
from data_modules.io import (
    check_same_size,
    check_size,
    read_depth_png,
    read_mask_png,
    read_rgb,
    require_dir,
)
from data_modules.poses import interpolate_poses
from data_modules.sequence import SequenceDataset
from data_modules.tables import (
    finite_float,
    read_intrinsics_file,
    read_pose_table,
    read_table,
)
from data_modules.timestamps import check_monotonic_timestamps

_RGB_EXT = (".png", ".jpg", ".jpeg")
_TS_NAME = re.compile(r"^[0-9]+\.[0-9]+$")


def _natural_key(stem: str) -> list:
    return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", stem)]


def _png_by_stem(folder: Path) -> dict[str, Path]:
    return {p.stem: p for p in folder.iterdir() if p.suffix.lower() == ".png"}


def _partner_files(folder: Path, found: dict[str, Path], stems: list[str], rgb: dict[str, Path]) -> list[Path]:
    """The ``<stem>.png`` of ``folder`` for every colour stem; raise naming the first one missing."""
    for s in stems:
        if s not in found:
            raise DatasetError(folder / f"{s}.png", f"missing (colour image {rgb[s].name} exists)")
    return [found[s] for s in stems]


class FolderSequence(SequenceDataset):
    """Your own recording converted to the folder layout above.

    Args:
        root: the folder.
        depth_scale: depth PNG units per metre (1000 = millimetres; 5000 for TUM-style).
        fps: frame rate for ``frame index / fps`` timestamps.
        timestamps_from: ``auto``, ``file``, ``names`` or ``fps``.
        intrinsics: ``{fx, fy, cx, cy[, width, height]}``; when null, read intrinsics.txt/.json.
        pose_max_gap: longest gap [s] between poses to interpolate across (None = any).
        max_depth: depth above this many metres becomes invalid (0).
        name: sequence name (default: the folder's name).
    """

    def __init__(
        self,
        root: str | Path,
        depth_scale: float = 1000.0,
        fps: float = 30.0,
        timestamps_from: str = "auto",
        intrinsics: dict | None = None,
        pose_max_gap: float | None = 0.1,
        max_depth: float | None = None,
        name: str | None = None,
    ) -> None:
        self.root = require_dir(root, "sequence folder")
        self.name = name or self.root.name
        if not depth_scale > 0:
            raise DatasetError("dataset.depth_scale", f"must be > 0, got {depth_scale}")
        self.depth_scale = float(depth_scale)
        self.max_depth = max_depth
        if timestamps_from not in ("auto", "file", "names", "fps"):
            raise DatasetError("dataset.timestamps_from", f"must be auto, file, names or fps, got {timestamps_from!r}")

        stems, names_are_ts = self._list_frames()
        self.timestamp_source, self.timestamps = self._read_timestamps(timestamps_from, fps, stems, names_are_ts)
        self.intrinsics = self._read_intrinsics(intrinsics)
        self._read_poses(pose_max_gap)

    def _list_frames(self) -> tuple[list[str], bool]:
        """Pair every colour image with its depth (and mask) file; return the stems in frame order
        and whether every stem is a timestamp. Sets rgb_paths, depth_paths, mask_paths, has_masks."""
        self.rgb_dir = require_dir(self.root / "rgb", "rgb folder")
        depth_dir = require_dir(self.root / "depth", "depth folder")
        rgb = {p.stem: p for p in self.rgb_dir.iterdir() if p.suffix.lower() in _RGB_EXT and p.is_file()}
        if not rgb:
            raise DatasetError(self.rgb_dir, "no .png/.jpg colour images")
        stems = list(rgb)
        names_are_ts = all(_TS_NAME.match(s) for s in stems)
        stems.sort(key=(lambda s: float(s)) if names_are_ts else _natural_key)
        self.rgb_paths = [rgb[s] for s in stems]
        depth = _png_by_stem(depth_dir)
        self.depth_paths = _partner_files(depth_dir, depth, stems, rgb)
        extra = sorted(set(depth) - set(stems))
        if extra:
            raise DatasetError(depth_dir / f"{extra[0]}.png", "has no colour image with the same name in rgb/")
        mask_dir = self.root / "masks"
        self.mask_paths = _partner_files(mask_dir, _png_by_stem(mask_dir), stems, rgb) if mask_dir.is_dir() else None
        self.has_masks = self.mask_paths is not None
        return stems, names_are_ts

    def _read_timestamps(self, source: str, fps: float | None, stems: list[str], names_are_ts: bool) -> tuple[str, np.ndarray]:
        """The timestamp source actually used (``auto`` resolved) and (N,) float64 timestamps."""
        ts_file = self.root / "timestamps.txt"
        if source == "auto":
            source = "file" if ts_file.is_file() else ("names" if names_are_ts else "fps")
        if source == "file":
            rows = read_table(ts_file, [("timestamp", finite_float)], what="timestamps file")
            if len(rows) != len(stems):
                raise DatasetError(ts_file, f"has {len(rows)} timestamps but rgb/ has {len(stems)} images")
            ts, where = [r.values[0] for r in rows], str(ts_file)
        elif source == "names":
            if not names_are_ts:
                bad = next(k for k, s in enumerate(stems) if not _TS_NAME.match(s))
                raise DatasetError(self.rgb_paths[bad], "file name is not a timestamp like 1341846313.553992.png")
            ts, where = [float(s) for s in stems], f"{self.rgb_dir} (file names)"
        else:
            if fps is None or not fps > 0:
                raise DatasetError("dataset.fps", f"must be > 0, got {fps}")
            ts, where = np.arange(len(stems), dtype=np.float64) / float(fps), f"{self.rgb_dir} (index / fps)"
        return source, check_monotonic_timestamps(ts, where)

    def _read_intrinsics(self, intrinsics: dict | None) -> Intrinsics:
        """From the ``dataset.intrinsics`` config when given, else intrinsics.txt / .json; the image
        size defaults to the first colour image's."""
        if intrinsics:
            fb = dict(intrinsics)
            missing = [k for k in ("fx", "fy", "cx", "cy") if fb.get(k) is None]
            if missing:
                raise DatasetError("dataset.intrinsics", f"missing {', '.join(missing)}")
            first = read_rgb(self.rgb_paths[0])
            w, h = fb.get("width") or first.shape[1], fb.get("height") or first.shape[0]
            return intrinsics_from("dataset.intrinsics", fb["fx"], fb["fy"], fb["cx"], fb["cy"], w, h)
        files = [self.root / n for n in ("intrinsics.txt", "intrinsics.json") if (self.root / n).is_file()]
        if not files:
            raise DatasetError(self.root / "intrinsics.txt", "not found (give intrinsics.txt/.json or dataset.intrinsics)")
        first = read_rgb(self.rgb_paths[0])
        return read_intrinsics_file(files[0], width=first.shape[1], height=first.shape[0])

    def _read_poses(self, pose_max_gap: float | None) -> None:
        """Sets has_gt_poses, gt_poses (pose or None per frame) and gt_valid from poses.txt."""
        n = len(self.timestamps)
        pose_file = self.root / "poses.txt"
        self.has_gt_poses = pose_file.is_file()
        self.gt_poses: list[torch.Tensor | None] = [None] * n
        self.gt_valid = np.zeros(n, dtype=bool)
        if self.has_gt_poses:
            pts, poses = read_pose_table(pose_file, key="timestamp", what="pose file")
            out, valid = interpolate_poses(pts, poses, self.timestamps, pose_max_gap)
            self.gt_valid = valid
            self.gt_poses = [out[k] if valid[k] else None for k in range(n)]

    def load_frame(self, i: int) -> Frame:
        rgb = read_rgb(self.rgb_paths[i])
        depth = read_depth_png(self.depth_paths[i], self.depth_scale)
        check_same_size(rgb, depth, self.rgb_paths[i], self.depth_paths[i])
        check_size(rgb, self.intrinsics, self.rgb_paths[i], "colour image")
        if self.max_depth is not None:
            depth = np.where(depth > self.max_depth, np.float32(0), depth).astype(np.float32)
        mask = None
        if self.mask_paths is not None:
            m = read_mask_png(self.mask_paths[i])
            check_size(m, self.intrinsics, self.mask_paths[i], "mask")
            mask = torch.from_numpy(m)
        pose = self.gt_poses[i]
        frame = Frame(
            index=i,
            timestamp=float(self.timestamps[i]),
            rgb=torch.from_numpy(np.ascontiguousarray(rgb)),
            depth=torch.from_numpy(np.ascontiguousarray(depth)),
            mask=mask,
            gt_pose=None if pose is None else pose.clone(),
            source=self.rgb_paths[i].name,
        )
        return frame.validate(self.rgb_paths[i], self.intrinsics)

    def describe(self) -> dict[str, object]:
        d = super().describe()
        d.update(gt_valid_frames=int(self.gt_valid.sum()), timestamp_source=self.timestamp_source)
        return d
