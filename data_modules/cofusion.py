"""Co-Fusion synthetic image folders (``room4-full`` = Room4, ``car4-full`` = ToyCar3).

Layout (see docs/datasets.md)::

    <root>/calibration.txt                 fx fy cx cy [width height]   (first data line)
    <root>/colour/ColorNNNN.png            8-bit RGB, first frame 0001
    <root>/depth_noise/DepthNNNN.exr       float z-depth in metres (channel Y)
    <root>/depth_original/DepthNNNN.exr    noise-free render (channel R/G/B or Y)
    <root>/mask_id/MaskNNNN.png            object id per pixel, 0 = static (also ``masks_id/``)
    <root>/trajectories/gt-cam-0.txt       frame tx ty tz qx qy qz qw, camera-to-world
    <root>/trajectories/gt-<name>-<id>.txt object-to-world, same columns

Assumptions (from the reference notes, not verified on the real archives): the camera poses are
camera-to-world with OpenCV camera axes (the Blender exporter's "Positive Z" option); set
``blender_camera_axes=True`` to convert from Blender axes (x right, y up, z backward) instead.
``depth_original`` may be Euclidean ray distance instead of z-depth; ``original_is_ray_distance``
picks ``"auto"`` (compare with ``depth_noise``), ``True`` or ``False``.
"""

from __future__ import annotations

import logging
import re
from pathlib import Path

import numpy as np
import torch

from data_modules.frame import DatasetError, Frame, Intrinsics, intrinsics_from
from data_modules.io import (
    check_same_size,
    check_size,
    read_exr_depth,
    read_label_png,
    read_rgb,
    require_dir,
    sanitize_depth,
)
from data_modules.sequence import SequenceDataset
from data_modules.tables import (
    finite_float,
    read_intrinsics_file,
    read_pose_table,
    read_table,
)
from data_modules.timestamps import check_monotonic_timestamps

log = logging.getLogger(__name__)

_BLENDER_TO_OPENCV = np.diag([1.0, -1.0, -1.0, 1.0])


def _numbered_files(folder: Path, prefix: str, suffix: str) -> dict[int, Path]:
    """``{number: path}`` for files ``<prefix><digits><suffix>`` in ``folder`` (case-sensitive prefix)."""
    pat = re.compile(rf"^{re.escape(prefix)}(\d+){re.escape(suffix)}$", re.IGNORECASE)
    out: dict[int, Path] = {}
    for p in folder.iterdir():
        m = pat.match(p.name)
        if m:
            out[int(m.group(1))] = p
    return out


def _partner_files(folder: Path, prefix: str, suffix: str, colours: dict[int, Path]) -> list[Path]:
    """``<prefix>NNNN<suffix>`` of ``folder`` for every colour frame; raise naming the first one missing."""
    found = _numbered_files(folder, prefix, suffix)
    for n, colour in sorted(colours.items()):
        if n not in found:
            raise DatasetError(folder / f"{prefix}{n:04d}{suffix}", f"missing (colour frame {colour.name} exists)")
    return [found[n] for n in sorted(colours)]


def ray_distance_factor(intr: Intrinsics) -> np.ndarray:
    """(H, W) factor sqrt(((u-cx)/fx)^2 + ((v-cy)/fy)^2 + 1): ray distance = z * factor."""
    v, u = np.mgrid[0 : intr.height, 0 : intr.width].astype(np.float64)
    return np.sqrt(((u - intr.cx) / intr.fx) ** 2 + ((v - intr.cy) / intr.fy) ** 2 + 1.0).astype(np.float32)


class CoFusionSequence(SequenceDataset):
    """A Co-Fusion synthetic sequence folder.

    Args:
        root: the extracted archive folder (holding ``colour/``, ``depth_noise/``, ...).
        depth: ``"noise"`` (``depth_noise/``, default) or ``"original"`` (``depth_original/``).
        fps: frame rate used for timestamps ``frame_number / fps`` (24 Hz assumed for Co-Fusion).
        timestamps_file: optional text file with one timestamp [s] per frame (relative to root or
            absolute), in frame order; overrides ``fps``.
        masks: read ``mask_id/`` when present (set False to ignore the masks).
        max_depth: depth above this many metres (Blender "no hit" values) becomes invalid (0).
        original_is_ray_distance: ``"auto"``, ``True`` or ``False`` (only for ``depth="original"``).
        blender_camera_axes: the GT files use Blender camera axes; convert them to OpenCV axes.
        fallback_intrinsics: ``{fx, fy, cx, cy[, width, height]}`` used only if calibration.txt is
            missing (a warning is logged).
        name: sequence name (default: the root folder's name).
    """

    def __init__(
        self,
        root: str | Path,
        depth: str = "noise",
        fps: float = 24.0,
        timestamps_file: str | Path | None = None,
        masks: bool = True,
        max_depth: float = 100.0,
        original_is_ray_distance: str | bool = "auto",
        blender_camera_axes: bool = False,
        fallback_intrinsics: dict | None = None,
        name: str | None = None,
    ) -> None:
        self.root = require_dir(root, "Co-Fusion sequence folder")
        self.name = name or self.root.name
        if depth not in ("noise", "original"):
            raise DatasetError("dataset.depth", f"must be 'noise' or 'original', got {depth!r}")
        if fps is None or not fps > 0:
            raise DatasetError("dataset.fps", f"must be > 0, got {fps}")
        self.max_depth = float(max_depth)
        self.depth_kind = depth

        self._list_frames(depth, masks)
        self.intrinsics = self._read_intrinsics(fallback_intrinsics)
        self.timestamps = self._read_timestamps(timestamps_file, fps)
        self.fps = float(fps)
        self._read_trajectories(blender_camera_axes)

        self.ray_distance = False
        if depth == "original":
            self.ray_distance = self._decide_ray_distance(original_is_ray_distance)
        self._ray_factor = ray_distance_factor(self.intrinsics) if self.ray_distance else None

    # ------------------------------------------------------------------------------------------
    def _list_frames(self, depth: str, masks: bool) -> None:
        """Sets frame_numbers, colour_paths, depth_paths, mask_paths and has_masks; frames must be
        numbered without gaps and every frame needs its depth (and mask) file."""
        colour_dir = require_dir(self.root / "colour", "colour folder")
        depth_dir = require_dir(self.root / f"depth_{depth}", f"depth_{depth} folder")
        colours = _numbered_files(colour_dir, "Color", ".png")
        if not colours:
            raise DatasetError(colour_dir, "no ColorNNNN.png files")
        numbers = sorted(colours)
        first, last = numbers[0], numbers[-1]
        if len(numbers) != last - first + 1:
            missing = sorted(set(range(first, last + 1)) - set(numbers))[0]
            raise DatasetError(colour_dir / f"Color{missing:04d}.png", f"missing (frames {first}..{last} expected without gaps)")
        self.frame_numbers = np.asarray(numbers, dtype=np.int64)
        self.colour_paths = [colours[n] for n in numbers]
        self.depth_paths = _partner_files(depth_dir, "Depth", ".exr", colours)
        mask_dir = next((self.root / d for d in ("mask_id", "masks_id") if (self.root / d).is_dir()), None)
        self.mask_paths = _partner_files(mask_dir, "Mask", ".png", colours) if masks and mask_dir is not None else None
        self.has_masks = self.mask_paths is not None

    def _read_timestamps(self, timestamps_file: str | Path | None, fps: float) -> np.ndarray:
        """(N,) float64 timestamps: one per line of ``timestamps_file`` (relative to root), else
        frame number / fps."""
        n = len(self.frame_numbers)
        if timestamps_file is None:
            return check_monotonic_timestamps(self.frame_numbers / float(fps), f"{self.root} (frame numbers / fps)")
        tpath = Path(timestamps_file)
        if not tpath.is_absolute():
            tpath = self.root / tpath
        rows = read_table(tpath, [("timestamp", finite_float)], what="timestamps file")
        if len(rows) != n:
            raise DatasetError(tpath, f"has {len(rows)} timestamps but the sequence has {n} frames")
        return check_monotonic_timestamps([r.values[0] for r in rows], str(tpath))

    def _read_trajectories(self, blender_camera_axes: bool) -> None:
        """Sets has_gt_poses, gt_poses / gt_valid (camera, per frame), object_trajectories and object_ids."""
        n = len(self.frame_numbers)
        traj_dir = self.root / "trajectories"
        self.gt_poses: list[torch.Tensor | None] = [None] * n
        self.gt_valid = np.zeros(n, dtype=bool)
        self.object_trajectories: dict[str, tuple[np.ndarray, torch.Tensor]] = {}
        self.object_ids: dict[str, int] = {}
        cam_file = traj_dir / "gt-cam-0.txt"
        self.has_gt_poses = cam_file.is_file()
        if self.has_gt_poses:
            frames, poses = read_pose_table(cam_file, key="frame", what="camera trajectory")
            if blender_camera_axes:
                poses = poses @ torch.from_numpy(_BLENDER_TO_OPENCV)
            index = {int(num): i for i, num in enumerate(self.frame_numbers)}
            for f, pose in zip(frames, poses):
                i = index.get(int(f))
                if i is not None:
                    self.gt_poses[i] = pose
                    self.gt_valid[i] = True
        if not traj_dir.is_dir():
            return
        for p in sorted(traj_dir.glob("gt-*.txt")):
            if p.name == "gt-cam-0.txt":
                continue
            key = p.stem[3:]
            self.object_trajectories[key] = read_pose_table(p, key="frame", what="object trajectory")
            m = re.search(r"(\d+)$", key)
            if m:
                self.object_ids[key] = int(m.group(1))

    def _read_intrinsics(self, fallback: dict | None) -> Intrinsics:
        calib = self.root / "calibration.txt"
        if calib.is_file():
            # the size comes from the file (6 numbers) or from the first colour image
            try:
                return read_intrinsics_file(calib)
            except DatasetError as e:
                if "image size unknown" not in e.problem:
                    raise
            h, w = read_rgb(self.colour_paths[0]).shape[:2]
            return read_intrinsics_file(calib, width=w, height=h)
        if fallback:
            log.warning("%s: calibration.txt missing, using the configured fallback intrinsics", self.root)
            fb = dict(fallback)
            if "width" not in fb or "height" not in fb:
                h, w = read_rgb(self.colour_paths[0]).shape[:2]
                fb.setdefault("width", w)
                fb.setdefault("height", h)
            missing = [k for k in ("fx", "fy", "cx", "cy") if fb.get(k) is None]
            if missing:
                raise DatasetError("dataset.fallback_intrinsics", f"missing {', '.join(missing)}")
            return intrinsics_from("dataset.fallback_intrinsics", fb["fx"], fb["fy"], fb["cx"], fb["cy"], fb["width"], fb["height"])
        raise DatasetError(calib, "calibration file not found (and no fallback_intrinsics configured)")

    def _decide_ray_distance(self, setting: str | bool) -> bool:
        if isinstance(setting, bool):
            return setting
        if str(setting).lower() in ("true", "false"):
            return str(setting).lower() == "true"
        if setting != "auto":
            raise DatasetError("dataset.original_is_ray_distance", f"must be auto, true or false, got {setting!r}")
        noise_path = self.root / "depth_noise" / self.depth_paths[0].name
        if not noise_path.is_file():
            log.warning("%s: cannot compare with depth_noise; assuming depth_original is z-depth", self.root)
            return False
        orig = sanitize_depth(read_exr_depth(self.depth_paths[0]), self.max_depth)
        noisy = sanitize_depth(read_exr_depth(noise_path), self.max_depth)
        factor = ray_distance_factor(self.intrinsics)
        if orig.shape != factor.shape or noisy.shape != factor.shape:
            return False
        sel = (orig > 0) & (noisy > 0) & (factor > 1.02)
        if sel.sum() < 10:
            log.warning("%s: too few off-centre pixels to detect ray distance; assuming z-depth", self.root)
            return False
        ratio = orig[sel] / noisy[sel]
        err_z = np.median(np.abs(ratio - 1.0))
        err_ray = np.median(np.abs(ratio - factor[sel]))
        decision = bool(err_ray < err_z)
        log.info("%s: depth_original looks like %s", self.root, "ray distance (converted to z)" if decision else "z-depth")
        return decision

    def load_depth(self, i: int) -> np.ndarray:
        path = self.depth_paths[i]
        d = sanitize_depth(read_exr_depth(path), self.max_depth)
        check_size(d, self.intrinsics, path, "depth")
        if self._ray_factor is not None:
            d = (d / self._ray_factor).astype(np.float32)
        return d

    def load_mask_ids(self, i: int) -> np.ndarray | None:
        """The raw object-id image of frame ``i`` (0 = static), or None without masks."""
        if self.mask_paths is None:
            return None
        ids = read_label_png(self.mask_paths[i])
        check_size(ids, self.intrinsics, self.mask_paths[i], "mask")
        return ids

    def load_frame(self, i: int) -> Frame:
        rgb = read_rgb(self.colour_paths[i])
        depth = self.load_depth(i)
        check_same_size(rgb, depth, self.colour_paths[i], self.depth_paths[i])
        check_size(rgb, self.intrinsics, self.colour_paths[i], "colour image")
        ids = self.load_mask_ids(i)
        frame = Frame(
            index=i,
            timestamp=float(self.timestamps[i]),
            rgb=torch.from_numpy(np.ascontiguousarray(rgb)),
            depth=torch.from_numpy(np.ascontiguousarray(depth)),
            mask=None if ids is None else torch.from_numpy(ids != 0),
            gt_pose=None if self.gt_poses[i] is None else self.gt_poses[i].clone(),
            source=self.colour_paths[i].name,
            instances=None if ids is None else torch.from_numpy(ids.astype(np.int64)),
        )
        return frame.validate(self.colour_paths[i], self.intrinsics)

    def describe(self) -> dict[str, object]:
        d = super().describe()
        d.update(
            gt_valid_frames=int(self.gt_valid.sum()),
            depth=self.depth_kind,
            objects=sorted(self.object_trajectories),
        )
        return d
