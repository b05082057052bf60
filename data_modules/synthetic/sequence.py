"""The synthetic RGB-D dataset: any preset scene of the family, rendered exactly, with full ground truth.

Everything is generated procedurally and rendered *exactly* by vectorised analytic ray casting, so the
dataset comes with perfect ground truth: camera poses, per-object poses, dynamic masks and object
labels, and the exact signed distance / surface of the scene at any time, plus which surface the
cameras saw (:meth:`SyntheticSequence.visible`). World frame: metres, z up, floor at z = 0; poses are
camera-to-world with OpenCV camera axes (x right, y down, z forward).
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping
from dataclasses import fields, replace

import numpy as np
import torch

from data_modules.frame import DatasetError, Frame, Intrinsics
from data_modules.sequence import SequenceDataset
from data_modules.synthetic.cache import FrameCache
from data_modules.synthetic.presets import PRESETS, build_scene
from data_modules.synthetic.render import TextureBank, View, pixel_flow, pixel_rays, render_view
from data_modules.synthetic.scene import Hit, Placed, place, raycast, sample_surface, scene_sdf
from data_modules.synthetic.sensor import SensorModel, blur_offsets, corrupt_depth, corrupt_rgb, smear
from data_modules.synthetic.shapes import bound_half

__all__ = ["RENDER_VERSION", "SyntheticSequence"]

# Bump whenever the rendered images change for the same parameters, so stale caches are not reused.
RENDER_VERSION = 2


def _is_int(x: object, lowest: int) -> bool:
    return isinstance(x, (int, float, np.integer)) and not isinstance(x, bool) and float(x).is_integer() and x >= lowest


def _is_finite(x: object) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)


def _sensor_model(preset: str, depth_noise: bool, rgb_noise: float | None, sensor: Mapping[str, object] | None) -> SensorModel:
    """Kinect-like defaults, then the preset's settings, then the caller's (None = keep)."""
    known = {f.name for f in fields(SensorModel)} - {"depth_noise", "rgb_noise"}
    given = {k: v for k, v in dict(sensor or {}).items() if v is not None}
    for key in given:
        if key not in known:
            raise DatasetError(f"dataset.sensor.{key}", f"unknown sensor setting; known: {', '.join(sorted(known))}")
    if not isinstance(depth_noise, bool):
        raise DatasetError("dataset.depth_noise", f"must be true or false, got {depth_noise!r}")
    model = replace(SensorModel(), **{**PRESETS[preset].sensor, **given}, depth_noise=depth_noise)
    if rgb_noise is not None:
        model = replace(model, rgb_noise=rgb_noise)
    for key, problem in model.problems():
        raise DatasetError("dataset.rgb_noise" if key == "rgb_noise" else f"dataset.sensor.{key}", problem)
    return model


class SyntheticSequence(SequenceDataset):
    """Procedural, exactly rendered RGB-D sequence of a preset dynamic scene.

    Args:
        scene: preset name (``data_modules.synthetic.presets.PRESETS``): cube, big_fast, crossing,
            static_room, stop_and_go, orbit_ball, fast_turn, three_objects, door, breathing.
        seed: sensor-noise realisation, and the scene layout unless ``scene_seed`` is given (the
            ``cube`` scene is fixed: its seed only selects the noise).
        num_frames: number of frames (>= 1); frame ``i`` has timestamp ``i / fps`` seconds.
        fps: frame rate.
        width, height: image size in pixels (>= 16 each). ``fx = fy = 0.8 * width``,
            ``cx = (width - 1) / 2``, ``cy = (height - 1) / 2``.
        depth_noise: False = exact depth (every depth part of the sensor off).
        rgb_noise: sigma of additive colour noise (None = the preset's, 0.01); colours are always
            8-bit quantised.
        sensor: overrides of :class:`~data_modules.synthetic.sensor.SensorModel` fields (axial,
            edge_dropout, grazing_dropout, holes, dropout, lateral, quantization, exposure,
            motion_blur, shutter, blur_exact; None values keep the preset's setting, 0 switches a
            part off).
        camera_speed, object_speed: time scales of the camera and object trajectories (0 = still).
        cache_dir: directory for rendered frames (``~`` expanded), or None for no caching. Frames go
            to ``cache_dir/<name>-<hash of every render parameter>/frame_NNNNN.npz``.
        scene_seed: layout seed (None = ``seed``).
        name: dataset name (run folders); default ``synthetic_<scene>``.

    Ground truth (world frame, float64): :meth:`camera_pose`, :meth:`camera_pose_at`,
    :meth:`object_poses`, :attr:`object_names`, :meth:`dynamic_box`, :meth:`sdf`,
    :meth:`sample_surface`, :meth:`visible`, :meth:`raycast`, :meth:`render`, :meth:`labels`.
    """

    has_gt_poses = True
    has_masks = True

    def __init__(self, scene: str = "cube", seed: int = 0, num_frames: int = 150, fps: float = 30.0, width: int = 640,
                 height: int = 480, depth_noise: bool = True, rgb_noise: float | None = None,
                 sensor: Mapping[str, object] | None = None, camera_speed: float = 1.0, object_speed: float = 1.0,
                 cache_dir: str | os.PathLike | None = None, scene_seed: int | None = None, name: str | None = None) -> None:
        self._check_args(scene, seed, scene_seed, num_frames, fps, width, height, camera_speed, object_speed, rgb_noise)
        self.scene_name = scene
        self.seed = int(seed)
        self.scene_seed = self.seed if scene_seed is None else int(scene_seed)
        self.name = name or f"synthetic_{scene}"
        self.num_frames, self.fps = int(num_frames), float(fps)
        self.width, self.height = int(width), int(height)
        self.camera_speed, self.object_speed = float(camera_speed), float(object_speed)
        self.sensor = _sensor_model(scene, depth_noise, rgb_noise, sensor)
        self.scene = build_scene(scene, self.scene_seed)
        self.object_names = [m.name for m in self.scene.movers]
        self.room_min, self.room_max = self.scene.room.lo, self.scene.room.hi
        f = 0.8 * self.width
        self.intrinsics = Intrinsics(f, f, (self.width - 1) / 2.0, (self.height - 1) / 2.0, self.width, self.height)
        self.timestamps = np.arange(self.num_frames, dtype=np.float64) / self.fps
        self._rays = pixel_rays(f, f, self.intrinsics.cx, self.intrinsics.cy, self.width, self.height)
        self._bank = TextureBank(self.scene.room, place(self.scene, 0.0))
        self.cache = FrameCache(cache_dir, self.name, self.render_params())

    @staticmethod
    def _check_args(scene, seed, scene_seed, num_frames, fps, width, height, camera_speed, object_speed, rgb_noise) -> None:
        def bad(param: str, problem: str) -> DatasetError:
            return DatasetError(f"dataset.{param}", problem)

        if scene not in PRESETS:
            raise bad("scene", f"unknown scene {scene!r}; presets: {', '.join(PRESETS)}")
        if not _is_int(num_frames, 1):
            raise bad("num_frames", f"must be an integer >= 1, got {num_frames!r}")
        if not (_is_finite(fps) and fps > 0):
            raise bad("fps", f"must be a finite number > 0, got {fps!r}")
        for pname, val in (("width", width), ("height", height)):
            if not _is_int(val, 16):
                raise bad(pname, f"must be an integer >= 16 pixels, got {val!r}")
        for pname, val in (("seed", seed), ("scene_seed", 0 if scene_seed is None else scene_seed)):
            if not _is_int(val, 0):
                raise bad(pname, f"must be a non-negative integer, got {val!r}")
        for pname, val in (("camera_speed", camera_speed), ("object_speed", object_speed)):
            if not _is_finite(val):
                raise bad(pname, f"must be a finite number, got {val!r}")
        if rgb_noise is not None and not (_is_finite(rgb_noise) and 0 <= rgb_noise <= 0.5):
            raise bad("rgb_noise", f"must be within [0, 0.5], got {rgb_noise!r}")

    # ------------------------------------------------------------------------------ parameters

    def render_params(self) -> dict[str, object]:
        """Everything that determines the pixels of frame ``i`` (``num_frames`` does not)."""
        return {
            "version": RENDER_VERSION, "scene": self.scene_name, "scene_seed": self.scene_seed,
            "scene_repr": repr(self.scene), "seed": self.seed, "fps": self.fps, "width": self.width,
            "height": self.height, "camera_speed": self.camera_speed, "object_speed": self.object_speed,
            "sensor": self.sensor.as_dict(),
        }

    def render_key(self) -> str:
        """Short hash of :meth:`render_params` (names the cache folder)."""
        return self.cache.key

    # ------------------------------------------------------------------------- ground-truth motion

    def camera_pose_at(self, t: float) -> torch.Tensor:
        """(4, 4) float64 camera-to-world pose at time ``t`` seconds (bounded for any ``t``)."""
        return torch.from_numpy(self.scene.camera.pose(self.camera_speed * float(t)))

    def camera_pose(self, i: int) -> torch.Tensor:
        """(4, 4) float64 camera-to-world ground-truth pose of frame ``i``."""
        return self.camera_pose_at(float(self.timestamps[i]) if 0 <= i < len(self) else i / self.fps)

    def camera_poses(self) -> torch.Tensor:
        """(N, 4, 4) float64 ground-truth camera-to-world poses of all frames."""
        return torch.stack([self.camera_pose(i) for i in range(len(self))])

    def object_poses(self, t: float) -> dict[str, torch.Tensor]:
        """Object-to-world (4, 4) float64 pose of every moving object at time ``t`` seconds (the object
        frame is at the shape's centre, axes along its local axes; cylinders along local z)."""
        s = self.object_speed * float(t)
        return {m.name: torch.from_numpy(m.motion.pose(s)) for m in self.scene.movers}

    def dynamic_box(self, t: float, name: str | None = None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Oriented bounding box of moving object ``name`` (default: the first) at time ``t``:
        center (3,), half_extents (3,), R (3, 3). A world point ``p`` is inside iff
        ``all(|R^T (p - center)| <= half_extents)``; for a box it is the box itself."""
        if name is None and self.object_names:
            name = self.object_names[0]
        if name not in self.object_names:
            raise KeyError(f"unknown object {name!r}; objects: {self.object_names}")
        T = self.object_poses(t)[name]
        shape = self.scene.movers[self.object_names.index(name)].shape
        return T[:3, 3].clone(), torch.from_numpy(bound_half(shape)), T[:3, :3].clone()

    def placed(self, t: float) -> list[Placed]:
        """Every primitive posed at sequence time ``t`` seconds."""
        return place(self.scene, self.object_speed * float(t))

    # ----------------------------------------------------------------------------- exact geometry

    def sdf(self, points: torch.Tensor, t: float, part: str = "all") -> torch.Tensor:
        """Exact signed distance (N,) float64 metres of (N, 3) world points at time ``t``.

        ``part``: "all", "static" (room + static objects) or "dynamic" (moving objects only; +inf
        without any). Positive in free space, negative inside solids and beyond the walls.
        """
        return scene_sdf(self.scene.room, self.placed(t), points, part)

    def sample_surface(self, t: float, n: int, part: str = "all", seed: int = 0, name: str | None = None) -> torch.Tensor:
        """(n, 3) float64 world points uniform by area on the surfaces at time ``t``.

        ``part``: "all", "static" or "dynamic"; ``name``: only that moving or static object. Surface
        hidden by contact (box bottoms on the floor, the floor under them) is excluded. Empty (0, 3)
        when the selection has no surface (``part="dynamic"`` in a static scene).
        """
        if name is not None and name not in [o.name for o in self.scene.statics + self.scene.movers]:
            raise KeyError(f"unknown object {name!r}")
        gen = torch.Generator().manual_seed(int(seed))
        return sample_surface(self.scene.room, self.placed(t), int(n), gen, part, None if name is None else (name,))

    def raycast(self, c2w: torch.Tensor, t: float, rays_cam: torch.Tensor | None = None) -> Hit:
        """First hits at time ``t`` of camera rays from pose ``c2w``: ``rays_cam`` (N, 3) camera-frame
        directions with z = 1 (hit fields of shape (1, N)), default every pixel ((H, W))."""
        c2w = torch.as_tensor(c2w, dtype=torch.float64)
        d = self._rays if rays_cam is None else torch.as_tensor(rays_cam, dtype=torch.float64).reshape(-1, 3).T[:, None]
        return raycast(self.scene.room, self.placed(t), c2w[:3, 3], (c2w[:3, :3] @ d.reshape(3, -1)).view(d.shape))

    def visible(self, points: torch.Tensor, t: float, window: float = 0.0, name: str | None = None) -> torch.Tensor:
        """Which surface points were seen by a camera of this sequence within ``window`` s of ``t``.

        Args:
            points: (N, 3) world points on the surface at time ``t`` (e.g. :meth:`sample_surface`).
            t: time of the points, seconds.
            window: frames with ``|timestamp - t| <= window`` count.
            name: the moving object the points belong to (they move with it to each frame's time),
                or None for static points.
        Returns:
            (N,) bool: True where, in some such frame, the point projects into the image in front of
            the camera and the first surface on the ray from the camera to the point is the point
            itself (no occluder, not a face turned away).
        """
        if name is not None and name not in self.object_names:
            raise KeyError(f"unknown moving object {name!r}; objects: {self.object_names}")
        p = torch.as_tensor(points, dtype=torch.float64).reshape(-1, 3)
        seen = torch.zeros(p.shape[0], dtype=torch.bool)
        K = self.intrinsics
        frames = np.flatnonzero(np.abs(self.timestamps - float(t)) <= float(window) + 1e-9)
        for i in frames:
            ti = float(self.timestamps[i])
            pi = p
            if name is not None:
                pi = self._carry(name, p, t, ti)
            c2w = self.camera_pose(int(i))
            cam = (pi - c2w[:3, 3]) @ c2w[:3, :3]
            z = cam[:, 2]
            u, v = K.fx * cam[:, 0] / z + K.cx, K.fy * cam[:, 1] / z + K.cy
            inside = (z > 1e-6) & (u >= -0.5) & (u < K.width - 0.5) & (v >= -0.5) & (v < K.height - 0.5)
            if not bool(inside.any()):
                continue
            hit = self.raycast(c2w, ti, cam[inside] / z[inside, None])
            seen[inside] |= hit.depth.reshape(-1) >= z[inside] - 1e-5 * (1.0 + z[inside])
        return seen

    def _carry(self, name: str, p: torch.Tensor, t: float, ti: float) -> torch.Tensor:
        """(N, 3) points on moving object ``name`` at time ``t`` -> where they are at ``ti`` (its
        rigid motion, and the change of its breathing scale for a non-rigid object)."""
        a, b = self.object_poses(t)[name], self.object_poses(ti)[name]
        local = (p - a[:3, 3]) @ a[:3, :3]
        scale = getattr(self.scene.movers[self.object_names.index(name)].motion, "scale", None)
        if scale is not None:
            local = local * (scale(self.object_speed * ti) / scale(self.object_speed * t))
        return local @ b[:3, :3].T + b[:3, 3]

    # --------------------------------------------------------------------------------- rendering

    def _view(self, t: float, colour: bool = True) -> View:
        K = self.intrinsics
        return render_view(self.scene.room, self.placed(t), self._bank, self.camera_pose_at(t), self._rays,
                           (K.fx, K.fy, K.cx, K.cy), colour=colour)

    def render_at(self, c2w: torch.Tensor, t: float) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Noise-free view of the scene at time ``t`` from any camera pose ``c2w`` (4, 4): rgb (H, W, 3)
        float in [0, 1] on 8-bit levels, depth (H, W) float32 metres, labels (H, W) uint8 (0 = static,
        k = ``object_names[k - 1]``)."""
        K = self.intrinsics
        view = render_view(self.scene.room, self.placed(t), self._bank, torch.as_tensor(c2w, dtype=torch.float64), self._rays,
                           (K.fx, K.fy, K.cx, K.cy), colour=True)
        labels = (view.prim - len(self.scene.statics)).clamp_min(0).to(torch.uint8)
        rgb = (view.rgb.clamp(0, 1) * 255.0).round() / 255.0
        return rgb.float(), view.depth.float(), labels

    def render_rolling_shutter(
        self, c2w: torch.Tensor, velocity: torch.Tensor, readout_s: float, t: float = 0.0, band: int = 6
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Noise-free rgb (H, W, 3) and depth (H, W) of the scene at ``t`` as a rolling shutter sees
        them: rows read top to bottom over ``readout_s`` seconds, each band of ``band`` rows rendered
        (:meth:`render_at`) from the pose the camera, moving at ``velocity`` (6,) (body twist (v, ω)
        per second: c2w(s) = c2w · exp(s·velocity)), has when that band is read; ``c2w`` (4, 4) is the
        camera at the middle row."""
        xi = torch.as_tensor(velocity, dtype=torch.float64)
        twist = torch.zeros(4, 4, dtype=torch.float64)
        twist[:3, :3] = torch.tensor([[0.0, -xi[5], xi[4]], [xi[5], 0.0, -xi[3]], [-xi[4], xi[3], 0.0]], dtype=torch.float64)
        twist[:3, 3] = xi[:3]
        H = self.height
        rgb, depth = torch.zeros(H, self.width, 3), torch.zeros(H, self.width)
        for r0 in range(0, H, band):
            seconds = ((r0 + (min(band, H - r0) - 1) / 2) - (H - 1) / 2) / H * readout_s
            c, d, _ = self.render_at(torch.as_tensor(c2w, dtype=torch.float64) @ torch.linalg.matrix_exp(seconds * twist), t)
            rgb[r0:r0 + band], depth[r0:r0 + band] = c[r0:r0 + band], d[r0:r0 + band]
        return rgb, depth

    def render_arrays(self, i: int, noise: bool = True) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Render frame ``i`` (no cache): rgb (H, W, 3) uint8, depth (H, W) float32 metres (0 = no
        measurement), labels (H, W) uint8 (0 = static, k = ``object_names[k - 1]``).

        ``noise=False``: exact depth and noise-free colour (no blur, gain or noise; still 8-bit)."""
        if not 0 <= i < len(self):
            raise IndexError(f"frame {i} out of range for {self.name} with {len(self)} frames")
        t = float(self.timestamps[i])
        offsets = blur_offsets(self.sensor, self.fps) if noise else []
        exact_blur = bool(offsets) and self.sensor.blur_exact
        view = self._view(t, colour=not exact_blur)
        labels = (view.prim - len(self.scene.statics)).clamp_min(0)
        rgb = view.rgb
        if exact_blur:  # average colour renders over the shutter
            rgb = torch.stack([self._view(t + dt).rgb for dt in offsets]).mean(0)
        elif offsets:  # warp the frame along each pixel's exact motion
            rgb = smear(rgb, [self._flow(view.depth, labels, t, t + dt) for dt in offsets])
        if noise:
            rgb8 = corrupt_rgb(rgb, t, self.sensor, self.seed, i)
            depth = corrupt_depth(view.depth.numpy(), view.cos.numpy(), self.sensor, self.seed, i)
        else:
            rgb8, depth = (rgb.clamp(0, 1) * 255.0).round().to(torch.uint8), view.depth.numpy()
        return rgb8.numpy(), depth.astype(np.float32), labels.to(torch.uint8).numpy()

    def _flow(self, depth: torch.Tensor, labels: torch.Tensor, t: float, s: float) -> torch.Tensor:
        """(H, W, 2) pixel motion of the surface seen at time ``t`` to time ``s``."""
        a, b = self.object_poses(t), self.object_poses(s)
        moves = [b[n] @ torch.linalg.inv(a[n]) for n in self.object_names]
        K = self.intrinsics
        return pixel_flow(depth, labels, self._rays, self.camera_pose_at(t), self.camera_pose_at(s), moves, (K.fx, K.fy, K.cx, K.cy))

    def _frame(self, i: int, rgb8: np.ndarray, depth: np.ndarray, labels: np.ndarray) -> Frame:
        frame = Frame(
            index=int(i),
            timestamp=float(self.timestamps[i]),
            rgb=torch.from_numpy(rgb8).to(torch.float32) / 255.0,
            depth=torch.from_numpy(depth),
            mask=torch.from_numpy(labels > 0),
            gt_pose=self.camera_pose(i),
            instances=torch.from_numpy(labels.astype(np.int64)),  # k = object_names[k - 1]
        )
        return frame.validate(f"{self.name} frame {i}", self.intrinsics)

    def render(self, i: int, noise: bool = True) -> Frame:
        """Render frame ``i`` (no cache). ``noise=False`` gives exact depth and noise-free colour."""
        return self._frame(i, *self.render_arrays(i, noise))

    def _arrays(self, i: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Frame ``i``'s sensor arrays from the cache, rendered and stored on a miss."""
        cached = self.cache.read(i, self.height, self.width)
        if cached is not None:
            return cached
        arrays = self.render_arrays(i, noise=True)
        self.cache.write(i, *arrays)
        return arrays

    def labels(self, i: int) -> torch.Tensor:
        """(H, W) int64 object id of frame ``i``: 0 = static, k = ``object_names[k - 1]``."""
        if not 0 <= i < len(self):
            raise IndexError(f"frame {i} out of range for {self.name} with {len(self)} frames")
        return torch.from_numpy(self._arrays(i)[2].astype(np.int64))

    def load_frame(self, i: int) -> Frame:
        return self._frame(i, *self._arrays(i))
