"""The run's checkpoint (tivne/slam/checkpoint.py): a restored system continues exactly as the
uninterrupted one; failed writes keep the old file and leave no temporary; unreadable files are one line."""

from __future__ import annotations

import errno
import shutil
import warnings
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir

from data_modules.frame import DatasetError
from tivne.render.rays import View
from tivne.slam.checkpoint import check_resumable, load_checkpoint, read_checkpoint, stored_depth_views
from tivne.slam.keyframes import view_state
from tivne.slam.outputs import RunDirError
from tivne.slam.run import build_system, run

CONF = Path(__file__).resolve().parents[3] / "conf"


def smoke_cfg(*overrides: str):
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        return compose("config", overrides=["experiment=smoke", "dataset.cache_dir=null", *overrides])


def feed(system, frames, start: int) -> None:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # self.log without a Trainer
        for k, frame in enumerate(frames, start):
            system.training_step(frame, k)
        system.flush()  # the module runs one frame behind the stream: the segment's last frame too


@pytest.fixture
def one_thread():
    """One intra-op thread: threaded CPU sums add in an order that changes from run to run."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.mark.parametrize("masks", ["geometric", "dataset"])
def test_a_restored_system_continues_exactly_as_the_uninterrupted_one(tmp_path, tiny_cube, masks, one_thread):
    # field=tivne: a resumed field=objects run is not bit-exact by design (the object tracker's
    # reference pyramids are not saved; its first frame after a restore starts a new reference), see
    # test_a_restored_object_field_run_continues_on_its_tracks.
    cfg = smoke_cfg(f"masks={masks}", "field=tivne", "keyframe.every=2", "output.save_every=0", "output.checkpoint_every=3")
    frames = [tiny_cube[k] for k in range(6)]
    whole = build_system(cfg, tiny_cube.intrinsics, tmp_path / "whole")
    feed(whole, frames[:3], 0)  # the checkpoint after frame 3 ...
    shutil.copy(tmp_path / "whole" / "checkpoints" / "slam.pt", tmp_path / "at3.pt")
    feed(whole, frames[3:], 3)  # ... and the uninterrupted rest

    resumed = build_system(cfg, tiny_cube.intrinsics, tmp_path / "resumed")
    assert resumed.resume_from(read_checkpoint(tmp_path / "at3.pt")) == 3
    resumed.on_train_start()
    r, w = resumed.loop, whole.loop
    assert len(r) == 3 and r.keyframes.frame_ids() == [0, 2] and r.clock == w.clock
    feed(resumed, frames[3:], 3)
    # Bit for bit: on one thread two identical uninterrupted runs are equal too.
    assert torch.equal(r.poses.all(), w.poses.all())
    for name, value in w.field.state_dict().items():
        assert torch.equal(r.field.state_dict()[name], value), name
    assert r.mapper.steps == w.mapper.steps and r.timers.per_frame[:3] == w.timers.per_frame[:3]
    assert torch.equal(r.generator.get_state(), w.generator.get_state())
    assert r.keyframes.frame_ids() == w.keyframes.frame_ids() and r.tracker.reference.frame_id == w.tracker.reference.frame_id
    assert all(a.rgb.dtype == torch.uint8 and torch.equal(a.rgb, b.rgb) for a, b in zip(r.keyframes.records, w.keyframes.records))


def test_a_failed_write_keeps_the_old_checkpoint_and_leaves_no_temporary(tmp_path, tiny_cube, monkeypatch):
    cfg = smoke_cfg("output.save_every=0", "output.checkpoint_every=0")
    system = build_system(cfg, tiny_cube.intrinsics, tmp_path)
    feed(system, [tiny_cube[0], tiny_cube[1]], 0)
    path = system.writer.save_checkpoint(system.loop)
    before = path.read_bytes()
    feed(system, [tiny_cube[2]], 2)

    def full_disk(obj, f, *args, **kwargs):
        f.write(b"partial")
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(torch, "save", full_disk)
    with pytest.raises(OSError) as info:
        system.writer.save_checkpoint(system.loop)
    assert info.value.errno == errno.ENOSPC and info.value.filename == str(path)  # the file asked for, not a temporary
    monkeypatch.setattr(torch, "save", lambda *a, **k: (_ for _ in ()).throw(RuntimeError("PytorchStreamWriter failed")))
    with pytest.raises(RuntimeError):
        system.writer.save_checkpoint(system.loop)
    assert path.read_bytes() == before and sorted(p.name for p in path.parent.iterdir()) == ["slam.pt"]


def test_unreadable_checkpoints_are_one_line(tmp_path, tiny_cube):
    path = tmp_path / "slam.pt"
    with pytest.raises(DatasetError, match="checkpoint not found"):
        load_checkpoint(path)
    path.write_bytes(b"\x00" * 100)
    with pytest.raises(DatasetError, match="not a readable TivNe checkpoint"):
        load_checkpoint(path)
    torch.save({"weights": torch.zeros(3)}, path)
    with pytest.raises(DatasetError, match="not a TivNe checkpoint"):
        read_checkpoint(path)
    system = build_system(smoke_cfg("output.save_every=0"), tiny_cube.intrinsics, tmp_path / "run")
    feed(system, [tiny_cube[0]], 0)
    good = system.writer.save_checkpoint(system.loop, resumable=False)
    field, meta = load_checkpoint(good)  # mesh and evaluate read it
    assert meta["timestamps"] == [0.0] and "resume" not in meta and field.grid.num_voxels > 0
    assert meta["clock"] == system.loop.clock and field.cfg == system.loop.field.cfg  # one source of τ and of the field's settings
    assert meta["depth_views"] is None  # not resumable: no keyframes to carve meshes with
    with pytest.raises(RunDirError, match="holds no resume state"):
        check_resumable(good)
    _, meta = load_checkpoint(system.writer.save_checkpoint(system.loop))  # resumable: its keyframes carve the meshes
    assert [v.frame_id for v in meta["depth_views"].views] == [0] and torch.equal(meta["depth_views"].K, system.loop.K.cpu())
    payload = torch.load(good, weights_only=True)
    torch.save(payload | {"format": 2}, tmp_path / "old.pt")
    with pytest.raises(DatasetError, match="written by another version of TivNe .checkpoint format 2"):
        read_checkpoint(tmp_path / "old.pt")  # an old checkpoint is refused in one line
    good.write_bytes(good.read_bytes()[:-100])
    with pytest.raises(DatasetError, match="not a readable TivNe checkpoint"):
        check_resumable(good)


def test_a_crash_in_the_final_pass_resumes_from_the_checkpoint_before_it(tmp_path, monkeypatch):
    # The cube rendered at 160x120 (shrunk to the smoke runs' 80x60 as the full 640x480 is): ~1 s less a run.
    overrides = ("data.max_frames=4", "output.checkpoint_every=10", "output.save_every=0", "dataset.width=160", "dataset.height=120")
    reference = run(smoke_cfg(*overrides), tmp_path / "reference")

    def crash(*args, **kwargs):
        raise RuntimeError("power cut")

    monkeypatch.setattr("tivne.slam.loop.final_pass", crash)
    with pytest.raises(RuntimeError, match="power cut"):
        run(smoke_cfg(*overrides), tmp_path / "crashed")
    assert not (tmp_path / "crashed" / "metrics.json").exists()
    assert read_checkpoint(tmp_path / "crashed" / "checkpoints" / "slam.pt")["resume"]["position"] == 4
    monkeypatch.undo()
    resumed = run(smoke_cfg(*overrides, "resume=true"), tmp_path / "crashed")  # no frame left: the final pass and the results
    assert resumed["complete"] is True and resumed["frames"] == 4
    assert resumed["ate_rmse_m"] == pytest.approx(reference["ate_rmse_m"], abs=1e-9)
    assert len(list((tmp_path / "crashed" / "meshes").glob("*.ply"))) == 2
    with pytest.raises(RunDirError, match="the run is complete"):
        run(smoke_cfg(*overrides, "resume=true"), tmp_path / "crashed")


def test_a_restored_object_field_run_continues_on_its_tracks(tmp_path, tiny_cube, one_thread):
    """field=objects: the restored loop's object fields are placed by the restored tracker's tracks
    (the field reads the live ones, which a restore replaces); the object's reference keyframe is
    not saved, so the rest matches the uninterrupted run closely, not bit for bit."""
    cfg = smoke_cfg("field=objects", "objects.min_pixels=64", "keyframe.every=2", "output.save_every=0", "output.checkpoint_every=3")
    frames = [tiny_cube[k] for k in range(6)]
    whole = build_system(cfg, tiny_cube.intrinsics, tmp_path / "whole")
    feed(whole, frames[:3], 0)
    shutil.copy(tmp_path / "whole" / "checkpoints" / "slam.pt", tmp_path / "at3.pt")
    feed(whole, frames[3:], 3)
    resumed = build_system(cfg, tiny_cube.intrinsics, tmp_path / "resumed")
    assert resumed.resume_from(read_checkpoint(tmp_path / "at3.pt")) == 3
    resumed.on_train_start()
    r, w = resumed.loop, whole.loop
    assert r.field.tracks is r.objects.tracks and len(r.objects.tracks[1]) == 3 and list(r.field.slots) == [1]
    feed(resumed, frames[3:], 3)
    assert r.field.tracks is r.objects.tracks and list(r.field.slots) == [1]
    ours, theirs = r.objects.tracks[1], w.objects.tracks[1]
    # The first frame after the restore becomes the object's reference, recorded at its predicted pose
    # (the anchor the next poses are measured from), so both runs hold a pose at every frame.
    assert ours.observed_taus() == theirs.observed_taus() and len(ours) == 6
    apart = [float((ours.pose_at(t)[:3, 3] - theirs.pose_at(t)[:3, 3]).norm()) for t in theirs.observed_taus()]
    assert max(apart) < 2e-3, apart
    n, m = r.field.slots[1].field.grid.num_voxels, w.field.slots[1].field.grid.num_voxels
    assert abs(n - m) <= 0.05 * m, (n, m)  # its voxels: where the (slightly different) poses put its depth


def test_a_resumable_checkpoint_hands_its_keyframes_to_mesh_carving_and_an_old_one_nothing():
    view = View(3, 0.1, torch.zeros(4, 5, 3, dtype=torch.uint8), torch.full((4, 5), 2.0), None, torch.eye(4))
    K = torch.tensor([[5.0, 0.0, 2.0], [0.0, 5.0, 2.0], [0.0, 0.0, 1.0]])
    payload = {"extra": {"K": K}, "resume": {"keyframes": {"views": [view_state(view)]}}}
    stored = stored_depth_views(payload)
    assert [v.frame_id for v in stored.views] == [3] and torch.equal(stored.views[0].depth, view.depth) and torch.equal(stored.K, K)
    assert stored_depth_views({"extra": {}, "resume": payload["resume"]}) is None  # written before the intrinsics were kept
    assert stored_depth_views({"extra": {"K": K}, "resume": None}) is None  # not resumable: no keyframes
