"""ObjectTracker: one rigid SE(3) track per moving object, frame by frame, with the camera known.

Per frame: the object instances (:mod:`tivne.slam.objects.instances`), then for each the existing
dense odometry (:func:`tivne.slam.tracking.odometry.track_pyramids`, photometric + point-to-plane, robust,
coarse to fine) on that object's pixels only, against the object's own keyframe observations,
turned into an object-to-world pose (:mod:`tivne.slam.objects.motion` derives it). The track's
velocity predicts the pose and, as a prior of ``objects.accel_sigma`` / ``angular_accel_sigma``, holds
what the pixels leave open (a symmetric object's spin, a blurred view); a pose more than
``MOTION_GATE_SIGMAS`` σ of that prior from the prediction is refused. An object seen again after more than
``max_gap_s`` is re-centred on what is seen now, by a stored view that showed as much of it, and turned by the
best of several rotation hypotheses (:mod:`tivne.slam.objects.reacquire`). Objects cut off by the border, or
back while partly hidden, wait for a whole view; a reference is renewed when its overlap or inlier ratio
falls, never from a view showing less than half of what it did (:mod:`tivne.slam.objects.references`).
An object aligned again to a view far back up that chain of views closes a loop: once its next view
confirms the chain's drift, the drift is spread over the chain's views and poses (:mod:`tivne.slam.objects.loops`).
"""

from __future__ import annotations

import bisect
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch

from data_modules.frame import Frame
from data_modules.poses import pose_on_track
from data_modules.tables import write_tum_trajectory
from tivne.config import ObjectsConfig, OdometryConfig
from tivne.geometry import backproject_depth, invert_pose, orthonormalize_pose, transform_points
from tivne.morphology import erode
from tivne.slam.objects.instances import (
    dataset_instances,
    extent,
    greedy_match,
    iou,
    mask_segments,
    projected_mask,
    smooth_depth,
    touches_border,
    world_points,
)
from tivne.slam.objects.live import LiveObject, PendingView
from tivne.slam.objects.loops import ChainLoops, view_aligner
from tivne.slam.objects.motion import camera_in_object, centred_information, object_pose, odometry_init, within_motion_gate
from tivne.slam.objects.reacquire import reacquire
from tivne.slam.objects.references import (
    REUSE_ANGLE_DEG,
    Reference,
    add_reference,
    centred_on,
    companions,
    comparable_view,
    pick_reference,
    shows_enough,
)
from tivne.slam.objects.track import ObjectTrack, run_velocity
from tivne.slam.outputs import RunDir
from tivne.slam.tracking.odometry import OdometryResult, PosePrior, frame_pyramid, track_pyramids
from tivne.slam.tracking.pyramid import crop_pyramid

# A track is written once it has this many observed poses (one-frame segments are clutter).
MIN_WRITTEN_POSES = 3
# The least share of an object's pixels its reference must see for a pose to count.
MIN_OVERLAP = 0.1
# Keyframe observations kept per object: views REUSE_ANGLE_DEG apart all round one axis (add_reference).
MAX_REFERENCES = 32
# Stored views an object's view is aligned to at once (the reference and its nearest companions).
JOINT_VIEWS = 5
# Alignments whose photometric RMS makes an object's typical residual (re-acquisition's yardstick).
RMS_HISTORY = 20
MOTION_GATE_SIGMAS = 10.0  # a pose further from the prediction (σ of the motion prior) is refused


@dataclass(frozen=True)
class ObjectObservation:
    """What the tracker made of one object in one frame.

    pose: (4, 4) float64 object-to-world (the prediction when ``ok`` is False; then it is not
    recorded in the track). new_track: the object's first frame. reidentified: a lost track taken
    up again. new_reference: this frame became the object's reference observation. overlap,
    inlier_ratio: the odometry's (nan on a new track).
    """

    object_id: int
    tau: float
    timestamp: float
    pose: torch.Tensor
    pixels: int
    ok: bool
    new_track: bool = False
    reidentified: bool = False
    new_reference: bool = False
    overlap: float = float("nan")
    inlier_ratio: float = float("nan")


class ObjectTracker:
    """Tracks every moving object of a stream (see the module docstring).

    Args:
        config: the ``objects`` section. K: (3, 3) camera matrix. odometry: the camera odometry's
            settings (the object odometry uses them with ``config.levels`` levels).
        names: dataset names of dataset instance ids (e.g. the synthetic family's object names).
        masks: the name of the run's mask provider (what ``objects.source=auto`` follows).
    """

    def __init__(self, config: ObjectsConfig, K: torch.Tensor, odometry: OdometryConfig = OdometryConfig(),
                 names: dict[int, str] | None = None, masks: str = "dataset") -> None:
        self.cfg = config
        # objects.source=auto follows the run's mask provider (its name: "dataset", "geometric", ...),
        # and with the dataset's masks segments a frame's mask where the frame has no instance ids.
        self.source = config.source if config.source != "auto" else ("dataset" if masks == "dataset" else "geometric")
        self.segment_without_ids = config.source == "auto"
        self.K = K.float()
        self.odo = replace(odometry, levels=config.levels, depth_filter=False)  # objects.depth_smoothing, on their pixels only
        self.names = dict(names or {})
        self.tracks: dict[int, ObjectTrack] = {}
        self.stamps: dict[int, dict[float, float]] = {}  # per track: τ -> timestamp [s]
        self.live: dict[int, LiveObject] = {}
        self.pending: dict[int, list[PendingView]] = {}  # new objects cut off by the border, oldest first
        self.reached: dict[int, Reference] = {}  # per object: the stored view its last pose was measured against
        self.loops = ChainLoops()
        self.next_id = 1
        self.seconds, self.frames = 0.0, 0

    # ---- the per-frame step -------------------------------------------------------------------
    def instances_of(self, frame: Frame, dynamic: torch.Tensor | None) -> torch.Tensor | None:
        """What :meth:`step` reads for ``objects.source``: the frame's instance ids (dataset) or its
        dynamic mask ``dynamic`` (H, W) bool (geometric). Under ``auto`` with the dataset's masks, a
        frame without instance ids (a dataset with motion masks only) gives its mask's segments, so
        its moving objects still get tracks and fields instead of dropping out of the map."""
        if self.source == "geometric" or (frame.instances is None and self.segment_without_ids):
            return dynamic
        return frame.instances

    def observe(self, frame: Frame, camera_pose: torch.Tensor, tau: float, dynamic: torch.Tensor | None) -> list[ObjectObservation]:
        """:meth:`step` on :meth:`instances_of`, timed (``seconds``, ``frames``: the objects' cost)."""
        start = time.perf_counter()
        out = self.step(frame, camera_pose, tau, self.instances_of(frame, dynamic))
        self.seconds += time.perf_counter() - start
        self.frames += 1
        return out

    def metrics(self) -> dict[str, Any]:
        """metrics.json keys of the tracking itself: tracks written, the objects' s/frame, loop closures."""
        return {"objects_written": len(self.written_tracks()),
                "objects_s_per_frame": self.seconds / self.frames if self.frames else None} | self.loops.metrics()

    def step(self, frame: Frame, camera_pose: torch.Tensor, tau: float, instances: torch.Tensor | None) -> list[ObjectObservation]:
        """Observe the objects of one frame whose camera-to-world pose ``camera_pose`` (4, 4) is known.

        ``instances``: (H, W) int64 dataset instance ids (``objects.source=dataset``) or (H, W) bool
        dynamic mask (``geometric``); None: no object this frame.
        """
        if instances is None:
            return []
        T_wc = orthonormalize_pose(camera_pose.detach().double().cpu())  # a float32 pose is orthonormal to 1e-7 only
        depth = frame.depth.cpu()
        if instances.dtype == torch.bool:
            segments = mask_segments(instances.cpu(), depth, self.cfg.min_pixels)
            found = self._associate(segments, frame, T_wc, tau)
        else:
            found = {(k, False): m for k, m in dataset_instances(instances.cpu(), depth, self.cfg.min_pixels).items()}
        self._drop_stale_pending(float(frame.timestamp))
        seen = [self._observe(oid, mask, frame, T_wc, tau, reid) for (oid, reid), mask in sorted(found.items())]
        return [o for o in seen if o is not None]

    def _observe(self, oid: int, mask: torch.Tensor, frame: Frame, T_wc: torch.Tensor, tau: float, reid: bool) -> ObjectObservation | None:
        """One object's observation; None while a new object waits for a view the border does not cut."""
        inner = erode(mask, 1)
        inner = inner if int(inner.sum()) >= self.cfg.min_pixels // 2 else mask
        rgb, depth = frame.rgb.cpu(), frame.depth.cpu()
        pyramid = frame_pyramid(rgb, smooth_depth(depth, inner, self.cfg.depth_smoothing), self.K, self.odo, ~inner)
        pixels, t = int(mask.sum()), float(frame.timestamp)
        back = oid in self.tracks and oid in self.live and t - self.live[oid].last_time > self.cfg.max_gap_s
        if oid not in self.tracks or back:
            # A sliver at the border is a poor view to start from (its rotation is barely determined and
            # each later view is aligned to it): a new object, or one back after a gap, waits for a
            # whole view; then the waiting views are aligned to it.
            waiting = self.pending.setdefault(oid, [])
            live = self.live.get(oid)  # one coming back also waits while hidden in part (occluded)
            hidden = back and live is not None and live.reference is not None and not shows_enough(
                int(inner.sum()), float(depth[inner & (depth > 0)].median()), live.reference)
            if (touches_border(mask) or hidden) and len(waiting) < self.cfg.border_wait:
                waiting.append(PendingView(pyramid, mask, T_wc, tau, t, pixels))
                return None
            if not back:
                first = self._start(oid, inner, pyramid, depth, T_wc, tau, t, pixels)
                self._backfill(oid, self.pending.pop(oid, []), pixels, self.live[oid].reference)
                return first
        track, live = self.tracks[oid], self.live.get(oid)
        steady, in_run = self._steady(oid)
        T_pred = self._predict(oid, inner, depth, T_wc, tau, t, steady)
        if live is None or live.reference is None:  # resumed: no reference pyramid kept
            self._new_reference(oid, inner, pyramid, depth, T_wc, T_pred, tau, t)
            return ObjectObservation(oid, tau, t, T_pred, pixels, False, reidentified=reid, new_reference=True)
        if back:  # it may have turned by anything meanwhile: several rotations, the best alignment
            ref, res = reacquire(live.references, track, pyramid, int(inner.sum()), T_pred, T_wc,
                                 world_points(inner, depth, self.K, T_wc).mean(0), self.odo, live.typical_rms())
        else:
            C_pred = camera_in_object(T_pred, T_wc)
            ref = pick_reference(live.references, C_pred, REUSE_ANGLE_DEG)
            if self.loops.step(oid, live.references, track, ref, self.reached.get(oid), tau, view_aligner(pyramid, T_pred, T_wc, self.odo),
                               self._good, live.typical_rms()):  # a loop up the chain closed: its past poses moved
                T_pred = self._predict(oid, inner, depth, T_wc, tau, t, steady)
                C_pred = camera_in_object(T_pred, T_wc)
                ref = pick_reference(live.references, C_pred, REUSE_ANGLE_DEG)
            init = odometry_init(T_pred, T_wc, ref.C)
            prior = self._prior(init, ref.C, t - live.last_time) if steady else None  # one view since a gap: no velocity
            also = tuple((o.pyramid, invert_pose(o.C) @ ref.C) for o in companions(live.references, ref, C_pred, 2 * REUSE_ANGLE_DEG, JOINT_VIEWS - 1))
            res = track_pyramids(ref.pyramid, pyramid, init, self.odo, prior=prior, also=also)
        T_wo = object_pose(T_wc, res.T_ref_cur, ref.C)
        accel = self.cfg.accel_sigma if in_run else float("inf")  # a velocity read across a gap is unknown: the turn alone
        jolt = not back and steady and not within_motion_gate(  # a lock onto smeared or repeated texture
            T_wo, T_pred, t - live.last_time, accel, self.cfg.angular_accel_sigma, MOTION_GATE_SIGMAS)
        if not self._good(res) or jolt:
            if back and len(self.pending.get(oid, [])) < self.cfg.border_wait:  # no anchor from one poor view: try the next
                self.pending.setdefault(oid, []).append(PendingView(pyramid, mask, T_wc, tau, t, pixels))
                return None
            if back:  # no rotation aligns a whole view: restart from the prediction (its own motion stays right)
                self.pending.pop(oid, None)
                self._new_reference(oid, inner, pyramid, depth, T_wc, T_pred, tau, t)
            return ObjectObservation(oid, tau, t, T_pred, pixels, False, reidentified=reid,
                                     overlap=res.overlap, inlier_ratio=res.inlier_ratio)
        track.add(tau, T_wo)
        self.stamps[oid][tau] = t
        self.reached[oid] = ref
        if back:
            self._backfill(oid, self.pending.pop(oid, []), pixels, ref)
        # A view that shows less than half of what its reference did at the same distance (occluded)
        # does not become a reference: it would hand its open rotation on. Nor does one the border
        # cuts that shows less than its reference while it still aligns to it: its overlap fell
        # because it is cut, not because the reference is stale, and a chain of ever smaller cut
        # views, each over half the one before, would leave a sliver to centre and align the object
        # on when it comes back (crossing, scene seed 4: 8.8 cm off after its near box left the view).
        misfit = res.inlier_ratio < self.cfg.keyframe_inliers  # the reference no longer fits what is seen
        stale = res.overlap < self.cfg.keyframe_overlap or misfit
        share = 1.0 if touches_border(mask) and not misfit else 0.5
        new_ref = stale and shows_enough(int(inner.sum()), float(camera_in_object(T_wo, T_wc)[:3, 3].norm()), ref, share)
        self._remember(oid, inner, depth, T_wc, T_wo, t, pyramid if new_ref else None, tau)
        if not back and np.isfinite(res.rms_photometric):
            self.live[oid].rms = (self.live[oid].rms + [res.rms_photometric])[-RMS_HISTORY:]
        return ObjectObservation(oid, tau, t, T_wo, pixels, True, reidentified=reid, new_reference=new_ref,
                                 overlap=res.overlap, inlier_ratio=res.inlier_ratio)

    def _prior(self, init: torch.Tensor, C_ref: torch.Tensor, dt: float) -> PosePrior | None:
        """The motion prior (``objects.accel_sigma``, ``angular_accel_sigma``) on the odometry's
        T_ref_cur around its constant-velocity ``init``: isotropic at the object's origin (the centre
        of its first points), moved into the odometry's tangent at the reference camera."""
        a_t, a_r = self.cfg.accel_sigma, self.cfg.angular_accel_sigma
        if a_t <= 0 or a_r <= 0 or dt <= 0 or dt > self.cfg.max_gap_s:
            return None
        return PosePrior(init, centred_information(0.5 * a_t * dt * dt, 0.5 * a_r * dt * dt, invert_pose(C_ref)[:3, 3]))

    def _good(self, res: OdometryResult) -> bool:
        """The object odometry is usable: enough consistent pairs overlapping by MIN_OVERLAP (not
        the camera's overlap or pose_std thresholds: an object entering the view grows by more than
        its reference shows, and on few pixels σ is larger than a whole frame's)."""
        o = self.odo
        return res.num_valid >= o.min_correspondences and res.overlap >= MIN_OVERLAP and res.inlier_ratio >= o.min_inlier_ratio

    def _start(self, oid, mask, pyramid, depth, T_wc, tau, t, pixels) -> ObjectObservation:
        """A new track: the object frame has the world's axes and its origin at the centre of the
        first observed points."""
        T_wo = torch.eye(4, dtype=torch.float64)
        T_wo[:3, 3] = world_points(mask, depth, self.K, T_wc).mean(0)
        self.tracks[oid] = ObjectTrack(oid, self.names.get(oid))
        self.tracks[oid].add(tau, T_wo)
        self.stamps[oid] = {tau: t}
        self.next_id = max(self.next_id, oid + 1)
        self._remember(oid, mask, depth, T_wc, T_wo, t, pyramid, tau)
        return ObjectObservation(oid, tau, t, T_wo, pixels, True, new_track=True, new_reference=True)

    def _backfill(self, oid: int, waiting: list[PendingView], pixels: int, ref: Reference) -> None:
        """The poses of the observations that waited for a whole view (``pixels`` pixels, aligned to
        ``ref``), newest first, each aligned to ``ref`` starting from the track carried back to it.
        Back to the first one that fails or shows less than half as many pixels: a sliver leaves the
        rotation open."""
        track = self.tracks[oid]
        for obs in reversed(waiting):
            if obs.pixels < pixels // 2:
                break
            # The poses after it (since the gap, if any) carried back at their velocity; the motion
            # prior only once there is a velocity.
            taus = track.observed_taus()
            later = bisect.bisect_right(taus, obs.tau)
            init = odometry_init(pose_on_track(taus[later:], track.poses()[later:], obs.tau), obs.T_wc, ref.C)
            dt = self.stamps[oid][taus[later]] - obs.time
            prior = self._prior(init, ref.C, dt) if len(taus) - later >= 2 else None
            res = track_pyramids(ref.pyramid, obs.pyramid, init, self.odo, prior=prior)
            if not self._good(res):
                break
            track.add(obs.tau, object_pose(obs.T_wc, res.T_ref_cur, ref.C))
            self.stamps[oid][obs.tau] = obs.time

    def _drop_stale_pending(self, t: float) -> None:
        """Forget waiting observations of objects not seen for longer than ``max_gap_s``."""
        self.pending = {k: w for k, w in self.pending.items() if not (w and t - w[-1].time > self.cfg.max_gap_s)}

    def _new_reference(self, oid, mask, pyramid, depth, T_wc, T_wo, tau, t) -> None:
        """Restart the object's tracking from this view at pose T_wo (a prediction): the pose is
        recorded too, as the anchor the following poses are measured from (they are relative to it)."""
        self.tracks[oid].add(tau, T_wo)
        self.stamps[oid][tau] = t
        self._remember(oid, mask, depth, T_wc, T_wo, t, pyramid, tau)

    def _remember(self, oid, mask, depth, T_wc, T_wo, t, pyramid, tau) -> None:
        """Keep the observation's object-frame points (and, with ``pyramid``, make it the reference)."""
        C = camera_in_object(T_wo, T_wc)
        cam = backproject_depth(depth, self.K)[mask & (depth > 0)].double()
        pts = transform_points(C, cam[:: max(1, len(cam) // 2000)])
        if len(pts) >= 10:  # the box from the 1-99 % range: silhouette pixels may sit on the background
            lo, hi = torch.quantile(pts, 0.01, dim=0), torch.quantile(pts, 0.99, dim=0)
            self.tracks[oid].grow_box(torch.stack([lo, hi]))
        refs = list(self.live[oid].references) if oid in self.live else []
        if pyramid is not None:
            refs = add_reference(refs, Reference(crop_pyramid(pyramid, mask), C, tau, int(mask.sum()), pts), MAX_REFERENCES)
        self.live[oid] = LiveObject(refs, pts, extent(pts), t, self.live[oid].rms if oid in self.live else [])

    def _predict(self, oid: int, mask: torch.Tensor | None, depth: torch.Tensor, T_wc: torch.Tensor, tau: float, t: float,
                 steady: bool) -> torch.Tensor:
        """Constant velocity: the track carried on at its end's velocity (``pose_at``), when the object
        was seen within ``max_gap_s`` or it has a velocity (``steady``, :meth:`_steady`); else its
        last pose. After a gap, and on a new track's second view (no velocity yet), that pose is moved
        so the last observed points' centre lands on this observation's (``mask``; None: not moved),
        which only picks the predicted side; the stored view of that side that showed about as much as
        now then centres it (:func:`comparable_view`, :func:`centred_on`: a sliver's centre is not a whole view's)."""
        track, live = self.tracks[oid], self.live.get(oid)
        recent = live is not None and t - live.last_time <= self.cfg.max_gap_s
        # Just seen: carried on at the track's last velocity, across a gap if it had one (held still it
        # lags a moving object, and the prior then holds the lag); after a gap only a steady velocity.
        T = track.pose_at(tau) if recent or steady else track.poses()[-1].clone()
        if recent and (len(track) > 1 or mask is None):  # one pose: held still, a fast object leaves the basin
            return T
        if live is not None and len(live.points):
            centre_now = world_points(mask, depth, self.K, T_wc).mean(0)
            T[:3, 3] += centre_now - transform_points(T, live.points.mean(0, keepdim=True))[0]
            if live.references:
                ref = comparable_view(live.references, camera_in_object(T, T_wc), int(mask.sum()), REUSE_ANGLE_DEG)
                T = centred_on(T, ref, centre_now, T_wc[:3, :3], track.middle)
        return T

    def _steady(self, oid: int) -> tuple[bool, bool]:
        """Whether the track has a velocity, and whether it is read within its last run (:func:`run_velocity`)."""
        return run_velocity(self.tracks[oid].observed_taus(), self.stamps[oid], self.cfg.max_gap_s)

    # ---- identities from geometric segments ---------------------------------------------------
    def _associate(self, segments: list[torch.Tensor], frame: Frame, T_wc: torch.Tensor, tau: float) -> dict[tuple[int, bool], torch.Tensor]:
        """{(track id, re-identified): mask}: segments matched to followed tracks by the IoU of the
        track's last points moved by its predicted motion; the rest re-identify a lost track of
        similar size predicted near them, or start a track."""
        t, depth, shape = float(frame.timestamp), frame.depth.cpu(), tuple(frame.depth.shape)
        followed = [k for k, lv in self.live.items() if t - lv.last_time <= self.cfg.max_gap_s]
        scores = np.zeros((len(followed), len(segments)))
        for i, k in enumerate(followed):
            T_pred = self._predict(k, None, depth, T_wc, tau, t, self._steady(k)[0])
            footprint = projected_mask(transform_points(T_pred, self.live[k].points), T_wc, self.K, shape)
            scores[i] = [iou(footprint, s) for s in segments]
        out, taken = {}, set()
        for i, j in greedy_match(scores, self.cfg.min_iou):
            out[(followed[i], False)] = segments[j]
            taken.add(j)
        for j, seg in enumerate(segments):
            if j in taken:
                continue
            busy = set(followed) | {key for key, _ in out}
            k = self._reidentify(seg, depth, T_wc, tau, busy)
            if k is None:
                k = self._waiting_for(seg, busy)
            if k is None:
                k, self.next_id = self.next_id, self.next_id + 1
            out[(k, k in self.tracks)] = seg
        return out

    def _waiting_for(self, seg: torch.Tensor, busy: set[int]) -> int | None:
        """The waiting new object (cut off by the border) whose last mask overlaps the segment best,
        by at least ``min_iou``; None if none (objects move little in one frame)."""
        scores = [(iou(w[-1].mask, seg), k) for k, w in self.pending.items() if w and k not in busy]
        best = max(scores, default=(0.0, None))
        return best[1] if best[0] >= self.cfg.min_iou else None

    def _reidentify(self, seg: torch.Tensor, depth: torch.Tensor, T_wc: torch.Tensor, tau: float, busy: set[int]) -> int | None:
        """The lost track that puts its points' centre nearest the segment's centre, held at its last
        pose or carried on at its end velocity (``pose_at``; whichever is nearer), within
        ``reid_distance`` and with a size within ``reid_size_ratio``; None if none."""
        pts = world_points(seg, depth, self.K, T_wc)
        if len(pts) == 0:
            return None
        centre, size, best = pts.mean(0), extent(pts), None
        for k, lv in self.live.items():
            if k in busy or not len(lv.points):
                continue
            ratio = max(size, lv.size) / max(min(size, lv.size), 1e-6)
            ends = [transform_points(T, lv.points).mean(0) for T in (self.tracks[k].poses()[-1], self.tracks[k].pose_at(tau))]
            d = min(float((e - centre).norm()) for e in ends)
            if d <= self.cfg.reid_distance and ratio <= self.cfg.reid_size_ratio and (best is None or d < best[0]):
                best = (d, k)
        return None if best is None else best[1]

    # ---- results ------------------------------------------------------------------------------
    def written_tracks(self) -> list[ObjectTrack]:
        return [tr for k, tr in sorted(self.tracks.items()) if len(tr) >= MIN_WRITTEN_POSES]

    def write(self, run: RunDir) -> list[Path]:
        """objects/<id>.txt (TUM: timestamp, object-to-world pose at each observed frame) per track."""
        paths = []
        for tr in self.written_tracks():
            stamps = [self.stamps[tr.object_id][tau] for tau in tr.observed_taus()]
            paths.append(write_tum_trajectory(run.object_path(tr.object_id), stamps, tr.poses()))
        return paths

    def snapshot(self) -> dict[str, Any]:
        """What :meth:`state_dict` saves, as it is now, copied cheaply (no tensor is copied: the
        tracker replaces, never changes, the poses and points it saves)."""
        return {"tracks": {k: tr.copy() for k, tr in self.tracks.items()}, "stamps": {k: dict(v) for k, v in self.stamps.items()},
                "live": dict(self.live), "next_id": self.next_id, "loops": self.loops.metrics()}

    def state_dict(self, snapshot: dict[str, Any] | None = None) -> dict[str, Any]:
        """The tracks and identities, now or as a :meth:`snapshot` held them (not the reference
        pyramids: after a restore each object's next observation becomes its reference, at its predicted pose)."""
        s = snapshot or self.snapshot()
        return {
            "tracks": {k: tr.state_dict() for k, tr in s["tracks"].items()},
            "stamps": s["stamps"],
            "live": {k: {"points": lv.points, "size": lv.size, "last_time": lv.last_time} for k, lv in s["live"].items()},
            "next_id": s["next_id"],
            "loops": s["loops"],
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.tracks = {int(k): ObjectTrack.from_state_dict(s) for k, s in state["tracks"].items()}
        self.stamps = {int(k): {float(a): float(b) for a, b in v.items()} for k, v in state["stamps"].items()}
        self.live = {int(k): LiveObject([], v["points"], float(v["size"]), float(v["last_time"])) for k, v in state["live"].items()}
        self.next_id = int(state["next_id"])
        self.loops.restore(state.get("loops", {}))  # a checkpoint from before loop closures has none
