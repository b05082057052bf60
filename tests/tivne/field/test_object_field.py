"""Object fields beside the static map (tivne/field/objects.py): frames, routing of depth,
composition, the optimiser hook, and the GT oracle's SLAM frame (tivne/field/oracle.py)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from tivne.config import ConfigError, FieldConfig, MappingConfig, ObjectFieldConfig
from tivne.field.networks import TimeVaryingField, time_encoding
from tivne.field.objects import ObjectField, attach_optimizer, build_field, inside_box, static_only, world_to_object
from tivne.field.oracle import ground_truth_tracks


def pose(yaw: float, t: tuple[float, float, float]) -> torch.Tensor:
    c, s = math.cos(yaw), math.sin(yaw)
    T = torch.eye(4, dtype=torch.float64)
    T[:3, :3] = torch.tensor([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    T[:3, 3] = torch.tensor(t, dtype=torch.float64)
    return T


class LinearTrack:
    """An object moving along x at 1 m per τ and turning 0.5 rad per τ, box ±0.1 m."""

    def __init__(self, seen: tuple[float, float] = (-1e9, 1e9)) -> None:
        self.box = torch.tensor([[-0.1, -0.1, -0.1], [0.1, 0.1, 0.1]], dtype=torch.float64)
        self.seen = seen

    def pose_at(self, tau: float) -> torch.Tensor:
        return pose(0.5 * tau, (float(tau), 0.0, 1.0))

    def observed_near(self, tau: float, window: float) -> bool:
        return self.seen[0] - window <= tau <= self.seen[1] + window


def small_object_field(time: bool = False, margin: float = 0.0) -> ObjectField:
    torch.manual_seed(0)
    obj = FieldConfig(time=True, voxel_size=0.05, embed_dim=8, capacity=64, hidden_dim=16, init_std=0.5)
    field = ObjectField(obj, box_margin=margin, window=0.5, object_dilation=0, time=time, voxel_size=0.1, embed_dim=8, capacity=64,
                        hidden_dim=16, init_std=0.5)
    field.set_tracks({1: LinearTrack()})
    return field


def test_world_to_object_inverts_the_pose_per_point_time():
    track = LinearTrack()
    local = torch.tensor([[0.05, -0.02, 0.03], [0.0, 0.08, -0.01], [0.02, 0.02, 0.02]], dtype=torch.float64)
    tau = torch.tensor([0.0, 0.3, 0.3], dtype=torch.float64)
    world = torch.stack([(track.pose_at(float(t)) @ torch.cat([p, p.new_ones(1)]))[:3] for p, t in zip(local, tau)])
    back, inverse = world_to_object(world, tau, track)
    assert torch.allclose(back, local, atol=1e-12)
    assert inverse.tolist() == [0, 1, 1]
    assert inside_box(back, track.box, 0.0).all() and not inside_box(back + 0.2, track.box, 0.05).any()


def test_object_depth_goes_to_the_object_grid_in_object_coordinates_and_static_depth_to_the_static_grid():
    field = small_object_field()
    tau = 0.4
    T = LinearTrack().pose_at(tau)
    on_object = torch.tensor([[0.07, 0.0, 0.0], [-0.07, 0.01, 0.0]], dtype=torch.float64)
    world_obj = (on_object @ T[:3, :3].T + T[:3, 3]).float()
    floor = torch.tensor([[2.0, 2.0, 0.0], [2.3, 2.0, 0.0]])
    stray = torch.tensor([[-3.0, 0.0, 1.0]])  # a moving point no object claims
    points = torch.cat([world_obj, floor, stray])
    dynamic = torch.tensor([True, True, False, False, True])
    field.allocate(points, dynamic, tau, dilation=0)
    slot = field.slots[1]
    assert slot.tau0 == pytest.approx(tau)
    assert slot.field.grid.contains(on_object.float()).all()  # object frame
    assert not slot.field.grid.contains(world_obj).any()
    assert field.grid.contains(floor).all()
    assert not field.grid.contains(world_obj).any() and not field.grid.contains(stray).any()  # static grid: static depth only
    assert int(field.grid.voxel_hits.sum()) == 2 and field.grid.dynamic_keys.numel() == 0


def test_unclaimed_moving_depth_stays_with_a_static_field_that_has_time():
    field = small_object_field(time=True)
    field.allocate(torch.tensor([[-3.0, 0.0, 1.0]]), torch.tensor([True]), 0.0, dilation=0)
    assert field.grid.contains(torch.tensor([[-3.0, 0.0, 1.0]])).all() and field.grid.dynamic_keys.numel() == 1


def test_composition_is_the_object_field_inside_its_box_where_smaller_and_static_outside():
    field = small_object_field()
    tau = 0.2
    T = LinearTrack().pose_at(tau)
    local = torch.tensor([[0.02, 0.01, 0.0]], dtype=torch.float64)
    world = (local @ T[:3, :3].T + T[:3, 3]).float()
    field.allocate(world, torch.tensor([True]), tau, dilation=0)
    outside = torch.tensor([[5.0, 5.0, 5.0]])
    field.allocate(outside, torch.tensor([False]), tau, dilation=0)
    pts = torch.cat([world, outside])
    taus = torch.full((2,), tau)
    with torch.no_grad():
        out = field(pts, taus)
        obj = field.slots[1].field(local.float(), torch.zeros(1))
    assert out.valid.all()
    assert out.sdf[0] == pytest.approx(float(obj.sdf[0])) and torch.allclose(out.rgb[0], obj.rgb[0])
    with static_only(field):
        static = field(pts, taus)
    assert not static.valid[0] and out.sdf[1] == pytest.approx(float(static.sdf[1]))
    # The parts of the composition: the static field's SDF, and the object's where it is valid (NaN elsewhere).
    assert out.parts is not None and static.parts is None
    assert torch.allclose(out.parts[:, 0], static.sdf) and out.parts[0, 1] == pytest.approx(float(obj.sdf[0]))
    assert torch.isnan(out.parts[1, 1])
    # Unobserved at that time: the object is not placed, the static field alone answers.
    field.set_tracks({1: LinearTrack(seen=(5.0, 6.0))})
    assert not field(pts, taus).valid[0]


def test_the_object_residual_deformation_is_zero_at_its_first_time():
    field = small_object_field()
    tau = 0.7
    T = LinearTrack().pose_at(tau)
    world = (torch.tensor([[0.0, 0.0, 0.0]], dtype=torch.float64) @ T[:3, :3].T + T[:3, 3]).float()
    field.allocate(world, torch.tensor([True]), tau, dilation=0)
    deformation = field.slots[1].field.deformation
    torch.nn.init.normal_(deformation.out.weight)  # as after training
    with torch.no_grad():
        assert float(field(world, torch.full((1,), tau)).offset_sq[0]) == 0.0
    later = LinearTrack().pose_at(tau + 0.3)
    moved = (torch.tensor([[0.0, 0.0, 0.0]], dtype=torch.float64) @ later[:3, :3].T + later[:3, 3]).float()
    with torch.no_grad():
        assert float(field(moved, torch.full((1,), tau + 0.3)).offset_sq[0]) > 0


def test_an_object_fields_time_code_tells_apart_states_that_the_static_fields_code_shares():
    """field's default code repeats every 2 s of τ; an object's (object_field.time_lowest_octave)
    only after 16 s, so a deforming object's states 2 s or 8 s apart get their own codes."""
    static = FieldConfig()
    own = ObjectFieldConfig().object_config(static)
    assert TimeVaryingField(own).time_lowest_octave == own.time_lowest_octave == -3
    tau = torch.tensor([1.0, 3.0, 9.0])
    shared = time_encoding(tau, static.time_frequencies, static.time_lowest_octave)[:, 1:]  # the periodic part
    assert torch.allclose(shared[0], shared[1], atol=1e-5) and torch.allclose(shared[0], shared[2], atol=1e-5)
    code = time_encoding(tau, own.time_frequencies, own.time_lowest_octave)[:, 1:]
    assert float((code[0] - code[1]).norm()) > 0.5 and float((code[0] - code[2]).norm()) > 0.5


def test_object_fields_join_the_map_optimiser_and_learn():
    field = small_object_field()
    optimizer = torch.optim.Adam([{"params": [field.grid.embeddings], "lr": 1e-2}], foreach=True)
    attach_optimizer(field, optimizer, MappingConfig())
    tau = 0.1
    T = LinearTrack().pose_at(tau)
    world = (torch.rand(50, 3, dtype=torch.float64) * 0.1 @ T[:3, :3].T + T[:3, 3]).float()
    field.allocate(world, torch.ones(50, dtype=torch.bool), tau, dilation=0)
    assert len(optimizer.param_groups) == 3
    names = [p for g in optimizer.param_groups[1:] for p in g["params"]]
    assert names[0] is field.slots[1].field.grid.embeddings
    before = field.slots[1].field.grid.embeddings.detach().clone()
    loss = field(world, torch.full((50,), tau)).sdf.pow(2).sum()
    optimizer.zero_grad()
    loss.backward()
    optimizer.step()
    assert not torch.equal(before, field.slots[1].field.grid.embeddings.detach())
    # Object parameters stay out of the static field's state (checkpoints load as a TimeVaryingField).
    assert all(not k.startswith("slots") for k in field.state_dict())


def test_build_field_chooses_by_name():
    assert type(build_field(FieldConfig())) is TimeVaryingField
    field = build_field(FieldConfig(name="objects", time=False), ObjectFieldConfig(voxel_size=0.03))
    assert isinstance(field, ObjectField) and not field.time and field.object_cfg.voxel_size == 0.03


def test_the_oracle_is_the_gt_object_pose_in_the_first_camera_frame():
    from data_modules.sequence import SequenceView
    from data_modules.synthetic import SyntheticSequence

    seq = SyntheticSequence("orbit_ball", seed=1, num_frames=10, width=32, height=24, cache_dir=None)
    view = SequenceView(seq, stride=2)
    tracks = ground_truth_tracks(view, time_scale=2.0)
    t = float(view.timestamps[3])
    tau = (t - float(view.timestamps[0])) * 2.0
    expected = torch.linalg.inv(seq.camera_pose(0)) @ seq.object_poses(t)["ball"]
    assert torch.allclose(tracks[1].pose_at(tau), expected, atol=1e-12)
    radius = float(seq.dynamic_box(0.0, "ball")[1][0])
    assert np.allclose(tracks[1].box.numpy(), [[-radius] * 3, [radius] * 3])
    assert tracks[1].observed_near(tau, 0.0)


def test_the_oracle_needs_gt_object_poses():
    class NoObjects:
        name = "tum"
        timestamps = [0.0]

    with pytest.raises(ConfigError, match="no ground-truth object poses"):
        ground_truth_tracks(NoObjects(), 1.0)
