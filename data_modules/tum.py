"""TUM RGB-D and Bonn RGB-D Dynamic sequences (same on-disk layout).

Layout::

    <root>/rgb.txt          "timestamp rgb/<file>.png" lines, '#' comments
    <root>/depth.txt        "timestamp depth/<file>.png"
    <root>/groundtruth.txt  "timestamp tx ty tz qx qy qz qw" (optional)
    <root>/rgb/  <root>/depth/   8-bit colour and 16-bit depth PNGs (depth / 5000 = metres)

Frames are the colour images that have a depth image within ``max_time_diff`` (TUM associate.py
semantics: all pairs with |dt| <= the limit, accepted greedily by increasing difference, each image
used once); a frame's timestamp is its colour timestamp. Ground truth is interpolated at the frame
timestamps (SLERP rotation, linear translation) between the two bracketing GT poses; frames before
the first / after the last GT pose or inside a GT gap longer than ``gt_max_gap`` get ``gt_pose=None``
and ``gt_valid[i] = False``.

Distortion: freiburg1/2 and Bonn have radial-tangential distortion. With ``undistort=True``
(default) colour and depth are remapped with the same OpenCV undistortion map onto a pinhole camera
with the *same* K (colour bilinear, depth and masks nearest-neighbour so no depths are mixed), which
keeps the 1:1 colour/depth pixel registration. Pixels that map from outside the image become black
/ invalid. freiburg3 has zero distortion, so nothing is done there.

Colour not registered to depth (e.g. 7-Scenes: raw Kinect streams, colour camera f ≈ 0.9 × the depth
camera's): ``colour_camera=[fx, fy, cx, cy]`` gives the colour camera's intrinsics; each frame's colour
is then resampled onto the depth camera's pixels (through the colour camera's distortion, if any), so
``Frame.rgb`` and ``Frame.depth`` share pixels as the data contract requires. ``colour_offset=[x, y]``
(metres) is the colour camera's centre in the depth camera's frame: each pixel's colour is then taken
where its own depth projects (the baseline's parallax, fx·o/Z, :func:`data_modules.registration.with_parallax`);
without it the model is the homography K_colour K⁻¹ and the parallax at the scene's usual depth goes
into the principal point. ``python -m data_modules.inspect ... colour_camera=true`` estimates the colour
camera from the frames (the offset comes from the rig's calibration).
"""

from __future__ import annotations

import logging
import math
from pathlib import Path

import cv2
import numpy as np
import torch

from data_modules.frame import DatasetError, Frame, intrinsics_from
from data_modules.io import (
    check_same_size,
    check_size,
    read_depth_png,
    read_rgb,
    require_dir,
)
from data_modules.poses import interpolate_poses, orthonormalize_pose
from data_modules.registration import colour_maps, with_parallax
from data_modules.sequence import SequenceDataset
from data_modules.tables import finite_float, read_pose_table, read_table
from data_modules.timestamps import associate_by_timestamp, check_monotonic_timestamps

log = logging.getLogger(__name__)

# fx, fy, cx, cy, (k1, k2, p1, p2, k3) — dataset-formats.md §3.3 / §4.2
CAMERAS: dict[str, tuple[tuple[float, float, float, float], tuple[float, ...]]] = {
    "fr1": ((517.3, 516.5, 318.6, 255.3), (0.2624, -0.9531, -0.0054, 0.0026, 1.1633)),
    "fr2": ((520.9, 521.0, 325.1, 249.7), (0.2312, -0.7849, -0.0033, -0.0001, 0.9172)),
    "fr3": ((535.4, 539.2, 320.1, 247.6), (0.0, 0.0, 0.0, 0.0, 0.0)),
    "ros": ((525.0, 525.0, 319.5, 239.5), (0.0, 0.0, 0.0, 0.0, 0.0)),
    "bonn": ((542.822841, 542.576870, 315.593520, 237.756098), (0.039903, -0.099343, -0.000730, -0.000144, 0.0)),
}

# Bonn marker-to-camera correction, dataset-formats.md §4.3: T_cam = T_ROS @ T_gt @ T_ROS @ T_M
T_ROS = np.array([[-1, 0, 0, 0], [0, 0, 1, 0], [0, 1, 0, 0], [0, 0, 0, 1]], dtype=np.float64)
T_M_RAW = np.array(
    [
        [1.0157, 0.1828, -0.2389, 0.0113],
        [0.0009, -0.8431, -0.6413, -0.0098],
        [-0.3009, 0.6147, -0.8085, 0.0111],
        [0.0, 0.0, 0.0, 1.0],
    ],
    dtype=np.float64,
)
# T_M_RAW's rotation block has singular values ~1.06 (a scaled rotation); use its nearest rotation.
T_M = orthonormalize_pose(torch.from_numpy(T_M_RAW)).numpy()


def bonn_marker_to_camera(T_gt: torch.Tensor) -> torch.Tensor:
    """Bonn groundtruth (marker body) poses (..., 4, 4) -> camera-to-world poses.

    ``T_cam = T_ros @ T_gt @ T_ros @ T_m`` with T_m's rotation block projected to SO(3).
    """
    ros = torch.as_tensor(T_ROS, dtype=T_gt.dtype)
    tm = torch.as_tensor(T_M, dtype=T_gt.dtype)
    return ros @ T_gt @ ros @ tm


def _list_file(root: Path, name: str) -> tuple[np.ndarray, list[Path], list[int], Path]:
    path = root / name
    rows = read_table(path, [("timestamp", finite_float), ("filename", str)], allow_extra=False, what=f"{name}")
    ts = np.array([r.values[0] for r in rows], dtype=np.float64)
    files = [root / r.values[1] for r in rows]
    check_monotonic_timestamps(ts, str(path))
    return ts, files, [r.lineno for r in rows], path


def _check_numbers(**values: object) -> None:
    """Each ``dataset.<key>`` a finite number >= 0 (``depth_scale`` > 0; ``gt_max_gap`` may be
    null), or a one-line DatasetError."""
    for key, value in values.items():
        if value is None and key == "gt_max_gap":
            continue
        ok = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
        strict = key == "depth_scale"
        if not ok or value < 0 or (strict and value == 0):
            raise DatasetError(f"dataset.{key}", f"must be a finite number {'> 0' if strict else '>= 0'}, got {value!r}")


def _numbers(values: list[float], n: int) -> bool:
    vals = tuple(values)
    return len(vals) == n and all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in vals)


def _colour_camera(values: list[float]) -> tuple[float, float, float, float]:
    """dataset.colour_camera as (fx, fy, cx, cy), or a one-line DatasetError."""
    if not _numbers(values, 4) or values[0] <= 0 or values[1] <= 0:
        raise DatasetError("dataset.colour_camera", f"must be [fx, fy, cx, cy] with fx, fy > 0, got {list(values)!r}")
    return tuple(float(v) for v in values)


def _colour_offset(values: list[float]) -> tuple[float, float]:
    """dataset.colour_offset as (x, y) metres, or a one-line DatasetError."""
    if not _numbers(values, 2) or max(abs(v) for v in values) > 1.0:
        raise DatasetError("dataset.colour_offset", f"must be [x, y] in metres (|x|, |y| <= 1), got {list(values)!r}")
    return tuple(float(v) for v in values)


class TUMSequence(SequenceDataset):
    """A TUM RGB-D sequence folder (``rgbd_dataset_freiburgX_<name>``).

    Args:
        root: the extracted sequence folder.
        camera: ``fr1``, ``fr2``, ``fr3`` (default), ``ros`` (525/319.5/239.5, no distortion),
            ``bonn`` or ``custom`` (then give fx, fy, cx, cy).
        fx, fy, cx, cy: override the camera's values (required for ``custom``).
        distortion: override the (k1, k2, p1, p2, k3) coefficients.
        width, height: image size (default: read from the first colour image).
        undistort: remap colour/depth/masks with the distortion model onto the same K.
        depth_scale: raw depth value per metre (5000).
        max_time_diff: rgb<->depth association limit in seconds (0.02).
        gt_max_gap: longest GT gap [s] to interpolate across (0.1); None = any.
        gt_file: ground-truth file name relative to root (``groundtruth.txt``), if present.
        name: sequence name (default: the root folder's name).
        colour_camera: [fx, fy, cx, cy] of unregistered colour's camera (module docstring); None = registered.
        colour_offset: [x, y] metres, that camera's centre in the depth camera's frame (needs colour_camera).
        readout_s: the cameras' rolling-shutter readout in seconds (:class:`~data_modules.frame.Intrinsics`);
            0 = a global shutter. ``conf/dataset/tum.yaml`` gives the Kinect's and Xtion's 0.03.
    """

    default_camera = "fr3"

    def __init__(
        self,
        root: str | Path,
        camera: str | None = None,
        fx: float | None = None,
        fy: float | None = None,
        cx: float | None = None,
        cy: float | None = None,
        distortion: list[float] | None = None,
        width: int | None = None,
        height: int | None = None,
        undistort: bool = True,
        depth_scale: float = 5000.0,
        max_time_diff: float = 0.02,
        gt_max_gap: float | None = 0.1,
        gt_file: str = "groundtruth.txt",
        name: str | None = None,
        colour_camera: list[float] | None = None,
        colour_offset: list[float] | None = None,
        readout_s: float = 0.0,
    ) -> None:
        self.root = require_dir(root, f"{type(self).__name__} sequence folder")
        self.name = name or self.root.name
        _check_numbers(max_time_diff=max_time_diff, gt_max_gap=gt_max_gap, depth_scale=depth_scale)
        camera = camera or self.default_camera
        if camera != "custom" and camera not in CAMERAS:
            raise DatasetError("dataset.camera", f"unknown camera {camera!r} (use {', '.join(CAMERAS)} or custom)")
        base, dist = CAMERAS.get(camera, ((None, None, None, None), (0.0,) * 5))
        vals = [v if v is not None else b for v, b in zip((fx, fy, cx, cy), base)]
        if any(v is None for v in vals):
            raise DatasetError("dataset", "camera=custom needs fx, fy, cx and cy")
        if distortion is not None:
            dist = tuple(float(d) for d in distortion)
            if len(dist) not in (4, 5):
                raise DatasetError("dataset.distortion", f"expected 4 or 5 coefficients (k1 k2 p1 p2 [k3]), got {len(dist)}")
        self.camera = camera
        self.distortion = np.array(dist, dtype=np.float64)
        self.depth_scale = float(depth_scale)

        rgb_ts, rgb_files, rgb_lines, rgb_list = _list_file(self.root, "rgb.txt")
        depth_ts, depth_files, depth_lines, depth_list = _list_file(self.root, "depth.txt")
        rgb_idx, depth_idx = associate_by_timestamp(rgb_ts, depth_ts, max_time_diff)
        if not len(rgb_idx):
            raise DatasetError(rgb_list, f"no colour image has a depth image within {max_time_diff} s in depth.txt")
        self.dropped_rgb = len(rgb_ts) - len(rgb_idx)
        if self.dropped_rgb:
            log.warning("%s: %d colour images without depth within %.3f s skipped", self.root, self.dropped_rgb, max_time_diff)
        self.rgb_paths = [rgb_files[i] for i in rgb_idx]
        self.depth_paths = [depth_files[j] for j in depth_idx]
        for i, j in zip(rgb_idx, depth_idx):
            if not rgb_files[i].is_file():
                raise DatasetError(rgb_files[i], f"missing (listed in {rgb_list.name}:{rgb_lines[i]})")
            if not depth_files[j].is_file():
                raise DatasetError(depth_files[j], f"missing (listed in {depth_list.name}:{depth_lines[j]})")
        self.timestamps = check_monotonic_timestamps(rgb_ts[rgb_idx], str(rgb_list))
        self.depth_timestamps = depth_ts[depth_idx]

        if width is None or height is None:
            h, w = read_rgb(self.rgb_paths[0]).shape[:2]
            width, height = width or w, height or h
        self.intrinsics = intrinsics_from(f"dataset (camera {camera})", *vals, width, height, readout_s)

        self._set_up_remapping(undistort, colour_camera, colour_offset)

        # ground truth
        self.gt_path = self.root / gt_file
        self.has_gt_poses = self.gt_path.is_file()
        self.gt_poses: list[torch.Tensor | None] = [None] * len(self.timestamps)
        self.gt_valid = np.zeros(len(self.timestamps), dtype=bool)
        if self.has_gt_poses:
            gt_ts, gt_poses = read_pose_table(self.gt_path, key="timestamp", what="ground-truth file")
            poses, valid = interpolate_poses(gt_ts, gt_poses, self.timestamps, gt_max_gap)
            poses = self.convert_gt(poses)
            self.gt_valid = valid
            self.gt_poses = [poses[k] if valid[k] else None for k in range(len(valid))]
            if not valid.all():
                log.info("%s: %d of %d frames have no ground truth (outside coverage or gap)", self.root, int((~valid).sum()), len(valid))

    def _set_up_remapping(self, undistort: bool, colour_camera: list[float] | None, colour_offset: list[float] | None) -> None:
        """The undistortion maps (depth, masks; colour when registered) and unregistered colour's own
        camera maps and offset (module docstring)."""
        own = (self.intrinsics.fx, self.intrinsics.fy, self.intrinsics.cx, self.intrinsics.cy)  # undistorted onto the same K
        self._maps = colour_maps(self.intrinsics, own, self.distortion) if undistort and np.any(self.distortion != 0) else None
        self.undistort = self._maps is not None
        self.colour_camera = None if colour_camera is None else _colour_camera(colour_camera)
        dist = self.distortion if undistort else None  # colour: its own camera, resampled onto the depth pixels
        self._colour_maps = self._maps if self.colour_camera is None else colour_maps(self.intrinsics, self.colour_camera, dist)
        if colour_offset is not None and self.colour_camera is None:
            raise DatasetError("dataset.colour_offset", "needs dataset.colour_camera (the offset is that camera's)")
        self.colour_offset = None if colour_offset is None else _colour_offset(colour_offset)

    def convert_gt(self, poses: torch.Tensor) -> torch.Tensor:
        """Hook: map interpolated groundtruth poses to camera-to-world (identity for TUM)."""
        return poses

    def _remap(self, img: np.ndarray, nearest: bool, maps: tuple | None) -> np.ndarray:
        if maps is None:
            return img
        interp = cv2.INTER_NEAREST if nearest else cv2.INTER_LINEAR
        return cv2.remap(img, maps[0], maps[1], interp, borderMode=cv2.BORDER_CONSTANT, borderValue=0)

    def load_frame(self, i: int) -> Frame:
        rgb = read_rgb(self.rgb_paths[i])
        depth = read_depth_png(self.depth_paths[i], self.depth_scale)
        check_same_size(rgb, depth, self.rgb_paths[i], self.depth_paths[i])
        check_size(rgb, self.intrinsics, self.rgb_paths[i], "colour image")
        depth = self._remap(depth, True, self._maps)
        maps = self._colour_maps
        if self.colour_offset is not None:
            maps = with_parallax(maps, depth, self.colour_camera, self.colour_offset)
        rgb = np.clip(self._remap(rgb, False, maps), 0.0, 1.0)
        pose = self.gt_poses[i]
        frame = Frame(
            index=i,
            timestamp=float(self.timestamps[i]),
            rgb=torch.from_numpy(np.ascontiguousarray(rgb, dtype=np.float32)),
            depth=torch.from_numpy(np.ascontiguousarray(depth, dtype=np.float32)),
            mask=None,
            gt_pose=None if pose is None else pose.clone(),
            source=self.rgb_paths[i].name,
        )
        return frame.validate(self.rgb_paths[i], self.intrinsics)

    def describe(self) -> dict[str, object]:
        d = super().describe()
        d.update(gt_valid_frames=int(self.gt_valid.sum()), camera=self.camera, undistort=self.undistort, dropped_rgb=self.dropped_rgb)
        if self.colour_camera is not None:
            d.update(colour_camera=list(self.colour_camera))
        if self.colour_offset is not None:
            d.update(colour_offset=list(self.colour_offset))
        return d


class BonnSequence(TUMSequence):
    """A Bonn RGB-D Dynamic sequence folder (``rgbd_bonn_<name>``): TUM layout, Bonn intrinsics.

    Extra args:
        marker_to_camera: convert the mocap-marker groundtruth to camera poses with
            ``T_ros @ T_gt @ T_ros @ T_m`` (dataset-formats.md §4.3; T_m's rotation block projected to
            SO(3), translation kept). Default True. The marker pose is interpolated first.
    Other args as :class:`TUMSequence` (``camera`` defaults to ``bonn``).
    """

    default_camera = "bonn"

    def __init__(self, root: str | Path, marker_to_camera: bool = True, **kwargs) -> None:
        self.marker_to_camera = bool(marker_to_camera)
        super().__init__(root, **kwargs)
        log.info("%s: Bonn marker-to-camera correction %s", self.root, "applied" if self.marker_to_camera else "NOT applied")

    def convert_gt(self, poses: torch.Tensor) -> torch.Tensor:
        return bonn_marker_to_camera(poses) if self.marker_to_camera else poses

    def describe(self) -> dict[str, object]:
        d = super().describe()
        d["marker_to_camera"] = self.marker_to_camera
        return d
