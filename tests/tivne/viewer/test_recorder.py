"""The live recorder on hand-made records, read back with rerun's own reader: entity paths, poses,
timelines, images, map points, meshes; and a viewer error is one warning line, never a failure."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import trimesh

pytest.importorskip("rerun")

from data_modules.frame import Intrinsics  # noqa: E402
from tivne.config import ViewerConfig  # noqa: E402
from tivne.slam.observer import FrameRecord, ObjectState, track_status  # noqa: E402
from tivne.viewer import entities as E  # noqa: E402
from tivne.viewer.readback import mesh_of, pose_of, read_recording, rows_with  # noqa: E402
from tivne.viewer.recorder import Recorder  # noqa: E402

K = Intrinsics(40.0, 40.0, 15.5, 11.5, 32, 24)


def pose(k: int) -> torch.Tensor:
    """A c2w pose with a rotation that is not symmetric (catches a transposed matrix)."""
    a = 0.1 * k
    p = torch.eye(4, dtype=torch.float64)
    p[:3, :3] = torch.tensor([[math.cos(a), -math.sin(a), 0.0], [math.sin(a), math.cos(a), 0.0], [0.0, 0.0, 1.0]])
    p[:3, 3] = torch.tensor([0.1 * k, -0.05 * k, 0.02 * k])
    return p


def record(k: int, status: str = "tracked", **kw) -> FrameRecord:
    rgb = torch.full((24, 32, 3), 0.5)
    depth = torch.full((24, 32), 1.5)
    return FrameRecord(k, 10.0 + k / 10, k / 10, pose(k), pose(k) @ pose(1), rgb, depth, depth > 2, status, k % 2 == 0,
                       render=lambda s: (rgb[::s, ::s], depth[::s, ::s]), **kw)


def test_a_recording_reads_back_with_poses_times_images_map_and_meshes(tmp_path):
    rec = Recorder(ViewerConfig(kind="rerun", image_every=2, trajectory_every=2, map_every=1, map_points=7), tmp_path, K)
    box = ObjectState(pose(3).float(), torch.tensor([0.1, 0.2, 0.3]))
    for k in range(6):
        if k % 3 == 0:
            rec.on_map(k, lambda: torch.arange(60, dtype=torch.float32).reshape(20, 3))
        rec.on_frame(record(k, "lost" if k == 4 else "first" if k == 0 else "tracked", objects={"cube": box}))
    rec.on_mesh(10.3, trimesh.creation.box())
    rec.on_finish([10.0 + k / 10 for k in range(6)], torch.stack([pose(k) for k in range(6)]))
    rec.close()
    rows = read_recording(tmp_path / "viewer.rrd")
    for entity in (E.CAMERA, E.GT_CAMERA, E.RGB, E.DEPTH, E.MASK, E.RENDERED_RGB, E.TRAJECTORY, E.GT_TRAJECTORY, E.KEYFRAMES,
                   E.MAP, E.MESH, E.STATUS, E.LOST, f"{E.OBJECTS}/cube"):
        assert "/" + entity in rows, entity
    cams = rows_with(rows["/" + E.CAMERA], "Transform3D:translation")
    assert [r.frame for r in cams] == list(range(6))
    assert [r.scene_time for r in cams] == pytest.approx([k / 10 for k in range(6)])
    for r in cams:
        assert np.allclose(pose_of(r), pose(r.frame).numpy(), atol=1e-6)
    # GT in the SLAM frame: tied at frame 0, so the GT camera is est @ (pose(1)) mapped by est0 @ gt0^-1
    gt = rows_with(rows["/" + E.GT_CAMERA], "Transform3D:translation")
    tie = pose(0).numpy() @ np.linalg.inv((pose(0) @ pose(1)).numpy())
    assert np.allclose(pose_of(gt[3]), tie @ (pose(3) @ pose(1)).numpy(), atol=1e-5)
    assert [r.frame for r in rows["/" + E.RGB]] == [0, 2, 4]
    assert [r.frame for r in rows["/" + E.RENDERED_RGB]] == [2, 4]  # frame 0 has no map to render yet
    assert [r.frame for r in rows["/" + E.MAP]] == [0, 3] and len(rows["/" + E.MAP][0].values["Points3D:positions"]) == 7
    assert [r.frame for r in rows["/" + E.STATUS]] == [4]
    assert [r.values["Scalars:scalars"][0] for r in rows["/" + E.LOST]] == [0, 0, 0, 0, 1, 0]
    assert len(rows["/" + E.KEYFRAMES][-1].values["Points3D:positions"]) == 3
    (mesh,) = rows["/" + E.MESH]
    assert mesh.frame == 3 and mesh.scene_time == pytest.approx(0.3)
    verts, faces = mesh_of(mesh)
    assert verts.shape == (8, 3) and faces.shape == (12, 3)
    final = rows_with(rows["/" + E.TRAJECTORY], "LineStrips3D:strips")[-1]
    assert final.frame == 5 and np.allclose(final.values["LineStrips3D:strips"][0], [pose(k)[:3, 3].numpy() for k in range(6)], atol=1e-6)


def test_a_viewer_error_is_one_warning_line_and_the_run_goes_on(tmp_path, capsys):
    rec = Recorder(ViewerConfig(kind="rerun", image_every=1), tmp_path, K)
    bad = FrameRecord(1, 0.1, 0.1, pose(1), None, torch.zeros(3), torch.zeros(3), None, "tracked", False)  # not an image
    rec.on_frame(record(0))
    rec.on_frame(bad)
    rec.on_frame(record(2))  # off: ignored, no second line
    rec.on_mesh(0.2, trimesh.creation.box())
    rec.close()
    lines = [line for line in capsys.readouterr().err.splitlines() if line.startswith("warning:")]
    assert len(lines) == 1 and "viewer off" in lines[0]
    assert [r.frame for r in rows_with(read_recording(tmp_path / "viewer.rrd")["/" + E.CAMERA], "Transform3D:translation")] == [0, 1]


def test_a_recording_that_cannot_be_opened_is_one_warning_line(tmp_path, capsys):
    (tmp_path / "file").write_text("")
    rec = Recorder(ViewerConfig(kind="rerun"), tmp_path / "file" / "run", K)  # a file where the folder should be
    rec.on_frame(record(0))
    rec.close()
    err = capsys.readouterr().err
    assert err.count("warning:") == 1 and "could not open the recording" in err


def test_track_status_reads_the_typed_tracking_result():
    from types import SimpleNamespace

    from tivne.slam.tracking import TrackStatus

    def report(index, status):
        return SimpleNamespace(index=index, track=SimpleNamespace(status=status))

    assert track_status(report(0, TrackStatus.TRACKED)) == "first"
    assert track_status(report(3, TrackStatus.TRACKED)) == "tracked" and track_status(report(3, TrackStatus.RECOVERED)) == "tracked"
    assert track_status(report(3, TrackStatus.NO_DEPTH)) == "untracked"
    assert track_status(report(3, TrackStatus.LOST)) == "lost"


def test_decimate_keeps_at_most_the_limit():
    pts = np.arange(300, dtype=np.float32).reshape(100, 3)
    assert len(E.decimate(pts, 30)) <= 30 and len(E.decimate(pts, 30)) >= 25
    assert len(E.decimate(pts, 1000)) == 100 and len(E.decimate(pts, 0)) == 0
