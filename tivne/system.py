"""TivNeSLAM: the LightningModule that runs track -> keyframe -> map -> allocate on each frame."""

from __future__ import annotations

import json
import math
import resource
import time
from dataclasses import dataclass, field as dc_field
from pathlib import Path
from typing import Any

import lightning as L
import numpy as np
import torch

from data_modules.frame import Frame, Intrinsics
from tivne.checkpoint import CHECKPOINT_NAME, save_checkpoint, time_to_tau
from tivne.field.networks import TimeVaryingField
from tivne.geometry import backproject, invert_pose, orthonormalize_pose, write_tum_trajectory
from tivne.keyframes import KeyframeDatabase, KeyframePolicy, View
from tivne.losses import LossWeights
from tivne.mapping import Mapper, MappingConfig
from tivne.masks import MaskContext, MaskProvider, NoMasks
from tivne.rendering import RenderConfig, gather_rays, render_rays
from tivne.sampling import PixelPool, PixelSampler, depth_guided_depths
from tivne.tracking import TrackingConfig, frozen, predict_pose, track_frame


@dataclass(frozen=True)
class OutputConfig:
    """mesh_times: seconds on the sequence clock, or empty for the first and last frame.
    mesh_resolution: marching-cubes lattice step (m). mesh_min_hits, mesh_dynamic_window, mesh_backfaces: see
    :class:`tivne.meshing.MeshCulling` (observed space only). image_every: log rendered images every n
    frames (0 = never). save_every: rewrite trajectory.txt every n frames so an interrupted run
    keeps its results. allocation_stride: back-project every n-th pixel when allocating voxels."""

    mesh_times: tuple[float, ...] = ()
    mesh_resolution: float = 0.02
    mesh_min_hits: int = 1
    mesh_dynamic_window: float | None = 0.2
    mesh_backfaces: bool = True
    image_every: int = 50
    save_every: int = 25
    allocation_stride: int = 4
    evaluate: bool = True


@dataclass
class FrameRecord:
    """Where a processed frame's pose lives: relative to a keyframe, so refining the keyframe moves it."""

    timestamp: float
    keyframe: int
    relative: torch.Tensor
    gt_pose: torch.Tensor | None


@dataclass
class Timers:
    track_s: float = 0.0
    track_iters: int = 0
    map_s: float = 0.0
    map_iters: int = 0
    refine_s: float = 0.0
    frames: int = 0
    wall_s: float = 0.0
    per_frame: list[float] = dc_field(default_factory=list)


class TivNeSLAM(L.LightningModule):
    """Online dynamic RGB-D SLAM over a stream of :class:`Frame` (batch size 1, time order)."""

    def __init__(
        self,
        field: TimeVaryingField,
        field_kwargs: dict[str, Any],
        intrinsics: Intrinsics,
        sampler: PixelSampler,
        keyframes: KeyframePolicy,
        masks: MaskProvider | None,
        render: RenderConfig,
        loss: LossWeights,
        tracking: TrackingConfig,
        mapping: MappingConfig,
        output: OutputConfig,
        run_dir: str | Path,
        seed: int = 0,
    ) -> None:
        super().__init__()
        self.automatic_optimization = False
        self.field = field
        self.field_kwargs = dict(field_kwargs)
        self.intrinsics = intrinsics
        self.sampler = sampler
        self.keyframe_policy = keyframes
        self.masks = masks or NoMasks()
        self.render_cfg = render
        self.loss_weights = loss
        self.tracking_cfg = tracking
        self.mapping_cfg = mapping
        self.output_cfg = output
        self.run_dir = Path(run_dir)
        self.mapper = Mapper(field, mapping)
        self.db = KeyframeDatabase(keyframes.every)
        self.records: list[FrameRecord] = []
        self.tracked: list[torch.Tensor] = []  # latest absolute poses, for the motion model
        self.t0: float | None = None
        self.last_mapped_tau = 0.0
        self.last_view: View | None = None
        self.timers = Timers()
        self.generator = torch.Generator().manual_seed(seed)
        self.last_metrics: dict[str, Any] = {}

    # ---- Lightning plumbing -------------------------------------------------------------------
    def configure_optimizers(self):
        return self.mapper.optimizer  # registered so Lightning checkpoints its state

    def transfer_batch_to_device(self, batch: Frame, device, dataloader_idx: int) -> Frame:
        return batch.to(device)

    @property
    def K(self) -> torch.Tensor:
        return self.intrinsics.K(device=self.device)

    # ---- the per-frame pipeline ---------------------------------------------------------------
    def training_step(self, frame: Frame, batch_idx: int) -> None:
        start = time.perf_counter()
        k = len(self.records)
        if self.t0 is None:
            self.t0 = float(frame.timestamp)
        tau = time_to_tau(frame.timestamp, self.t0, self.field.time_scale)
        # Post-tracking providers lend tracking a prediction (their previous mask) meanwhile.
        mask = self.masks.predict(frame) if self.masks.needs_tracked_pose else self.masks(frame, None)
        stats: dict[str, float] = {}
        if k == 0:
            pose = torch.eye(4, device=self.device)  # the SLAM world frame is the first camera's
        else:
            init = predict_pose(self.tracked, self.tracking_cfg.motion_model)
            t = time.perf_counter()
            query_tau = self.last_mapped_tau if self.tracking_cfg.query_time == "last_mapped" else tau
            pose, tstats = track_frame(
                self.field, View(k, query_tau, frame.rgb, frame.depth, mask, init), self.K, self.render_cfg,
                self.loss_weights, self.tracking_cfg, self.generator,
            )
            self.timers.track_s += time.perf_counter() - t
            self.timers.track_iters += self.tracking_cfg.iters
            stats.update({f"track/{n}": v for n, v in tstats.items()})
        if self.masks.needs_tracked_pose:
            with frozen(self.field), torch.no_grad():
                mask = self.masks(frame, MaskContext(self.field, pose, self.K, tau, self.render_cfg, k, last_mapped_tau=self.last_mapped_tau))
        view = View(k, tau, frame.rgb, frame.depth, mask, pose)
        self.masks.revise(self.db.views, view, self.K)  # what this frame shows about earlier keyframes
        if k == 0:
            self._allocate(view)
        if self.db.should_insert(k):
            self.db.add(view)
        if k == 0 or k % self.mapping_cfg.every == 0:
            stats.update(self._map(view, first=k == 0))
            self.last_mapped_tau = tau
        self._allocate(view)
        self._record(frame, view)
        self.last_view = view
        self.timers.frames += 1
        elapsed = time.perf_counter() - start
        self.timers.per_frame.append(elapsed)
        self._log_frame(k, frame, view, stats, elapsed)
        if self.output_cfg.save_every and (k + 1) % self.output_cfg.save_every == 0:
            self.write_trajectory()

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
        s = self.output_cfg.allocation_stride
        depth = view.depth[::s, ::s]
        h, w = depth.shape
        v, u = torch.meshgrid(torch.arange(h, device=self.device) * s, torch.arange(w, device=self.device) * s, indexing="ij")
        valid = depth > 0
        uv = torch.stack([u[valid], v[valid]], dim=-1).float()
        cam = backproject(uv, depth[valid], self.K)
        world = (view.pose[:3, :3] @ cam.T).T + view.pose[:3, 3]
        dynamic = None if view.dynamic is None else view.dynamic[::s, ::s][valid]
        self.field.grid.allocate(world, dilation=self.field.allocation_dilation, dynamic=dynamic, tau=view.tau)

    def _record(self, frame: Frame, view: View) -> None:
        kf = len(self.db) - 1
        rel = orthonormalize_pose(invert_pose(self.db.views[kf].pose) @ view.pose)
        self.records.append(FrameRecord(float(frame.timestamp), kf, rel, frame.gt_pose))
        self.tracked.append(view.pose.detach())
        if len(self.tracked) > 2:
            self.tracked.pop(0)

    # ---- results --------------------------------------------------------------------------------
    def trajectory(self) -> torch.Tensor:
        """(N, 4, 4) c2w poses of every processed frame, with keyframe refinements applied."""
        return torch.stack([self.db.views[r.keyframe].pose @ r.relative for r in self.records]).detach().cpu().double()

    def timestamps(self) -> list[float]:
        return [r.timestamp for r in self.records]

    def gt_pairs(self) -> tuple[torch.Tensor, torch.Tensor] | None:
        """(estimated, GT) poses of the frames that have GT (readers leave uncovered frames without)."""
        keep = [i for i, r in enumerate(self.records) if r.gt_pose is not None]
        if len(keep) < 3:
            return None
        est = self.trajectory()[keep]
        gt = torch.stack([self.records[i].gt_pose for i in keep]).detach().cpu().double()
        return est, gt

    def ate(self):
        """ATE (SE(3)-aligned) over frames with GT, or None."""
        pairs = self.gt_pairs()
        if pairs is None:
            return None
        from tivne.metrics import absolute_trajectory_error

        return absolute_trajectory_error(pairs[0].numpy(), pairs[1].numpy(), align="se3")

    def write_trajectory(self) -> Path:
        self.run_dir.mkdir(parents=True, exist_ok=True)
        path = self.run_dir / "trajectory.txt"
        write_tum_trajectory(path, self.timestamps(), self.trajectory())
        return path

    def _log_frame(self, k: int, frame: Frame, view: View, stats: dict[str, float], elapsed: float) -> None:
        stats = dict(stats)
        stats["perf/s_per_frame"] = elapsed
        stats["map/voxels"] = float(self.field.grid.num_voxels)
        result = self.ate() if k % 10 == 0 else None
        if result is not None:
            stats["eval/ate_rmse_m"] = float(result.rmse)
        logger = self.logger.experiment if self.logger is not None and hasattr(self.logger, "experiment") else None
        if logger is not None and hasattr(logger, "add_scalar"):
            for name, value in stats.items():
                if value is not None and math.isfinite(value):
                    logger.add_scalar(name, value, k)  # logged against the frame index, not optimiser steps
            every = self.output_cfg.image_every
            if every and k % every == 0:
                images = self.render_view(view, stride=2)
                for name, img in images.items():
                    logger.add_image(f"render/{name}", img, k, dataformats="HWC")
        self.log("fps", 1.0 / max(elapsed, 1e-6), prog_bar=True, on_step=True, batch_size=1)
        if "eval/ate_rmse_m" in stats:
            self.log("ate_cm", 100 * stats["eval/ate_rmse_m"], prog_bar=True, on_step=True, batch_size=1)

    @torch.no_grad()
    def render_view(self, view: View, stride: int = 1) -> dict[str, np.ndarray]:
        """Render rgb, depth and |depth error| at ``view.pose`` (pixels with observed depth only;
        others stay black since samples are placed around the observed depth)."""
        depth = view.depth[::stride, ::stride]
        rgb = view.rgb[::stride, ::stride]
        K = self.K.clone()
        K[:2] /= stride
        h, w = depth.shape
        pool = PixelPool.from_masks(depth > 0, None)
        out_rgb = torch.zeros(h * w, 3, device=self.device)
        out_depth = torch.zeros(h * w, device=self.device)
        chunk = self.render_cfg.chunk
        for start in range(0, pool.valid.numel(), chunk):
            idx = pool.valid[start : start + chunk]
            rays = gather_rays([idx], [(rgb, depth, None, view.tau)], view.pose[None], K)
            r = self.render_cfg
            z = depth_guided_depths(rays.depth, r.truncation, r.n_band, r.n_free, r.band, r.near, stratified=False)
            rendered, _ = render_rays(self.field, rays, z, r.truncation)
            out_rgb[idx] = rendered.rgb
            out_depth[idx] = rendered.depth
        out_rgb = out_rgb.view(h, w, 3)
        out_depth = out_depth.view(h, w)
        dmax = float(depth.max().clamp_min(1e-3))
        err = (out_depth - depth).abs() * (depth > 0)
        to8 = lambda x: (x.clamp(0, 1) * 255).byte().cpu().numpy()  # noqa: E731
        return {
            "rgb": to8(torch.cat([rgb, out_rgb], dim=1)),
            "depth": to8(torch.cat([depth, out_depth], dim=1)[..., None].expand(-1, -1, 3) / dmax),
            "depth_error": to8((err / 0.05)[..., None].expand(-1, -1, 3)),
        }

    def on_train_end(self) -> None:
        self.refine_map()
        self.finalize()

    def refine_map(self) -> dict[str, float]:
        """Final pass over the whole sequence (Co-SLAM's final global BA, poses fixed):
        ``mapping.final_iters`` steps in rounds of ``mapping.iters``, each over a window of
        ``mapping.final_window`` keyframes (plus the last frame) drawn without replacement from a
        shuffled cycle, so every time is revisited about equally often."""
        cfg = self.mapping_cfg
        views = list(self.db.views)
        if self.last_view is not None and (not views or views[-1] is not self.last_view):
            views.append(self.last_view)
        if cfg.final_iters <= 0 or not views:
            return {}
        start = time.perf_counter()
        window = max(1, min(cfg.final_window, len(views)))
        order: list[int] = []
        done, terms = 0, {}
        while done < cfg.final_iters:
            if len(order) < window:  # next cycle; the last cycle's leftovers go first, no repeats in a window
                order += [i for i in torch.randperm(len(views), generator=self.generator).tolist() if i not in order]
            picked, order = order[:window], order[window:]
            iters = min(cfg.iters, cfg.final_iters - done)
            _, terms = self.mapper.run(
                [views[i] for i in picked], [True] * window, iters, self.K, self.sampler, self.render_cfg,
                self.loss_weights, self.generator, current_share=1.0 / window,
            )
            done += iters
        self.timers.refine_s = time.perf_counter() - start
        return terms

    def finalize(self) -> dict[str, Any]:
        """Write trajectory.txt, the checkpoint, renders, meshes and metrics.json into the run dir."""
        if not self.records:
            return {}
        self.run_dir.mkdir(parents=True, exist_ok=True)
        self.write_trajectory()
        ckpt = save_checkpoint(
            self.run_dir / "checkpoints" / CHECKPOINT_NAME, self.field, self.field_kwargs, self.timestamps(),
            self.trajectory(), self.t0, extra={"keyframes": self.db.frame_ids()},
        )
        t = self.timers
        metrics: dict[str, Any] = {
            "frames": t.frames,
            "wall_s": float(sum(t.per_frame)),
            "s_per_frame": float(np.mean(t.per_frame)),
            "s_per_frame_after_first": float(np.mean(t.per_frame[1:])) if len(t.per_frame) > 1 else None,
            "track_ms_per_iter": 1000 * t.track_s / t.track_iters if t.track_iters else None,
            "map_ms_per_iter": 1000 * t.map_s / t.map_iters if t.map_iters else None,
            "final_refine_s": t.refine_s,
            "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
            "voxels": self.field.grid.num_voxels,
            "embedding_rows": self.field.grid.num_corners,
            "keyframes": len(self.db),
            "checkpoint": str(ckpt.relative_to(self.run_dir)),
        }
        result = self.ate()
        if result is not None:
            metrics.update(result.as_metrics())
            metrics["ate_frames"] = int(result.num_poses)
        else:
            metrics.update({"ate_rmse_m": None, "ate_reason": "fewer than 3 frames have ground-truth poses"})
        self._write_renders()
        metrics.update(self._write_meshes())
        write_metrics(self.run_dir / "metrics.json", metrics)
        self.last_metrics = metrics
        return metrics

    def _write_renders(self) -> None:
        import cv2

        if not self.db.views:
            return
        out = self.run_dir / "renders"
        out.mkdir(parents=True, exist_ok=True)
        for view in (self.db.views[0], self.db.views[-1]):
            with frozen(self.field):
                images = self.render_view(view, stride=2)
            for name, img in images.items():
                cv2.imwrite(str(out / f"frame{view.frame_id:05d}_{name}.png"), img[..., ::-1])

    def _write_meshes(self) -> dict[str, Any]:
        try:
            from tivne.meshing import MeshCulling, extract_mesh, save_mesh
        except ImportError as exc:  # meshing is optional at import time only while developing
            return {"mesh_reason": f"meshing unavailable: {exc}"}
        times = list(self.output_cfg.mesh_times) or [self.records[0].timestamp, self.records[-1].timestamp]
        culling = MeshCulling(self.output_cfg.mesh_min_hits, self.output_cfg.mesh_dynamic_window, self.output_cfg.mesh_backfaces)
        centres = self.trajectory()[:, :3, 3].cpu().numpy()
        out = self.run_dir / "meshes"
        out.mkdir(parents=True, exist_ok=True)
        result: dict[str, Any] = {}
        for ts in times:
            tau = time_to_tau(ts, self.t0, self.field.time_scale)
            mesh = extract_mesh(
                self.field, tau, resolution=self.output_cfg.mesh_resolution, culling=culling, camera_centres=centres
            )
            save_mesh(mesh, out / f"mesh_t{ts:.3f}.ply")
            result[f"mesh_t{ts:.3f}_faces"] = int(len(mesh.faces))
        return result


def write_metrics(path: Path, metrics: dict[str, Any]) -> None:
    """Merge ``metrics`` into a JSON file atomically (existing keys not recomputed are kept)."""
    current: dict[str, Any] = {}
    if path.is_file():
        try:
            current = json.loads(path.read_text())
        except json.JSONDecodeError:
            current = {}
    current.update(metrics)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(current, indent=2, sort_keys=True) + "\n")
    tmp.replace(path)
