"""The SLAM loop as a plain object: ``step(frame) -> FrameReport`` per frame, ``finish()`` for the
final pass, ``state_dict()`` / ``load_state_dict()`` for checkpoints. No Lightning, no Hydra, no files:
the LightningModule (:mod:`tivne.slam.system`) adapts it to a Trainer, :mod:`tivne.slam.results`
writes what it holds, and a plain ``for frame in frames: loop.step(frame)`` runs it too.

One frame: masks -> track -> (mask after tracking, revise keyframe masks) -> objects -> keyframe ->
map -> allocate -> odometry reference -> record. Given the next frame too (``step(frame,
next_frame)``), this frame's reference update and the next frame's mask, track and objects run in a
worker thread during this frame's mapping round where that changes nothing (:attr:`SlamLoop.overlaps`);
the mapping thread keeps the cores the worker leaves. Each component owns its settings and its state:

    clock       Clock: the one conversion of timestamps to field time τ (set by the first frame)
    masks       MaskProvider: the motion mask (before or after tracking)
    tracker     Tracker: the camera pose (a TrackResult), its reference, counters and warnings
    keyframes   KeyframeStore: keyframe records and the one copy of their (refined) poses
    mapper      Mapper: the map optimiser, rounds over the current frame + the policy's window
    allocator   VoxelAllocator: where the map grows
    trajectory  Trajectory: every frame's pose, relative to its keyframe (PoseBook reads both)
    objects     ObjectTracker (optional): one SE(3) track per moving object, by the same odometry
    backend     KeyframePoseGraph (optional, backend.method=graph): keyframe edges, loop closures,
                iSAM2; its corrections go to the keyframe store, the map follows
"""

from __future__ import annotations

import dataclasses
import time
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import torch

from data_modules.frame import Frame, Intrinsics
from tivne.field.clock import Clock
from tivne.field.networks import TimeVaryingField
from tivne.masks.base import MaskContext, MaskProvider, NoMasks
from tivne.render.rays import View
from tivne.slam.allocation import VoxelAllocator
from tivne.slam.backend.apply import Correction, follow_corrections
from tivne.slam.keyframes import KeyframePolicy, KeyframeStore, view_from_state, view_state
from tivne.slam.mapping import Mapper, final_pass
from tivne.slam.objects import ObjectObservation, ObjectTrack, ObjectTracker
from tivne.slam.state import FrameReport, Timers
from tivne.slam.tracking import Tracker, TrackingCounts, TrackResult
from tivne.slam.tracking.field import frozen
from tivne.slam.trajectory import PoseBook, Trajectory
from tivne.utils import torch_threads

if TYPE_CHECKING:  # gtsam is optional: the graph's module is imported only where it is built
    from tivne.slam.backend.posegraph import KeyframePoseGraph


@dataclass(frozen=True)
class _Ahead:
    """The next frame, tracked in the worker while the current one was mapped: its timestamp, mask
    and result, the tracker's counts before it and whether the current frame switched the odometry
    reference (updated there first); where its objects were observed there too, their observations
    and the object tracker's snapshot from before them (what a checkpoint saves)."""

    timestamp: float
    mask: torch.Tensor | None
    result: TrackResult
    counts: TrackingCounts
    switched: bool = False
    objects: tuple[ObjectObservation, ...] | None = None
    objects_state: dict[str, Any] | None = None


class SlamLoop:
    """Online dynamic RGB-D SLAM over frames in time order (see the module docstring)."""

    def __init__(
        self,
        field: TimeVaryingField,
        intrinsics: Intrinsics,
        tracker: Tracker,
        mapper: Mapper,
        keyframes: KeyframeStore,
        policy: KeyframePolicy,
        allocator: VoxelAllocator,
        masks: MaskProvider | None = None,
        seed: int = 0,
        objects: ObjectTracker | None = None,
        backend: KeyframePoseGraph | None = None,
    ) -> None:
        self.field, self.intrinsics = field, intrinsics
        self.objects = objects  # per-object rigid tracks (objects.track), or None
        self.backend = backend  # the keyframe pose graph (backend.method=graph), or None
        self.tracker, self.mapper, self.keyframes, self.policy = tracker, mapper, keyframes, policy
        self.allocator = allocator
        self.masks = masks or NoMasks()
        self.trajectory = Trajectory()
        self.poses = PoseBook(self.trajectory, self.keyframes.pose_map)
        self.clock: Clock | None = None
        self.last_mapped_tau = 0.0
        self.last_view: View | None = None  # the latest tracked frame's observation when it is no keyframe (the final pass maps it too)
        self.timers = Timers()
        self.generator = torch.Generator().manual_seed(seed)
        self.final_pass_done = False
        self.between_frames = True  # the state is whole (a checkpoint of it can be resumed)
        self._ahead: _Ahead | None = None  # the next frame, tracked while this one was mapped
        self._worker: ThreadPoolExecutor | None = None
        self._objects_now: dict | None = None  # the object tracker's snapshot while the worker observes the next frame's

    @property
    def device(self) -> torch.device:
        return self.field.grid.embeddings.device

    @property
    def K(self) -> torch.Tensor:
        return self.intrinsics.K(device=self.device)

    def __len__(self) -> int:
        return len(self.trajectory)

    # ---- one frame -----------------------------------------------------------------------------
    def step(self, frame: Frame, next_frame: Frame | None = None) -> FrameReport:
        """Process the next frame of the stream. ``next_frame``, the one after it (optional): where
        :attr:`overlaps` it is tracked in a worker thread while this frame is mapped, and the next
        ``step`` (which must get that frame) takes the result; the figures are those of a plain step."""
        self.between_frames = False
        start = time.perf_counter()
        k = len(self.trajectory)
        if self.clock is None:
            self.clock = Clock(float(frame.timestamp), self.field.time_scale)
        tau = self.clock.tau(frame.timestamp)
        ahead, self._ahead = self._ahead, None
        if ahead is not None and ahead.timestamp != float(frame.timestamp):
            raise ValueError(f"SlamLoop.step: got the frame at t={float(frame.timestamp):.6f}s, but the previous step was "
                             f"given the frame at t={ahead.timestamp:.6f}s as next_frame (and has tracked it)")
        mask, result = (ahead.mask, ahead.result) if ahead is not None else self._track(k, frame, tau)
        view = View(k, tau, frame.rgb, frame.depth, mask, result.pose)
        keyframe = new_reference = False
        mapping, objects, correction = None, (), None
        if not result.lost:  # a frame whose pose is not known is never mapped
            observed = None if ahead is None else ahead.objects
            view, keyframe, new_reference, mapping, correction, objects = self._integrate(k, view, frame, result, next_frame, observed)
        if len(self.trajectory) == k:  # not yet recorded before its mapping round (see _integrate)
            self._record(frame, view, result.lost)
        if not result.lost:
            self.last_view = None if keyframe else view
        elapsed = time.perf_counter() - start
        self.timers.per_frame.append(elapsed)
        self.between_frames = True
        return FrameReport(k, float(frame.timestamp), tau, result, view, keyframe, new_reference, mapping, elapsed,
                           self.field.grid.num_voxels, objects, correction)

    def _track(self, k: int, frame: Frame, tau: float) -> tuple[torch.Tensor | None, TrackResult]:
        """The frame's motion mask for tracking and its :class:`TrackResult`."""
        # Post-tracking providers lend tracking a prediction (their previous mask) meanwhile.
        mask = self.masks.predict(frame) if self.masks.needs_tracked_pose else self.masks(frame, None)
        return mask, self.tracker.track(k, frame, tau, mask, self.field, self.poses, self.K, self.last_mapped_tau, self.generator)

    def _record(self, frame: Frame, view: View, lost: bool = False) -> None:
        latest = self.keyframes.frame_ids()[-1]
        self.trajectory.append(frame.timestamp, view.pose, latest, self.keyframes.pose(latest), frame.gt_pose, lost)
        if not lost:
            self.trajectory.bridge_lost(self.keyframes.pose_map())

    @property
    def overlaps(self) -> bool:
        """Whether the next frame may be tracked while this one is mapped: ``tracking.overlap``, a
        tracker that does not read the map (``tracking.method=odometry``) and mapping that moves no
        pose (``mapping.optimize_poses`` off), so the order of the two changes nothing."""
        return self.tracker.cfg.overlap and not self.tracker.cfg.reads_map and not self.mapper.cfg.optimize_poses

    @property
    def object_tracks(self) -> dict[int, ObjectTrack]:
        """The object tracks the map reads (``field=objects``): while the worker observes the next
        frame's objects, a copy of this frame's, so the mapping round sees what it would in order."""
        if self._objects_now is not None:
            return self._objects_now["tracks"]
        return {} if self.objects is None else self.objects.tracks

    def _track_ahead(self, k: int, frame: Frame, view: View, result: TrackResult, keyframe: bool, next_frame: Frame) -> Future:
        """In the worker thread: frame k's odometry reference update (``update_reference``), then the
        track of ``next_frame`` (stream index k + 1). Frame k is recorded first: its pose is final
        (mapping will not move it) and the reference update reads it. The next frame's objects are
        observed there too where its mask does not wait for the tracked pose (the object tracker
        reads frames and poses, never the map); the map reads a copy of frame k's tracks meanwhile
        (:attr:`object_tracks`)."""
        self._record(frame, view)
        K, tau, threads = self.K, self.clock.tau(next_frame.timestamp), self.tracker.cfg.overlap_threads
        objects_too = self.objects is not None and not self.masks.needs_tracked_pose
        before = self._objects_now = self.objects.snapshot() if objects_too else None

        def work() -> _Ahead:
            torch.set_num_threads(threads)  # this thread's own OpenMP team: the map keeps the main one
            switched = self.tracker.update_reference(view, K, result, keyframe, self.poses)
            counts = dataclasses.replace(self.tracker.counts)  # a checkpoint before the next step must not count it
            mask, next_result = self._track(k + 1, next_frame, tau)
            ahead = _Ahead(float(next_frame.timestamp), mask, next_result, counts, switched)
            if not objects_too or next_result.lost:
                return ahead
            observed = tuple(self.objects.observe(next_frame, next_result.pose, tau, mask))
            return dataclasses.replace(ahead, objects=observed, objects_state=before)

        if self._worker is None:
            self._worker = ThreadPoolExecutor(max_workers=1, thread_name_prefix="tivne-track")
        return self._worker.submit(work)

    def _integrate(
        self, k: int, view: View, frame: Frame, result: TrackResult, next_frame: Frame | None = None,
        observed: tuple[ObjectObservation, ...] | None = None,
    ) -> tuple[View, bool, bool, Any, Correction | None, tuple[ObjectObservation, ...]]:
        """Everything after a successful track: the mask, the objects (``observed``: already, in the
        worker), keyframes, mapping, voxels, the odometry reference (and, where it overlaps the
        mapping round, the next frame's track)."""
        K = self.K
        if self.masks.needs_tracked_pose:
            with frozen(self.field), torch.no_grad():
                context = MaskContext(self.field, view.pose, K, view.tau, self.mapper.render, k, self.last_mapped_tau)
                view = dataclasses.replace(view, dynamic=self.masks(frame, context))
        # Each moving object's SE(3), the camera pose known: before voxels and mapping, which place
        # the object fields (field=objects) by these poses.
        if observed is None:
            observed = () if self.objects is None else tuple(self.objects.observe(frame, view.pose, view.tau, view.dynamic))
        self.keyframes.set_masks(self.masks.revise(self.keyframes.views(), view, K))  # what this frame shows about earlier keyframes
        if k == 0:  # the first frame is mapped before anything else: its voxels first
            self.allocator.allocate(self.field, view, K)
        keyframe = self.keyframes.should_insert(k)
        correction = None
        if keyframe:
            for frame_id, pose in self.keyframes.add(view):
                self.trajectory.freeze(frame_id, pose)
            if self.backend is not None:
                correction = self._correct_poses(result.velocity)
                view = dataclasses.replace(view, pose=self.keyframes.pose(k).to(view.pose.dtype))
        mapping, ahead, new_reference = None, None, False
        maps = k == 0 or k % self.mapper.cfg.every == 0
        if maps and next_frame is not None and self.overlaps:
            ahead = self._track_ahead(k, frame, view, result, keyframe, next_frame)
        # While the worker tracks, this thread keeps the cores the worker leaves it (oversubscribed
        # OpenMP teams wait on each other).
        split = max(1, torch.get_num_threads() - self.tracker.cfg.overlap_threads) if ahead is not None else None
        with torch_threads(split):
            if maps:
                mapping = self.mapper.map_frame(view, self.keyframes, self.policy, K, self.generator, first=k == 0)
                self.keyframes.update_poses(mapping.poses)
                if k in mapping.poses:
                    view = dataclasses.replace(view, pose=mapping.poses[k])
                self.last_mapped_tau = view.tau
            if k > 0:
                self.allocator.allocate(self.field, view, K)
        if ahead is None:
            new_reference = self.tracker.update_reference(view, K, result, keyframe, self.poses)
        else:
            try:
                self._ahead = ahead.result()
                new_reference = self._ahead.switched
            finally:
                self._objects_now = None
        return view, keyframe, new_reference, mapping, correction, observed

    def _correct_poses(self, velocity: torch.Tensor | None) -> Correction:
        """The pose graph's step for a new keyframe (``velocity``: its camera's, as tracked): its edges
        and closures, every keyframe pose corrected in the store (the trajectory, the odometry
        reference and the motion model read theirs from there), voxels where corrected depth lands,
        the most moved keyframes re-fit."""
        K, cfg = self.K, self.backend.cfg
        poses = self.backend.add_keyframe(self.keyframes.views(), K, velocity)

        def refit(views: list[View]) -> None:  # the stale part of the field, at the corrected (fixed) poses
            if cfg.refit_iters:
                self.mapper.run(views, [True] * len(views), cfg.refit_iters, K, self.generator)

        ids = self.keyframes.frame_ids()
        c = follow_corrections(poses, self.keyframes, lambda i: self.keyframes.view(ids.index(i)),
                               lambda v: self.allocator.allocate(self.field, v, K), refit, cfg.refit_min_m, self.policy.cfg.window + 1)
        self.backend.record(c.max_displacement_m, refit=bool(c.refit and cfg.refit_iters))
        return c

    # ---- after the last frame -------------------------------------------------------------------
    def finish(self) -> None:
        """The final mapping pass over every keyframe and the last tracked frame (once)."""
        if self.final_pass_done or not len(self.trajectory):
            return
        views = self.keyframes.views()
        if self.last_view is not None:  # its pose as the trajectory holds it now (its keyframe may have moved)
            last = self.last_view
            views.append(dataclasses.replace(last, pose=self.poses.pose(last.frame_id).to(last.pose.dtype)))
        start = time.perf_counter()
        self.between_frames = False
        final_pass(self.mapper, views, self.K, self.generator)
        self.timers.refine_s = time.perf_counter() - start
        self.final_pass_done = self.between_frames = True

    # ---- results --------------------------------------------------------------------------------
    def ate(self):
        """SE(3)-aligned ATE of the frames with GT so far (None with fewer than 3)."""
        return self.trajectory.ate(self.keyframes.pose_map())

    # ---- checkpoints ----------------------------------------------------------------------------
    def state_dict(self) -> dict[str, Any]:
        """Everything the next frame depends on but the field (saved beside it) and the global RNGs."""
        return {
            "position": len(self.trajectory),
            "final_pass_done": bool(self.final_pass_done),
            "clock": None if self.clock is None else self.clock.state_dict(),
            "last_mapped_tau": float(self.last_mapped_tau),
            "mapper": self.mapper.state_dict(),
            "keyframes": self.keyframes.state_dict(),
            "trajectory": self.trajectory.state_dict(),
            # a next frame tracked ahead is tracked again after a resume: its counts are not saved
            "tracker": self.tracker.state_dict() | ({} if self._ahead is None else {"counts": dataclasses.asdict(self._ahead.counts)}),
            "masks": self.masks.state_dict(),
            "last_view": None if self.last_view is None else view_state(self.last_view),
            "timers": dataclasses.asdict(self.timers),
            "generator": self.generator.get_state(),
            # objects observed ahead are observed again after a resume: the state before them is saved
            "objects": None if self.objects is None else self.objects.state_dict(None if self._ahead is None else self._ahead.objects_state),
            "backend": None if self.backend is None else self.backend.state_dict(),
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Continue from :meth:`state_dict` (tensors on this loop's device; the field loaded first)."""
        self._ahead, self._objects_now = None, None
        self.mapper.load_state_dict(state["mapper"])  # after the field: E has its saved rows
        self.keyframes.load_state_dict(state["keyframes"])
        self.trajectory.load_state_dict(state["trajectory"])
        self.tracker.load_state_dict(state["tracker"])
        self.masks.load_state_dict(state["masks"])
        self.clock = None if state["clock"] is None else Clock.from_state(state["clock"])
        self.last_mapped_tau = float(state["last_mapped_tau"])
        self.last_view = None if state["last_view"] is None else view_from_state(state["last_view"])
        self.final_pass_done = bool(state["final_pass_done"])
        self.timers = Timers(**state["timers"])
        self.generator.set_state(state["generator"].cpu())
        if self.objects is not None and state.get("objects") is not None:
            self.objects.load_state_dict(state["objects"])
        if self.backend is not None and state.get("backend") is not None:
            self.backend.load_state_dict(state["backend"])
