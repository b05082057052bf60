"""The tracking front end (tivne/slam/tracking/tracker.py): odometry against a reference, typed
results, loss detection, the precheck and its counters."""

from __future__ import annotations

import dataclasses
import math

import pytest
import torch

from data_modules.frame import Frame
from data_modules.synthetic import SyntheticSequence
from tivne.config import FieldTrackingConfig, LossWeights, OdometryConfig, RenderConfig, TrackingConfig
from tivne.field.networks import TimeVaryingField
from tivne.geometry import invert_pose, se3_exp, se3_log
from tivne.render.rays import View
from tivne.slam.tracking import TrackStatus
from tivne.slam.tracking.tracker import Tracker, pose_jump, reference_to_drop, velocity_steps

W, H = 160, 120


class Poses:
    """A PoseLookup over a plain list (index = frame id)."""

    def __init__(self, poses: list[torch.Tensor], times: list[float] | None = None) -> None:
        self.list = poses
        self.times = [i / 30 for i in range(len(poses))] if times is None else times  # frame_at's timestamps

    def pose(self, frame_id: int) -> torch.Tensor:
        return self.list[frame_id].double()

    def recent(self, n: int) -> list[torch.Tensor]:
        return [p.double() for p in self.list[-n:]]

    def recent_times(self, n: int) -> list[float]:
        return self.times[-n:]


@pytest.fixture(scope="module")
def room() -> SyntheticSequence:
    return SyntheticSequence("static_room", num_frames=8, width=W, height=H, depth_noise=False, rgb_noise=0.0, cache_dir=None)


def frame_at(seq: SyntheticSequence, c2w: torch.Tensor, index: int) -> Frame:
    rgb, depth, _ = seq.render_at(c2w, 0.0)
    return Frame(index=index, timestamp=index / 30, rgb=rgb, depth=depth, mask=None, gt_pose=None)


def view_of(frame: Frame, pose: torch.Tensor) -> View:
    return View(frame.index, 0.0, frame.rgb, frame.depth, None, pose)


def relative(seq: SyntheticSequence, i: int) -> torch.Tensor:
    """GT pose of frame i in the first camera's frame (the SLAM world frame), float32."""
    return (invert_pose(seq.camera_pose(0)) @ seq.camera_pose(i)).float()


def make_tracker(method: str = "odometry", field: dict | None = None, **kw) -> Tracker:
    return Tracker(TrackingConfig(method=method, **kw), FieldTrackingConfig(**(field or {})), OdometryConfig(), RenderConfig(), LossWeights())


def track(tracker: Tracker, frame: Frame, poses: list[torch.Tensor], K: torch.Tensor, field=None, generator=None):
    return tracker.track(frame.index, frame, 0.0, None, field or TimeVaryingField(), Poses(poses), K, 0.0, generator)


def test_odometry_tracks_against_the_reference_and_switches_it(room):
    tracker = make_tracker(reference="adaptive")
    K = room.intrinsics.K()
    first = frame_at(room, room.camera_pose(0), 0)
    origin = track(tracker, first, [], K)
    assert origin.status is TrackStatus.TRACKED and torch.equal(origin.pose, torch.eye(4))  # the world frame
    assert tracker.update_reference(view_of(first, origin.pose), K, origin, is_keyframe=True) and tracker.reference.frame_id == 0
    poses = [torch.eye(4)]
    for i in range(1, 4):
        result = track(tracker, frame_at(room, room.camera_pose(i), i), poses, K)
        t_err, r_err = pose_jump(result.pose, relative(room, i))
        assert result.status is TrackStatus.TRACKED and t_err < 2e-3 and r_err < 0.1, (i, t_err, r_err, result.describe())
        assert result.odometry.ok and result.odometry.inlier_ratio > 0.9
        assert result.scalars()["odo_ok"] == 1.0  # scalars only for the logs
        poses.append(result.pose)
    assert tracker.counts.frames == 3 and tracker.counts.lost == 0
    # adaptive: a well-overlapping frame does not become the reference; a poor overlap does
    good = dataclasses.replace(result, odometry=dataclasses.replace(result.odometry, overlap=0.9, inlier_ratio=0.9))
    assert not tracker.update_reference(view_of(first, poses[-1]), K, good, False)
    poor = dataclasses.replace(result, odometry=dataclasses.replace(result.odometry, overlap=0.5))
    assert tracker.update_reference(dataclasses.replace(view_of(first, poses[-1]), frame_id=3), K, poor, False)
    assert tracker.reference.frame_id == 3 and not hasattr(tracker.reference, "pose")  # an id: its pose is the trajectory's


def test_a_frame_that_jumps_is_lost_and_keeps_the_prediction_not_identity(room, capsys):
    tracker = make_tracker()
    K = room.intrinsics.K()
    first = frame_at(room, room.camera_pose(0), 0)
    tracker.update_reference(view_of(first, torch.eye(4)), K, track(tracker, first, [], K), is_keyframe=True)
    poses = [torch.eye(4), relative(room, 1)]
    # the camera turned 120 degrees between two frames: nothing overlaps the reference
    turned = room.camera_pose(1) @ se3_exp(torch.tensor([0.0, 0.0, 0.0, 0.0, math.radians(120.0), 0.0], dtype=torch.float64))
    result = track(tracker, frame_at(room, turned, 2), poses, K)
    assert result.status is TrackStatus.LOST and result.lost and result.jump_deg > 30
    predicted = poses[-1] @ invert_pose(poses[-2]) @ poses[-1]
    assert torch.allclose(result.pose, predicted, atol=1e-5)  # the motion model's guess, flagged
    assert not torch.allclose(result.pose, torch.eye(4), atol=1e-3)
    assert tracker.counts.lost == 1 and "warning: frame 2" in capsys.readouterr().err  # the tracker's own warning line


@pytest.mark.parametrize("dropped", [0, 9])
def test_a_frame_after_dropped_frames_is_predicted_over_the_time_between_them(room, dropped):
    # the camera slides 1 cm a frame; frames 2..10 never arrive (a stalled recorder) or all do
    tracker = make_tracker(max_jump_m=0.03)
    K = room.intrinsics.K()
    world = invert_pose(room.camera_pose(0))
    slid = [room.camera_pose(0) @ se3_exp(torch.tensor([0.01 * i, 0.0, 0.0, 0.0, 0.0, 0.0], dtype=torch.float64)) for i in range(12)]
    first = frame_at(room, slid[0], 0)
    tracker.update_reference(view_of(first, torch.eye(4)), K, track(tracker, first, [], K), is_keyframe=True)
    poses = [(world @ slid[i]).float() for i in (0, 1)]
    arrives = 2 + dropped
    frame = dataclasses.replace(frame_at(room, slid[arrives], arrives), index=2)
    assert velocity_steps(Poses(poses).recent_times(2), float(frame.timestamp)) == pytest.approx(1 + dropped)
    result = track(tracker, frame, poses, K)
    t_err, r_err = pose_jump(result.pose, (world @ slid[arrives]).float())
    assert result.status is TrackStatus.TRACKED and result.jump_m < 0.005 and t_err < 2e-3 and r_err < 0.1, (t_err, result.describe())


def test_field_tracker_alone_reports_loss_by_inlier_ratio(room):
    tracker = make_tracker("field", field=dict(iters=2, rays=64))
    f = frame_at(room, room.camera_pose(1), 1)
    field = TimeVaryingField(voxel_size=0.2, capacity=512, hidden_dim=16)  # an empty map: no ray renders
    result = track(tracker, f, [torch.eye(4)], room.intrinsics.K(), field, torch.Generator().manual_seed(0))
    assert result.lost and result.field.inlier_ratio == 0.0 and result.odometry is None
    assert torch.equal(result.pose, torch.eye(4))  # the prediction (zero motion from one pose), flagged lost


def test_a_frame_without_static_depth_is_not_tracked(room, capsys):
    tracker = make_tracker(min_static_pixels=100)
    f = frame_at(room, room.camera_pose(1), 1)
    blank = dataclasses.replace(f, depth=torch.zeros_like(f.depth))
    last = relative(room, 0)
    result = track(tracker, blank, [last], room.intrinsics.K())
    assert result.status is TrackStatus.NO_DEPTH and result.lost and torch.equal(result.pose, last)
    assert tracker.counts.without_tracking == 1 and tracker.counts.frames == 0
    assert "only 0 static pixels with depth" in capsys.readouterr().err


def turned(seq: SyntheticSequence, degrees: float) -> torch.Tensor:
    """The first camera's GT pose turned by ``degrees`` about its y axis (world frame of the scene)."""
    return seq.camera_pose(0) @ se3_exp(torch.tensor([0.0, 0.0, 0.0, 0.0, math.radians(degrees), 0.0], dtype=torch.float64))


def test_a_camera_back_at_an_earlier_view_reuses_that_views_reference(room):
    tracker = make_tracker(reference="adaptive", stored_references=4)
    K = room.intrinsics.K()
    world = invert_pose(room.camera_pose(0))
    frames = [frame_at(room, turned(room, deg), i) for i, deg in enumerate([0.0, 25.0, 3.0])]
    poses = [(world @ turned(room, deg)).float() for deg in (0.0, 25.0, 3.0)]
    lookup = Poses(poses)
    first = track(tracker, frames[0], [], K)
    assert tracker.update_reference(view_of(frames[0], poses[0]), K, first, True, lookup)
    result = track(tracker, frames[1], poses[:1], K)
    stale = dataclasses.replace(result, odometry=dataclasses.replace(result.odometry, overlap=0.3))
    # 25 degrees away: no stored view fits, the frame becomes a new reference
    assert tracker.update_reference(view_of(frames[1], poses[1]), K, stale, False, lookup) and tracker.reference.frame_id == 1
    # back within 3 degrees of the first view: its reference again, not a third one
    assert tracker.update_reference(view_of(frames[2], poses[2]), K, stale, False, lookup)
    assert tracker.reference.frame_id == 0 and [r.frame_id for r in tracker.stored] == [0, 1]
    # without the pose lookup (or with reference=frame) nothing is reused
    assert tracker.update_reference(view_of(frames[2], poses[2]), K, stale, False) and tracker.reference.frame_id == 2
    # a checkpoint keeps every stored reference and which is current
    restored = make_tracker(reference="adaptive", stored_references=4)
    restored.load_state_dict(tracker.state_dict())
    assert [r.frame_id for r in restored.stored] == [0, 1, 2] and restored.reference is restored.stored[2]
    assert torch.equal(restored.stored[0].pyramid[0].intensity, tracker.stored[0].pyramid[0].intensity)


def test_reference_to_drop_keeps_the_oldest_and_the_current_and_thins_the_closest_pair():
    def at(deg: float) -> torch.Tensor:
        return se3_exp(torch.tensor([0.0, 0.0, 0.0, 0.0, math.radians(deg), 0.0], dtype=torch.float64))

    assert reference_to_drop([at(0.0), at(30.0), at(31.0), at(60.0), at(0.5)], 0.1, 15.0) == 2  # 30 / 31: the newer
    assert reference_to_drop([at(0.0), at(30.0)], 0.1, 15.0) == 0  # room for one: the current stays


def test_stored_references_that_see_the_frame_are_aligned_jointly(room):
    tracker = make_tracker(reference="adaptive", stored_references=4, joint_references=2)
    K = room.intrinsics.K()
    world = invert_pose(room.camera_pose(0))
    degrees = [0.0, 25.0, 4.0]
    frames = [frame_at(room, turned(room, deg), i) for i, deg in enumerate(degrees)]
    poses = [(world @ turned(room, deg)).float() for deg in degrees]
    lookup = Poses(poses)
    tracker.update_reference(view_of(frames[0], poses[0]), K, track(tracker, frames[0], [], K), True, lookup)
    for i in (1, 2):  # force new references at 25 and 4 degrees (stale, and nothing reusable verified)
        result = track(tracker, frames[i], poses[:i], K)
        stale = dataclasses.replace(result, odometry=dataclasses.replace(result.odometry, overlap=0.3))
        tracker.reference = None  # nothing to reuse from: a fresh reference each time
        tracker.update_reference(view_of(frames[i], poses[i]), K, stale, False)
    assert [r.frame_id for r in tracker.stored] == [0, 1, 2] and tracker.reference.frame_id == 2
    target = (world @ turned(room, 2.0)).float()
    view = view_of(frame_at(room, turned(room, 2.0), 3), target)
    also, chosen = tracker._companions(view, tracker.reference, lookup.pose(2), target.double(), lookup, K)
    assert len(also) == 1 and also[0][0] is tracker.stored[0].pyramid  # 25 degrees away: not a companion
    assert chosen == [tracker.stored[0]]
    assert torch.allclose(also[0][1], invert_pose(lookup.pose(0)) @ lookup.pose(2))
    result = track(tracker, frame_at(room, turned(room, 2.0), 3), poses, K)
    t_err, r_err = pose_jump(result.pose, target)
    assert result.status is TrackStatus.TRACKED and t_err < 2e-3 and r_err < 0.1, (t_err, r_err)


@pytest.mark.parametrize("readout_s", [0.0, 0.03])
def test_a_reference_keeps_the_velocity_its_rolling_shutter_was_read_at(room, readout_s):
    """With a rolling shutter each frame's velocity (from its tracked pose and the one before) goes with
    the reference made of it, through a checkpoint; a global shutter keeps none."""
    tracker = Tracker(TrackingConfig(reference="frame"), FieldTrackingConfig(), OdometryConfig(), RenderConfig(), LossWeights(),
                      readout_s=readout_s)
    K = room.intrinsics.K()
    poses = [torch.eye(4)]
    first = track(tracker, frame_at(room, room.camera_pose(0), 0), [], K)
    tracker.update_reference(view_of(frame_at(room, room.camera_pose(0), 0), first.pose), K, first, True)
    for i in range(1, 3):
        frame = frame_at(room, room.camera_pose(i), i)
        result = track(tracker, frame, poses, K)
        assert result.status is TrackStatus.TRACKED
        poses.append(result.pose)
    assert tracker.update_reference(view_of(frame, poses[-1]), K, result, is_keyframe=True)
    assert tracker.stored[0].velocity is None  # the first frame has no motion to read
    if readout_s == 0:
        assert tracker.reference.velocity is None
        return
    expected = se3_log((invert_pose(poses[1].double()) @ poses[2].double())[None])[0] * 30  # per second at 30 Hz
    assert torch.allclose(tracker.reference.velocity, expected, atol=1e-6)
    truth = se3_log((invert_pose(relative(room, 1).double()) @ relative(room, 2).double())[None])[0] * 30
    assert (tracker.reference.velocity - truth).abs().max() < 0.05  # the camera's own motion (m/s, rad/s)
    restored = make_tracker(reference="adaptive")
    restored.load_state_dict(tracker.state_dict())
    assert torch.equal(restored.reference.velocity, tracker.reference.velocity) and restored.stored[0].velocity is None
