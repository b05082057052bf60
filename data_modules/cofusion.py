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
    finite_float,
    read_exr_depth,
    read_intrinsics_file,
    read_label_png,
    read_pose_table,
    read_rgb,
    read_table,
    require_dir,
    sanitize_depth,
)
from data_modules.sequence import SequenceDataset
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

        depths = _numbered_files(depth_dir, "Depth", ".exr")
        self.depth_paths = []
        for n in numbers:
            if n not in depths:
                raise DatasetError(depth_dir / f"Depth{n:04d}.exr", f"missing (colour frame {colours[n].name} exists)")
            self.depth_paths.append(depths[n])

        self.mask_paths: list[Path] | None = None
        mask_dir = next((self.root / d for d in ("mask_id", "masks_id") if (self.root / d).is_dir()), None)
        if masks and mask_dir is not None:
            found = _numbered_files(mask_dir, "Mask", ".png")
            self.mask_paths = []
            for n in numbers:
                if n not in found:
                    raise DatasetError(mask_dir / f"Mask{n:04d}.png", f"missing (colour frame {colours[n].name} exists)")
                self.mask_paths.append(found[n])
        self.has_masks = self.mask_paths is not None

        self.intrinsics = self._read_intrinsics(fallback_intrinsics)

        # timestamps
        if timestamps_file is not None:
            tpath = Path(timestamps_file)
            if not tpath.is_absolute():
                tpath = self.root / tpath
            rows = read_table(tpath, [("timestamp", finite_float)], what="timestamps file")
            if len(rows) != len(numbers):
                raise DatasetError(tpath, f"has {len(rows)} timestamps but the sequence has {len(numbers)} frames")
            ts = [r.values[0] for r in rows]
            self.timestamps = check_monotonic_timestamps(ts, str(tpath))
        else:
            self.timestamps = check_monotonic_timestamps(self.frame_numbers / float(fps), f"{self.root} (frame numbers / fps)")
        self.fps = float(fps)

        # ground truth
        traj_dir = self.root / "trajectories"
        self.gt_poses: list[torch.Tensor | None] = [None] * len(numbers)
        self.gt_valid = np.zeros(len(numbers), dtype=bool)
        self.object_trajectories: dict[str, tuple[np.ndarray, torch.Tensor]] = {}
        self.object_ids: dict[str, int] = {}
        cam_file = traj_dir / "gt-cam-0.txt"
        self.has_gt_poses = cam_file.is_file()
        if self.has_gt_poses:
            frames, poses = read_pose_table(cam_file, key="frame", what="camera trajectory")
            if blender_camera_axes:
                poses = poses @ torch.from_numpy(_BLENDER_TO_OPENCV)
            index = {int(n): i for i, n in enumerate(numbers)}
            for f, pose in zip(frames, poses):
                i = index.get(int(f))
                if i is not None:
                    self.gt_poses[i] = pose
                    self.gt_valid[i] = True
        if traj_dir.is_dir():
            for p in sorted(traj_dir.glob("gt-*.txt")):
                if p.name == "gt-cam-0.txt":
                    continue
                key = p.stem[3:]
                frames, poses = read_pose_table(p, key="frame", what="object trajectory")
                self.object_trajectories[key] = (frames, poses)
                m = re.search(r"(\d+)$", key)
                if m:
                    self.object_ids[key] = int(m.group(1))

        self.ray_distance = False
        if depth == "original":
            self.ray_distance = self._decide_ray_distance(original_is_ray_distance)
        self._ray_factor = ray_distance_factor(self.intrinsics) if self.ray_distance else None

    # ------------------------------------------------------------------------------------------
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
