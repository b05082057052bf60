"""An ObjectField's objects through a checkpoint payload and back (tivne/field/object_state.py)."""

from __future__ import annotations

import torch
from test_object_field import LinearTrack, small_object_field

from tivne.config import MappingConfig
from tivne.field.networks import TimeVaryingField
from tivne.field.object_state import RecordedTrack, load_objects_into, objects_payload, restore_objects
from tivne.field.objects import ObjectField, attach_optimizer


def test_objects_survive_the_payload_round_trip():
    field = small_object_field()
    taus = [0.0, 0.1, 0.2, 0.3]
    for tau in taus:
        T = LinearTrack().pose_at(tau)
        local = torch.rand(30, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(1)) * 0.16 - 0.08
        field.allocate((local @ T[:3, :3].T + T[:3, 3]).float(), torch.ones(30, dtype=torch.bool), tau, dilation=0)
    field.allocate(torch.tensor([[3.0, 3.0, 0.0]]), torch.tensor([False]), 0.0, dilation=0)
    payload = objects_payload(field, taus)
    assert objects_payload(TimeVaryingField(), taus) == {}
    kwargs = dict(time=False, voxel_size=0.1, embed_dim=8, capacity=64, hidden_dim=16, init_std=0.5)
    static = TimeVaryingField(**kwargs)
    static.grid.load_sparse_state({k[5:]: v for k, v in field.state_dict().items() if k.startswith("grid.")})
    static.load_state_dict(field.state_dict())
    back = restore_objects(static, payload)
    assert isinstance(back, ObjectField) and back.slots[1].tau0 == field.slots[1].tau0
    assert isinstance(back.tracks[1], RecordedTrack)
    T = LinearTrack().pose_at(0.15)  # between two recorded samples: interpolated on SE(3)
    assert torch.allclose(back.tracks[1].pose_at(0.15), T, atol=1e-3)
    pts = torch.cat([(torch.zeros(1, 3, dtype=torch.float64) @ T[:3, :3].T + T[:3, 3]).float(), torch.tensor([[3.0, 3.0, 0.0]])])
    with torch.no_grad():
        a, b = field(pts, torch.full((2,), 0.2)), back(pts, torch.full((2,), 0.2))
    assert a.valid.all() and torch.allclose(a.sdf, b.sdf) and torch.allclose(a.rgb, b.rgb)
    assert restore_objects(static, {}) is static


def test_a_resumed_object_field_lines_up_with_the_saved_optimiser():
    def built():
        field = small_object_field()
        opt = torch.optim.Adam([{"params": [field.grid.embeddings]}], foreach=True)
        attach_optimizer(field, opt, MappingConfig())
        return field, opt

    field, opt = built()
    T = LinearTrack().pose_at(0.2)
    pts = (torch.rand(40, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(2)) * 0.1 @ T[:3, :3].T + T[:3, 3]).float()
    field.allocate(pts, torch.ones(40, dtype=torch.bool), 0.2, dilation=0)
    field(pts, torch.full((40,), 0.2)).sdf.sum().backward()
    opt.step()
    payload = objects_payload(field)
    fresh, fresh_opt = built()
    load_objects_into(fresh, payload)
    fresh_opt.load_state_dict(opt.state_dict())  # raises when the groups do not line up
    assert len(fresh_opt.param_groups) == 3 and fresh.slots[1].tau0 == field.slots[1].tau0
    with torch.no_grad():
        assert torch.allclose(fresh(pts, torch.full((40,), 0.2)).sdf, field(pts, torch.full((40,), 0.2)).sdf)
