"""TivNeSLAM: the LightningModule whose ``training_step`` is the per-frame loop
masks -> track -> keyframe -> map -> allocate; everything it writes goes through :class:`RunDir`."""

from __future__ import annotations

import math
import resource
import sys
import time
from dataclasses import dataclass
from dataclasses import field as dc_field
from pathlib import Path
from typing import Any

import lightning as L
import torch

from data_modules.frame import Frame, Intrinsics
from tivne.config import (
    FieldConfig,
    LossWeights,
    MappingConfig,
    MeshConfig,
    ObjectFieldConfig,
    OdometryConfig,
    OutputConfig,
    RenderConfig,
    TrackingConfig,
)
from tivne.field.networks import time_to_tau
from tivne.field.object_state import objects_payload
from tivne.field.objects import attach_optimizer, build_field
from tivne.geometry import backproject
from tivne.masks.base import MaskContext, MaskProvider, NoMasks
from tivne.meshing import mesh_at, save_mesh, select_mesh_times
from tivne.render.rays import View
from tivne.render.renderer import render_image
from tivne.render.samplers import PixelSampler
from tivne.slam.checkpoint import restore_run_state, run_state, save_checkpoint, set_global_rng_state
from tivne.slam.frontend import Tracker
from tivne.slam.keyframes import KeyframeDatabase, KeyframePolicy
from tivne.slam.mapping import Mapper, final_pass
from tivne.slam.outputs import RunDir, image_panels, tensorboard_mesh
from tivne.slam.tracking import frozen
from tivne.slam.trajectory import Trajectory
from tivne.utils import deferred_interrupts, interrupt_pending


@dataclass
class Timers:
    """Where the run's time went (seconds), for metrics.json."""

    track_s: float = 0.0
    track_iters: int = 0
    track_frames: int = 0
    map_s: float = 0.0
    map_iters: int = 0
    refine_s: float = 0.0
    per_frame: list[float] = dc_field(default_factory=list)


@dataclass
class TrackingCounts:
    """Frames whose pose is not a tracked one, for metrics.json: without_tracking (no usable static
    depth, nothing to track on), lost (tracking ran and failed), recovered (the first attempt failed,
    the wider retry succeeded)."""

    without_tracking: int = 0
    lost: int = 0
    recovered: int = 0
    warnings: int = 0


class TivNeSLAM(L.LightningModule):
    """Online dynamic RGB-D SLAM over a stream of :class:`Frame` (batch size 1, time order)."""

    def __init__(
        self,
        field_cfg: FieldConfig,
        intrinsics: Intrinsics,
        sampler: PixelSampler,
        keyframes: KeyframePolicy,
        masks: MaskProvider | None,
        render: RenderConfig,
        loss: LossWeights,
        tracking: TrackingConfig,
        odometry: OdometryConfig,
        mapping: MappingConfig,
        mesh: MeshConfig,
        output: OutputConfig,
        run_dir: str | Path,
        seed: int = 0,
        run_config: dict[str, Any] | None = None,
        objects: ObjectFieldConfig | None = None,
    ) -> None:
        super().__init__()
        self.automatic_optimization = False
        self.field_cfg = field_cfg
        self.field = build_field(field_cfg, objects)  # objects: field=objects (tivne.field.objects)
        self.intrinsics = intrinsics
        self.sampler = sampler
        self.keyframe_policy = keyframes
        self.masks = masks or NoMasks()
        self.render_cfg, self.loss_weights = render, loss
        self.tracking_cfg, self.mapping_cfg = tracking, mapping
        self.mesh_cfg, self.output_cfg = mesh, output
        self.run = RunDir(run_dir)
        self.mapper = Mapper(self.field, mapping)
        attach_optimizer(self.field, self.mapper.optimizer, mapping)  # object fields join the map optimiser
        self.tracker = Tracker(tracking, odometry, render, loss)
        self.counts = TrackingCounts()
        self.db = KeyframeDatabase(keyframes.cfg.every, keyframes.cfg.max_stored)
        self.trajectory = Trajectory()
        self.tracked: list[torch.Tensor] = []  # the last two absolute poses, for the motion model
        self.t0: float | None = None
        self.last_mapped_tau = 0.0
        self.last_view: View | None = None
        self.timers = Timers()
        self.generator = torch.Generator().manual_seed(seed)
        self.last_metrics: dict[str, Any] = {}
        self.run_config = run_config  # saved in the checkpoint: a resumed run must repeat it
        self.final_pass_done = False
        self.between_frames = True  # the state is whole (a checkpoint of it can be resumed)
        self.resume_payload: dict[str, Any] | None = None  # restored once the module is on its device
        self.pending_rng: dict[str, Any] | None = None  # set just before the next frame

    # ---- Lightning plumbing -------------------------------------------------------------------
    def configure_optimizers(self):
        return self.mapper.optimizer  # registered so Lightning knows the map's optimiser

    def transfer_batch_to_device(self, batch: Frame, device, dataloader_idx: int) -> Frame:
        return batch.to(device)

    @property
    def K(self) -> torch.Tensor:
        return self.intrinsics.K(device=self.device)

    # ---- resume ---------------------------------------------------------------------------------
    def resume_from(self, payload: dict[str, Any]) -> int:
        """Continue from a checkpoint payload (:func:`tivne.slam.checkpoint.load_resume_state`) once
        training starts; returns the number of frames it has processed (the stream starts there)."""
        self.resume_payload = payload
        return int(payload["resume"]["position"])

    def on_train_start(self) -> None:
        if self.resume_payload is not None:
            self.pending_rng = restore_run_state(self, self.resume_payload, self.device)
            self.resume_payload = None

    def _apply_pending_rng(self) -> None:
        if self.pending_rng is not None:
            set_global_rng_state(self.pending_rng)
            self.pending_rng = None

    # ---- the per-frame loop -------------------------------------------------------------------
    def training_step(self, frame: Frame, batch_idx: int) -> None:
        self._apply_pending_rng()
        with deferred_interrupts():  # SIGINT / SIGTERM take effect once the frame is whole
            self.between_frames = False
            self._step(frame)
            self.between_frames = True
        every = self.output_cfg.checkpoint_every
        if every and len(self.trajectory) % every == 0:
            self.save_checkpoint()

    def _step(self, frame: Frame) -> None:
        start = time.perf_counter()
        k = len(self.trajectory)
        if self.t0 is None:
            self.t0 = float(frame.timestamp)
        tau = time_to_tau(frame.timestamp, self.t0, self.field.time_scale)
        # Post-tracking providers lend tracking a prediction (their previous mask) meanwhile.
        mask = self.masks.predict(frame) if self.masks.needs_tracked_pose else self.masks(frame, None)
        pose, stats, lost = self._track(k, tau, frame, mask)
        view = View(k, tau, frame.rgb, frame.depth, mask, pose)
        if not lost:  # a frame whose pose is not known is never mapped
            stats.update(self._integrate(k, view, frame, stats))
        self.trajectory.append(frame.timestamp, view.pose, self.db.views[-1].frame_id, self.db.views[-1].pose, frame.gt_pose)
        self.tracked = (self.tracked + [view.pose.detach()])[-2:]
        self.last_view = view
        elapsed = time.perf_counter() - start
        self.timers.per_frame.append(elapsed)
        self._log_frame(k, view, stats, elapsed)
        if self.output_cfg.save_every and (k + 1) % self.output_cfg.save_every == 0:
            self.write_trajectory()

    def _integrate(self, k: int, view: View, frame: Frame, stats: dict[str, float]) -> dict[str, float]:
        """Everything after a successful track: the mask, keyframes, mapping, voxels, the odometry reference."""
        if self.masks.needs_tracked_pose:
            with frozen(self.field), torch.no_grad():
                context = MaskContext(self.field, view.pose, self.K, view.tau, self.render_cfg, k, self.last_mapped_tau)
                view.dynamic = self.masks(frame, context)
        self.masks.revise(self.db.views, view, self.K)  # what this frame shows about earlier keyframes
        if k == 0:
            self._allocate(view)
        is_keyframe = self.db.should_insert(k)
        if is_keyframe:
            for old in self.db.add(view):
                self.trajectory.freeze(old.frame_id, old.pose)
        out: dict[str, float] = {}
        if k == 0 or k % self.mapping_cfg.every == 0:
            out = self._map(view, first=k == 0)
            self.last_mapped_tau = view.tau
        self._allocate(view)
        odo = {n[len("track/"):]: v for n, v in stats.items() if n.startswith("track/")}
        out["track/new_reference"] = float(self.tracker.update_reference(view, self.K, odo, is_keyframe))
        return out

    def _track(self, k: int, tau: float, frame: Frame, mask: torch.Tensor | None) -> tuple[torch.Tensor, dict[str, float], bool]:
        """The frame's c2w pose and whether tracking was lost: the first camera defines the SLAM world
        frame; later ones are tracked (:class:`tivne.slam.frontend.Tracker`)."""
        if k == 0:
            return torch.eye(4, device=self.device), {}, False
        usable = (frame.depth > 0) if mask is None else (frame.depth > 0) & ~mask
        if int(usable.sum()) < self.tracking_cfg.rays:
            self.counts.without_tracking += 1
            self._warn(f"frame {k} (t={float(frame.timestamp):.3f}s): only {int(usable.sum())} static pixels with depth; not tracked, not mapped")
            return self.tracked[-1].clone(), {"track/lost": 1.0}, True
        query_tau = self.last_mapped_tau if self.tracking_cfg.query_time == "last_mapped" else tau
        t = time.perf_counter()
        result = self.tracker.track(self.field, View(k, query_tau, frame.rgb, frame.depth, mask, self.tracked[-1]), self.tracked, self.K, self.generator)
        self.timers.track_s += time.perf_counter() - t
        self.timers.track_iters += self.tracking_cfg.iters if self.tracking_cfg.method != "odometry" else 0
        self.timers.track_frames += 1
        self.counts.recovered += int(result.recovered and not result.lost)
        if result.lost:
            self.counts.lost += 1
            self._warn(f"frame {k} (t={float(frame.timestamp):.3f}s): tracking lost ({format_stats(result.stats)}); pose from the motion model, not mapped")
        return result.pose, {f"track/{n}": v for n, v in result.stats.items()}, result.lost

    def _warn(self, message: str, limit: int = 20) -> None:
        """A ``warning:`` line on stderr (the first ``limit`` of them; metrics.json counts all)."""
        self.counts.warnings += 1
        if self.counts.warnings <= limit:
            print(f"warning: {message}", file=sys.stderr)
        elif self.counts.warnings == limit + 1:
            print("warning: more frames without tracking; see tracking_lost / frames_without_tracking in metrics.json", file=sys.stderr)

    def _map(self, view: View, first: bool) -> dict[str, float]:
        if first:
            views, fixed, iters = [view], [True], self.mapping_cfg.first_iters
        else:
            picked = self.keyframe_policy.select(self.db, view, self.K, self.generator)
            views = [view] + [self.db.views[i] for i in picked]
            fixed = [False] + [self.db.views[i].frame_id == 0 for i in picked]
            iters = self.mapping_cfg.iters
        t = time.perf_counter()
        poses, terms = self.mapper.run(views, fixed, iters, self.K, self.sampler, self.render_cfg, self.loss_weights, self.generator)
        self.timers.map_s += time.perf_counter() - t
        self.timers.map_iters += iters
        for v, p in zip(views, poses):
            v.pose = p
        return {f"map/loss_{n}" if n != "total" else "map/loss": v for n, v in terms.items()} | {"map/window": float(len(views))}

    @torch.no_grad()
    def _allocate(self, view: View) -> None:
        """Allocate voxels where the frame's depth (every ``allocation_stride``-th pixel) lands."""
        s = self.output_cfg.allocation_stride
        depth = view.depth[::s, ::s]
        h, w = depth.shape
        v, u = torch.meshgrid(torch.arange(h, device=self.device) * s, torch.arange(w, device=self.device) * s, indexing="ij")
        valid = depth > 0
        cam = backproject(torch.stack([u[valid], v[valid]], dim=-1).float(), depth[valid], self.K)
        world = (view.pose[:3, :3] @ cam.T).T + view.pose[:3, 3]
        dynamic = None if view.dynamic is None else view.dynamic[::s, ::s][valid]
        self.field.allocate(world, dynamic=dynamic, tau=view.tau)  # an ObjectField routes object depth to its objects

    def _log_frame(self, k: int, view: View, stats: dict[str, float], elapsed: float) -> None:
        """Per-frame scalars (against the frame index) and every ``image_every`` frames the renders."""
        stats = dict(stats, **{"perf/s_per_frame": elapsed, "map/voxels": float(self.field.grid.num_voxels)})
        result = self.trajectory.ate(self.keyframe_poses()) if k % 10 == 0 else None
        if result is not None:
            stats["eval/ate_rmse_m"] = float(result.rmse)
        logger = getattr(self.logger, "experiment", None) if self.logger is not None else None
        if logger is not None and hasattr(logger, "add_scalar"):
            for name, value in stats.items():
                if value is not None and math.isfinite(value):
                    logger.add_scalar(name, value, k)
            every = self.output_cfg.image_every
            if every and k % every == 0:
                for name, img in self.render_panels(view, stride=2).items():
                    logger.add_image(f"render/{name}", img, k, dataformats="HWC")
        self.log("fps", 1.0 / max(elapsed, 1e-6), prog_bar=True, on_step=True, batch_size=1)
        if "eval/ate_rmse_m" in stats:
            self.log("ate_cm", 100 * stats["eval/ate_rmse_m"], prog_bar=True, on_step=True, batch_size=1)

    def render_panels(self, view: View, stride: int = 1) -> dict:
        """Observed | rendered colour and depth, and |depth error| at ``view.pose`` (uint8 images)."""
        with frozen(self.field):
            rgb, depth = render_image(self.field, view, self.K, self.render_cfg, stride)
        return image_panels(rgb, depth, view.colour()[::stride, ::stride], view.depth[::stride, ::stride])

    # ---- results --------------------------------------------------------------------------------
    def keyframe_poses(self) -> dict[int, torch.Tensor]:
        return {v.frame_id: v.pose for v in self.db.views}

    def poses(self) -> torch.Tensor:
        """(N, 4, 4) float64 c2w poses of every processed frame, with keyframe refinements applied."""
        return self.trajectory.poses(self.keyframe_poses())

    def write_trajectory(self) -> Path:
        return self.run.write_trajectory(self.trajectory.timestamps(), self.poses())

    def on_train_end(self) -> None:
        self._apply_pending_rng()
        if not len(self.trajectory):
            return
        self.write_trajectory()  # before the final pass: an interrupted pass keeps the poses
        if not self.final_pass_done:
            if self.output_cfg.checkpoint_every:
                self.save_checkpoint()  # a crash in the final pass resumes here, not frames back
            views = list(self.db.views)
            if self.last_view is not None and (not views or views[-1] is not self.last_view):
                views.append(self.last_view)
            start = time.perf_counter()
            self.between_frames = False
            final_pass(self.mapper, views, self.K, self.sampler, self.render_cfg, self.loss_weights, self.generator)
            self.timers.refine_s = time.perf_counter() - start
            self.final_pass_done = self.between_frames = True
        self.finalize()

    def finalize(self) -> dict[str, Any]:
        """Write trajectory.txt, the checkpoint, renders, meshes and metrics.json into the run dir."""
        self.write_trajectory()
        self.save_checkpoint()
        for view in (self.db.views[0], self.db.views[-1]):
            for name, img in self.render_panels(view, stride=2).items():
                self.run.write_image(self.run.render_path(view.frame_id, name), img)
        metrics = self.run_metrics() | self._write_meshes() | {"complete": True}
        self.last_metrics = self.run.merge_metrics(metrics)
        return self.last_metrics

    def save_partial(self, reason: str) -> dict[str, Any]:
        """After an interruption: trajectory, checkpoint and metrics.json with ``complete: false``
        (no final pass, renders or meshes: those need the whole sequence). Interrupted inside a
        frame or the final pass, the state is not whole: the last checkpoint is kept as it is (or,
        with periodic checkpoints off, one that cannot be resumed is written for tivne.mesh)."""
        if not len(self.trajectory):
            return {}
        self.write_trajectory()
        whole = self.between_frames and not interrupt_pending()
        if whole or not self.output_cfg.checkpoint_every:
            self.save_checkpoint(resumable=whole)
        self.last_metrics = self.run.merge_metrics(self.run_metrics() | {"complete": False, "complete_reason": reason})
        return self.last_metrics

    def save_checkpoint(self, resumable: bool = True) -> Path:
        """checkpoints/slam.pt: the field and trajectory, and (``resumable``) the whole run state."""
        return save_checkpoint(
            self.run.checkpoint, self.field, self.field_cfg.field_kwargs(), self.trajectory.timestamps(),
            self.poses(), self.t0, extra={"keyframes": self.db.frame_ids(), **objects_payload(self.field)},
            resume=run_state(self) if resumable else None, config=self.run_config,
        )

    def run_metrics(self) -> dict[str, Any]:
        """Speed, memory, map size and ATE of the run so far (metrics.json keys)."""
        t = self.timers
        per_frame = t.per_frame
        metrics: dict[str, Any] = {
            "frames": len(per_frame),
            "wall_s": float(sum(per_frame)),
            "s_per_frame": float(sum(per_frame) / len(per_frame)) if per_frame else None,
            "s_per_frame_after_first": float(sum(per_frame[1:]) / (len(per_frame) - 1)) if len(per_frame) > 1 else None,
            "first_frame_s": float(per_frame[0]) if per_frame else None,
            # flat cost over long sequences: the first and the last 100 frames after the first one
            "s_per_frame_first100": mean_or_none(per_frame[1:101]),
            "s_per_frame_last100": mean_or_none(per_frame[1:][-100:]),
            "track_ms_per_frame": 1000 * t.track_s / t.track_frames if t.track_frames else None,
            "track_ms_per_iter": 1000 * t.track_s / t.track_iters if t.track_iters else None,
            "map_ms_per_iter": 1000 * t.map_s / t.map_iters if t.map_iters else None,
            "final_refine_s": t.refine_s,
            "final_refine_share": t.refine_s / (sum(per_frame) + t.refine_s) if per_frame else None,
            "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
            "voxels": self.field.grid.num_voxels,
            "embedding_rows": self.field.grid.num_corners,
            "keyframes": len(self.db),
            "tracking_lost": self.counts.lost,
            "frames_without_tracking": self.counts.without_tracking,
            "tracking_recovered": self.counts.recovered,
            "checkpoint": RunDir.CHECKPOINT,
        }
        result = self.trajectory.ate(self.keyframe_poses())
        if result is not None:
            metrics.update(result.as_metrics())
            metrics["ate_frames"] = int(result.num_poses)
        else:
            metrics.update({"ate_rmse_m": None, "ate_reason": "fewer than 3 frames have ground-truth poses"})
        return metrics

    def _write_meshes(self) -> dict[str, Any]:
        stamps = self.trajectory.timestamps()
        times = select_mesh_times(stamps, list(self.mesh_cfg.times) or None)
        centres = self.poses()[:, :3, 3].numpy()
        writer = getattr(self.logger, "experiment", None) if self.logger is not None else None
        result: dict[str, Any] = {}
        cache: dict = {}  # an ObjectField meshes its static field (and rigid objects) once
        for ts in times:
            tau = time_to_tau(ts, self.t0, self.field.time_scale)
            mesh = mesh_at(self.field, tau, self.mesh_cfg, centres, cache)
            save_mesh(mesh, self.run.mesh_path(ts))
            result[f"mesh_t{ts:.3f}_faces"] = int(len(mesh.faces))
            if writer is not None and hasattr(writer, "add_mesh"):
                tensorboard_mesh(writer, f"mesh/t{ts:.3f}", mesh, len(stamps) - 1)
        return result


def format_stats(stats: dict[str, float]) -> str:
    """The tracking signals of a frame, for its warning line."""
    keys = ("odo_inlier_ratio", "odo_overlap", "field_inlier_ratio", "jump_m", "jump_deg")
    return ", ".join(f"{k} {stats[k]:.3g}" for k in keys if k in stats)


def mean_or_none(values: list[float]) -> float | None:
    return float(sum(values) / len(values)) if values else None
