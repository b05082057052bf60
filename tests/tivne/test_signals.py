"""SIGINT / SIGTERM in the middle of a run: results written, metrics marked incomplete, exit 130 / 143."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from data_modules.tables import read_tum_trajectory
from tivne.slam.checkpoint import load_checkpoint

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO / "tests"))
from cli_worker import end  # noqa: E402


def start_run(run_dir: Path) -> subprocess.Popen:
    args = [
        "experiment=smoke", "dataset.cache_dir=null", "dataset.width=80", "dataset.height=60", "dataset.num_frames=400",
        "data.max_frames=400", "output.save_every=1", "trainer.progress_bar=false", f"hydra.run.dir={run_dir}",
    ]
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    return subprocess.Popen([sys.executable, "-m", "tivne.train", *args], cwd=REPO, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def wait_for_frames(run_dir: Path, proc: subprocess.Popen, frames: int, timeout: float = 240.0) -> None:
    path = run_dir / "trajectory.txt"
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        assert proc.poll() is None, proc.communicate()[1][-2000:]
        if path.is_file() and len(path.read_text().splitlines()) > frames:
            return
        time.sleep(0.2)
    proc.kill()
    pytest.fail("the run did not reach the frame count in time")


SIGNALS = {signal.SIGTERM: 143, signal.SIGINT: 130}


@pytest.fixture(scope="module")
def signalled(tmp_path_factory) -> dict[int, tuple[Path, subprocess.Popen, str]]:
    """One run per signal, started together (each spends ~10 s starting its interpreter, torch and
    Lightning: two cores do both at once) and each sent its signal once it has 4 frames; {signal:
    (run dir, ended process, its stderr)}."""
    dirs = {signum: tmp_path_factory.mktemp(signal.Signals(signum).name) / "run" for signum in SIGNALS}
    runs = {signum: (run_dir, start_run(run_dir)) for signum, run_dir in dirs.items()}
    try:
        for signum, (run_dir, proc) in runs.items():
            wait_for_frames(run_dir, proc, 4)
            proc.send_signal(signum)
        return {signum: (run_dir, proc, proc.communicate(timeout=120)[1]) for signum, (run_dir, proc) in runs.items()}
    finally:
        for _, proc in runs.values():
            end(proc)


@pytest.mark.parametrize("signum, code", list(SIGNALS.items()))
def test_signal_writes_partial_results_and_exits_nonzero(signalled, signum, code):
    run_dir, proc, stderr = signalled[signum]
    assert proc.returncode == code, stderr[-2000:]
    assert "Traceback" not in stderr and "interrupted by " + signal.Signals(signum).name in stderr
    metrics = json.loads((run_dir / "metrics.json").read_text())
    assert metrics["complete"] is False and signal.Signals(signum).name in metrics["complete_reason"]
    ts, _ = read_tum_trajectory(run_dir / "trajectory.txt")
    assert len(ts) == metrics["frames"] >= 4
    _, meta = load_checkpoint(run_dir / "checkpoints" / "slam.pt")
    assert len(meta["timestamps"]) == len(ts)
    assert not list(run_dir.rglob("*.tmp"))
