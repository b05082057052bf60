"""A 30-frame smoke run with ``viewer=rerun`` and stdout piped (not a terminal): the log holds plain
progress lines, not carriage-return redraws, and the run's recording reads back with one camera
pose per frame on both timelines, images every output.image_every frames and the final trajectory
equal to trajectory.txt."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from data_modules.tables import read_tum_trajectory
from tivne.viewer.progress import progress_line

REPO = Path(__file__).resolve().parents[3]
SMOKE = ["experiment=smoke", "dataset.width=80", "dataset.height=60", "dataset.cache_dir=null"]


def test_progress_line():
    assert progress_line(20, 60, 3.14159, 1.234, 0) == "frame 20/60  3.14 fps  ATE 1.23 cm  lost 0"
    assert progress_line(7, None, None, None, None) == "frame 7"


@pytest.mark.slow  # one 30-frame subprocess run (~15 s)
def test_a_piped_run_logs_plain_lines_and_its_recording_reads_back(tmp_path):
    pytest.importorskip("rerun")
    from tivne.viewer import entities as E
    from tivne.viewer.readback import read_recording, rows_with

    run_dir = tmp_path / "run"
    out = subprocess.run(
        [sys.executable, "-m", "tivne.train", *SMOKE, "data.max_frames=30", "trainer.progress_bar=true", "viewer=rerun",
         "output.image_every=10", f"hydra.run.dir={run_dir}"],
        capture_output=True, text=True, timeout=400, cwd=REPO, env=dict(os.environ, PYTHONPATH=str(REPO)),
    )
    assert out.returncode == 0, out.stderr[-3000:]
    log = out.stdout + out.stderr
    assert log.count("\r") <= 10, f"{log.count(chr(13))} carriage returns"
    lines = [line for line in out.stdout.splitlines() if line.startswith("frame ")]
    assert [line.split()[1] for line in lines] == [f"{k}/30" for k in range(10, 31, 10)]
    assert all("fps" in line and "lost 0" in line for line in lines)
    assert "warning: viewer" not in out.stderr

    ts, poses = read_tum_trajectory(run_dir / "trajectory.txt")
    rows = read_recording(run_dir / "viewer.rrd")
    cams = rows_with(rows["/" + E.CAMERA], "Transform3D:translation")
    assert [r.frame for r in cams] == list(range(30))
    assert [r.scene_time for r in cams] == pytest.approx([float(t - ts[0]) for t in ts], abs=1e-6)
    assert rows["/" + E.RUN][0].values["t0_s"] == [pytest.approx(float(ts[0]))]
    assert [r.frame for r in rows["/" + E.RGB]] == [0, 10, 20]
    assert [r.frame for r in rows["/" + E.RENDERED_RGB]] == [10, 20]
    assert len(rows_with(rows["/" + E.GT_CAMERA], "Transform3D:translation")) == 30
    final = rows_with(rows["/" + E.TRAJECTORY], "LineStrips3D:strips")[-1]
    assert final.frame == 29
    assert np.allclose(np.asarray(final.values["LineStrips3D:strips"][0]), poses[:, :3, 3].numpy(), atol=1e-5)
    meshes = rows_with(rows["/" + E.MESH], "Mesh3D:vertex_positions")
    assert [r.frame for r in meshes] == [0, 29]  # mesh.times: the first and last frame
    assert rows_with(rows["/" + E.MAP], "Points3D:positions")
