"""What a run writes: the loop's state turned into the run directory's files (trajectory.txt, the
checkpoint, renders, meshes, metrics.json), periodically, at the end, or after an interruption.
Every path and writer is :class:`tivne.slam.outputs.RunDir`'s."""

from __future__ import annotations

import resource
from pathlib import Path
from typing import Any

from tivne.config import MeshConfig, OutputConfig
from tivne.field.object_state import objects_payload
from tivne.meshing import DepthViews, mesh_at, save_mesh, select_mesh_times
from tivne.render.rays import View
from tivne.render.renderer import render_image
from tivne.slam.checkpoint import global_rng_state, save_checkpoint
from tivne.slam.loop import SlamLoop
from tivne.slam.observer import NoObserver, RunObserver, frame_record, map_points
from tivne.slam.outputs import RunDir, image_panels, tensorboard_mesh
from tivne.slam.state import FrameReport
from tivne.slam.tracking.field import frozen
from tivne.utils import interrupt_pending


class RunWriter:
    """Writes a :class:`SlamLoop`'s results into ``run_dir``. ``run_config``: the composed config as
    plain values, saved in the checkpoint (a resumed run must repeat it); ``tensorboard``: a
    SummaryWriter for the meshes (or None)."""

    def __init__(
        self, run_dir: str | Path, output: OutputConfig, mesh: MeshConfig, run_config: dict[str, Any] | None = None,
        observer: RunObserver | None = None,
    ) -> None:
        self.run = RunDir(run_dir)
        self.output, self.mesh = output, mesh
        self.run_config = run_config
        self.observer = observer or NoObserver()  # a viewer (tivne.viewer); it never fails the run
        self.last_metrics: dict[str, Any] = {}

    def after_frame(self, loop: SlamLoop, report: FrameReport) -> None:
        """The frame to the observer, and the periodic writes: trajectory.txt every
        ``output.save_every`` frames, the checkpoint every ``output.checkpoint_every``."""
        if not isinstance(self.observer, NoObserver):
            boxes = {i: tr.box for i, tr in loop.objects.tracks.items()} if loop.objects is not None else None
            gt = loop.trajectory.records[report.index].gt_pose
            self.observer.on_frame(frame_record(report, gt, loop.field, loop.K, loop.mapper.render, boxes))
            if report.mapping is not None:
                self.observer.on_map(report.index, lambda: map_points(loop.field))
        n = report.index + 1
        if self.output.save_every and n % self.output.save_every == 0:
            self.write_trajectory(loop)
        if self.output.checkpoint_every and n % self.output.checkpoint_every == 0:
            self.save_checkpoint(loop)

    def write_trajectory(self, loop: SlamLoop) -> Path:
        """trajectory.txt, and objects/<id>.txt of every object track."""
        if loop.objects is not None:
            loop.objects.write(self.run)
        return self.run.write_trajectory(loop.trajectory.timestamps(), loop.poses.all())

    def save_checkpoint(self, loop: SlamLoop, resumable: bool = True) -> Path:
        """checkpoints/slam.pt: the field and trajectory, and (``resumable``) the whole run state."""
        resume = (loop.state_dict() | {"rng": global_rng_state()}) if resumable else None
        return save_checkpoint(
            self.run.checkpoint, loop.field, loop.trajectory.timestamps(), loop.poses.all(), loop.clock,
            extra={"keyframes": loop.keyframes.frame_ids(), "K": loop.K.detach().cpu(), **objects_payload(loop.field)}, resume=resume,
            config=self.run_config,
        )

    def finish(self, loop: SlamLoop, tensorboard: Any = None) -> dict[str, Any]:
        """After the last frame: trajectory (before the final pass: an interrupted pass keeps the
        poses), a checkpoint to resume a crashed final pass from, the pass, then every result."""
        if not len(loop):
            return {}
        self.write_trajectory(loop)
        if not loop.final_pass_done:
            if self.output.checkpoint_every:
                self.save_checkpoint(loop)  # a crash in the final pass resumes here, not frames back
            loop.finish()
        return self.finalize(loop, tensorboard)

    def finalize(self, loop: SlamLoop, tensorboard: Any = None) -> dict[str, Any]:
        """Write trajectory.txt, the checkpoint, renders, meshes and metrics.json into the run dir."""
        self.write_trajectory(loop)
        self.save_checkpoint(loop)
        for view in (loop.keyframes.view(0), loop.keyframes.view(len(loop.keyframes) - 1)):
            for name, img in render_panels(loop, view, stride=2).items():
                self.run.write_image(self.run.render_path(view.frame_id, name), img)
        metrics = run_metrics(loop) | self.write_meshes(loop, tensorboard) | {"complete": True}
        self.observer.on_finish(loop.trajectory.timestamps(), loop.poses.all())
        self.last_metrics = self.run.merge_metrics(metrics)
        return self.last_metrics

    def save_partial(self, loop: SlamLoop, reason: str) -> dict[str, Any]:
        """After an interruption: trajectory, checkpoint and metrics.json with ``complete: false``
        (no final pass, renders or meshes: those need the whole sequence). Interrupted inside a
        frame or the final pass, the state is not whole: the last checkpoint is kept as it is (or,
        with periodic checkpoints off, one that cannot be resumed is written for tivne.mesh)."""
        if not len(loop):
            return {}
        self.write_trajectory(loop)
        whole = loop.between_frames and not interrupt_pending()
        if whole or not self.output.checkpoint_every:
            self.save_checkpoint(loop, resumable=whole)
        self.last_metrics = self.run.merge_metrics(run_metrics(loop) | {"complete": False, "complete_reason": reason})
        return self.last_metrics

    def write_meshes(self, loop: SlamLoop, tensorboard: Any = None) -> dict[str, Any]:
        stamps = loop.trajectory.timestamps()
        times = select_mesh_times(stamps, list(self.mesh.times) or None)
        centres = loop.poses.all()[:, :3, 3].numpy()
        result: dict[str, Any] = {}
        cache: dict = {}  # field=objects: the static field and rigid objects are meshed once
        depth_views = DepthViews(loop.keyframes.views(), loop.K)
        for ts in times:
            mesh = mesh_at(loop.field, loop.clock.tau(ts), self.mesh, centres, cache, depth_views)
            save_mesh(mesh, self.run.mesh_path(ts))
            self.observer.on_mesh(ts, mesh)
            result[f"mesh_t{ts:.3f}_faces"] = int(len(mesh.faces))
            if tensorboard is not None and hasattr(tensorboard, "add_mesh"):
                tensorboard_mesh(tensorboard, f"mesh/t{ts:.3f}", mesh, len(stamps) - 1)
        return result


def render_panels(loop: SlamLoop, view: View, stride: int = 1) -> dict:
    """Observed | rendered colour and depth, and |depth error| at ``view.pose`` (uint8 images)."""
    with frozen(loop.field):
        rgb, depth = render_image(loop.field, view, loop.K, loop.mapper.render, stride)
    return image_panels(rgb, depth, view.colour()[::stride, ::stride], view.depth[::stride, ::stride])


def run_metrics(loop: SlamLoop) -> dict[str, Any]:
    """Speed, memory, map size and ATE of the run so far (metrics.json keys)."""
    per_frame, refine_s = loop.timers.per_frame, loop.timers.refine_s
    counts, mapper = loop.tracker.counts, loop.mapper
    metrics: dict[str, Any] = {
        "frames": len(per_frame),
        "wall_s": float(sum(per_frame)),
        "s_per_frame": mean_or_none(per_frame),
        "s_per_frame_after_first": mean_or_none(per_frame[1:]),
        "first_frame_s": float(per_frame[0]) if per_frame else None,
        # flat cost over long sequences: the first and the last 100 frames after the first one
        "s_per_frame_first100": mean_or_none(per_frame[1:101]),
        "s_per_frame_last100": mean_or_none(per_frame[1:][-100:]),
        "track_ms_per_frame": 1000 * counts.seconds / counts.frames if counts.frames else None,
        "track_ms_per_iter": 1000 * counts.seconds / counts.field_iters if counts.field_iters else None,
        "map_ms_per_iter": 1000 * mapper.seconds / mapper.iterations if mapper.iterations else None,
        "final_refine_s": refine_s,
        "final_refine_share": refine_s / (sum(per_frame) + refine_s) if per_frame else None,
        "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
        "voxels": loop.field.grid.num_voxels,
        "embedding_rows": loop.field.grid.num_corners,
        "keyframes": len(loop.keyframes),
        "tracking_lost": counts.lost,
        "frames_without_tracking": counts.without_tracking,
        "tracking_recovered": counts.recovered,
        "reference_reuses": counts.reused,
        "checkpoint": RunDir.CHECKPOINT,
    } | (loop.objects.metrics() if loop.objects is not None else {}) | (loop.backend.metrics() if loop.backend is not None else {})
    result = loop.ate()
    if result is not None:
        metrics.update(result.as_metrics())
        metrics["ate_frames"] = int(result.num_poses)
    else:
        metrics.update({"ate_rmse_m": None, "ate_reason": "fewer than 3 frames have ground-truth poses"})
    return metrics


def mean_or_none(values: list[float]) -> float | None:
    return float(sum(values) / len(values)) if values else None
