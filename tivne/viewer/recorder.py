"""The live recorder: a :class:`tivne.slam.observer.RunObserver` that logs a run to rerun as it goes.

Per frame (timelines ``frame`` and ``scene_time``, see :mod:`tivne.viewer.entities`): the camera
(transform + pinhole frustum), the GT camera, tracking status (lost / untracked frames as warnings
and a 0/1 plot), keyframes; every ``image_every`` frames the colour, depth and motion mask and the
colour / depth rendered at the estimated pose; every ``trajectory_every`` frames the estimated and
GT trajectories as line strips; every ``map_every``-th mapping round a decimated point set of the
map; at the end the meshes and the final trajectory. Objects' boxes when a record carries them.

Cheap on purpose: tensors go to the host only on the frames that log them, and rerun's SDK batches
and writes (file or network) in its own thread. A viewer never fails a run: the first error is one
``warning:`` line on stderr and the recorder is off for the rest of the run.
"""

from __future__ import annotations

import functools
import os
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch
import trimesh

from data_modules.frame import Intrinsics
from tivne.config import ViewerConfig
from tivne.slam.observer import FrameRecord
from tivne.viewer import entities as E

RECORDING = "viewer.rrd"


def has_display() -> bool:
    """A local window can be opened (X11 / Wayland, or not Linux)."""
    return not sys.platform.startswith("linux") or bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


def open_stream(cfg: ViewerConfig, path: Path, application_id: str = "tivne", recording_id: str | None = None, rendered: bool = True,
                play_state: str = "paused"):
    """A rerun RecordingStream on ``cfg.sink``: 'file' (``path``), 'spawn' (a local viewer; the file
    without a display, with a warning) or 'serve' (gRPC + the web viewer; prints where to connect),
    with :func:`tivne.viewer.entities.default_blueprint` (``rendered``: a panel for rendered frames)."""
    rr = E.rerun()
    rec = rr.RecordingStream(application_id, recording_id=recording_id)
    sink = cfg.sink
    if sink == "spawn" and not has_display():
        print(f"warning: viewer.sink=spawn but no display here; recording to {path} instead", file=sys.stderr)
        sink = "file"
    blueprint = E.default_blueprint(rendered, play_state)
    if sink == "file":
        path.parent.mkdir(parents=True, exist_ok=True)
        rec.save(path, default_blueprint=blueprint)
    elif sink == "spawn":
        rec.spawn(port=cfg.grpc_port, default_blueprint=blueprint)
    else:
        uri = rec.serve_grpc(grpc_port=cfg.grpc_port, server_memory_limit=cfg.server_memory_limit, default_blueprint=blueprint)
        rr.serve_web_viewer(web_port=cfg.web_port, open_browser=False, connect_to=uri)
        print(f"viewer: rerun --connect {uri}   or a browser at http://localhost:{cfg.web_port}/?url={uri}", file=sys.stderr)
    return rec


def guarded(method: Callable[..., Any]) -> Callable[..., Any]:
    """Run a recorder method; on any error print one warning line and switch the recorder off."""

    @functools.wraps(method)
    def wrapper(self: "Recorder", *args: Any, **kwargs: Any) -> Any:
        if self.rec is None:
            return None
        try:
            return method(self, *args, **kwargs)
        except Exception as exc:  # noqa: BLE001 -- a viewer must never fail a run
            self.off(f"{type(exc).__name__}: {exc}")
            return None

    return wrapper


def host(x: torch.Tensor) -> np.ndarray:
    return x.detach().cpu().numpy()


def to_uint8(rgb: torch.Tensor) -> np.ndarray:
    """(H, W, 3) float 0..1 -> uint8 (on the host, in numpy: no torch threads for a small image)."""
    return (np.clip(host(rgb), 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)


class Recorder:
    """Logs a run (see the module docstring). ``image_every``: the run's ``output.image_every``,
    used when ``cfg.image_every`` is null. ``stream``: an open RecordingStream (tests), else one on
    ``cfg.sink`` (the file ``run_dir/viewer.rrd``)."""

    def __init__(self, cfg: ViewerConfig, run_dir: str | Path, intrinsics: Intrinsics, image_every: int = 0, stream: Any = None) -> None:
        self.cfg = cfg
        self.path = Path(run_dir) / RECORDING
        self.intrinsics = intrinsics
        self.image_every = image_every if cfg.image_every is None else cfg.image_every
        self.rec = None
        self.t0: float | None = None
        self.timestamps: list[float] = []
        self.positions: list[np.ndarray] = []
        self.gt_positions: list[np.ndarray] = []
        self.keyframes: list[np.ndarray] = []
        self.gt_to_slam: np.ndarray | None = None
        self.map_rounds = 0
        self.pending_map: Callable[[], torch.Tensor] | None = None
        try:
            self.rec = stream if stream is not None else open_stream(cfg, self.path)
        except Exception as exc:  # noqa: BLE001
            self.off(f"could not open the recording: {type(exc).__name__}: {exc}")

    def off(self, why: str) -> None:
        print(f"warning: viewer off for the rest of the run ({why}); the run goes on", file=sys.stderr)
        self.rec = None

    def _time(self, index: int, timestamp: float) -> None:
        E.set_time(self.rec, index, timestamp - (self.t0 or 0.0))

    @guarded
    def on_frame(self, r: FrameRecord) -> None:
        if self.t0 is None:
            self.t0 = r.timestamp
            K = np.asarray(self.intrinsics.K(), dtype=np.float32)
            E.log_run_info(self.rec, r.timestamp, K, self.intrinsics.width, self.intrinsics.height)
        self.timestamps.append(r.timestamp)
        self._time(r.index, r.timestamp)
        pose = host(r.pose).astype(np.float64)
        E.log_pose(self.rec, E.CAMERA, pose)
        self.positions.append(pose[:3, 3])
        self._ground_truth(r, pose)
        self._status(r)
        if r.is_keyframe:
            self.keyframes.append(pose[:3, 3])
            self.rec.log(E.KEYFRAMES, E.rerun().Points3D(np.asarray(self.keyframes), radii=0.015, colors=[E.KEYFRAME_COLOUR]))
        if self.image_every and r.index % self.image_every == 0:
            self._images(r)
        if r.index % self.cfg.trajectory_every == 0:
            self._strips()
        if self.pending_map is not None:
            self._map()
        for name, obj in (r.objects or {}).items():
            E.log_box(self.rec, f"{E.OBJECTS}/{name}", host(obj.pose).astype(np.float64), host(obj.half_size), E.ESTIMATE_COLOUR)

    def _ground_truth(self, r: FrameRecord, pose: np.ndarray) -> None:
        if r.gt_pose is None:
            return
        gt = host(r.gt_pose).astype(np.float64)
        if self.gt_to_slam is None:  # the first frame with both poses ties the GT world to the SLAM frame
            self.gt_to_slam = pose @ np.linalg.inv(gt)
        gt = self.gt_to_slam @ gt
        E.log_pose(self.rec, E.GT_CAMERA, gt)
        self.gt_positions.append(gt[:3, 3])

    def _status(self, r: FrameRecord) -> None:
        rr = E.rerun()
        lost = r.status in ("lost", "untracked")
        self.rec.log(E.LOST, rr.Scalars(float(lost)))
        if lost:
            self.rec.log(E.STATUS, rr.TextLog(f"frame {r.index} t={r.timestamp:.3f}s: {r.status}", level="WARN"))

    def _images(self, r: FrameRecord) -> None:
        rr = E.rerun()
        self.rec.log(E.RGB, rr.Image(to_uint8(r.rgb)))
        self.rec.log(E.DEPTH, rr.DepthImage(host(r.depth).astype(np.float32), meter=1.0))
        if r.mask is not None:
            self.rec.log(E.MASK, rr.SegmentationImage(host(r.mask).astype(np.uint8)))
        if self.cfg.rendered and r.render is not None and r.index > 0:
            rgb, depth = r.render(self.cfg.render_stride)
            self.rec.log(E.RENDERED_RGB, rr.Image(to_uint8(rgb)))
            self.rec.log(E.RENDERED_DEPTH, rr.DepthImage(host(depth).astype(np.float32), meter=1.0))

    def _strips(self) -> None:
        E.log_strip(self.rec, E.TRAJECTORY, self.positions, E.ESTIMATE_COLOUR)
        E.log_strip(self.rec, E.GT_TRAJECTORY, self.gt_positions, E.GT_COLOUR)

    @guarded
    def on_map(self, index: int, points: Callable[[], torch.Tensor]) -> None:
        """Mapping runs inside the frame's step, before its record: the points are logged with it."""
        self.map_rounds += 1
        if self.cfg.map_points and (self.map_rounds - 1) % self.cfg.map_every == 0:
            self.pending_map = points

    def _map(self) -> None:
        points, self.pending_map = self.pending_map, None
        pts = E.decimate(host(points()).astype(np.float32), self.cfg.map_points)
        self.rec.log(E.MAP, E.rerun().Points3D(pts, radii=0.006, colors=[(170, 170, 170)]))

    @guarded
    def on_mesh(self, timestamp: float, mesh: trimesh.Trimesh) -> None:
        if not self.timestamps:
            return
        self._time(E.nearest_frame(self.timestamps, timestamp), timestamp)
        E.log_mesh(self.rec, mesh)

    @guarded
    def on_finish(self, timestamps: list[float], poses: torch.Tensor) -> None:
        """The final trajectory (keyframe refinements applied) at the last frame."""
        if not timestamps:
            return
        self._time(len(timestamps) - 1, timestamps[-1])
        self.positions = list(host(poses).astype(np.float64)[:, :3, 3])
        self._strips()

    def close(self) -> None:
        """Flush and end the recording (the file is whole after this)."""
        rec, self.rec = self.rec, None
        if rec is not None:
            try:
                rec.flush()
                rec.disconnect()
            except Exception as exc:  # noqa: BLE001
                print(f"warning: viewer: closing the recording failed ({type(exc).__name__}: {exc})", file=sys.stderr)
