"""One writer per run folder (tivne.runlock): a second run is refused naming the holder's pid; a
lock left by a dead process is taken over; two real runs started at once into one folder."""

from __future__ import annotations

import json
import multiprocessing
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml

from tivne import runlock
from tivne.runlock import LOCK_NAME, RunLocked, acquire, is_held, release, run_lock

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO / "tests"))
from cli_worker import end  # noqa: E402


def _hold(run: str, held) -> None:
    acquire(run)
    held.set()
    time.sleep(60)


def start_holder(run: Path) -> multiprocessing.Process:
    """Another process holding ``run``'s lock: forked from this one, so it starts without importing
    torch and Lightning again (a new interpreter spends ~10 s on that)."""
    ctx = multiprocessing.get_context("fork")
    held = ctx.Event()
    holder = ctx.Process(target=_hold, args=(str(run), held), daemon=True)
    holder.start()
    assert held.wait(60), "the holder did not take the lock"
    return holder


def test_a_second_process_is_refused_naming_the_holder(tmp_path):
    run = tmp_path / "run"
    holder = start_holder(run)
    try:
        with pytest.raises(RunLocked, match=rf"another run \(pid {holder.pid}\) is writing into this folder"):
            acquire(run)
        assert not is_held(run)
    finally:
        holder.kill()
        holder.join()
    with run_lock(run):  # its holder is dead: the kernel dropped the flock, the file is stale
        assert (run / LOCK_NAME).read_text().strip() == str(os.getpid())
    assert not (run / LOCK_NAME).exists()


def test_stale_lock_file_of_a_dead_pid_is_taken_over(tmp_path):
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    (tmp_path / LOCK_NAME).write_text(f"{dead.pid}\n")
    with run_lock(tmp_path):
        assert is_held(tmp_path)
    assert not is_held(tmp_path) and not (tmp_path / LOCK_NAME).exists()


def test_holds_are_counted_and_a_folder_made_by_the_lock_goes_when_empty(tmp_path):
    run = tmp_path / "new"
    acquire(run)
    acquire(run)  # the Hydra callback and run() in one process
    release(run)
    assert is_held(run) and (run / LOCK_NAME).exists()
    release(run)
    assert not is_held(run) and not run.exists()


def test_lock_in_a_read_only_folder_names_the_folder(tmp_path):
    if os.geteuid() == 0:
        pytest.skip("root writes through mode bits")
    tmp_path.chmod(0o555)
    try:
        with pytest.raises(PermissionError) as info:
            acquire(tmp_path)
        assert info.value.filename == str(tmp_path)
    finally:
        tmp_path.chmod(0o755)
    assert runlock._HELD == {}


def start(run_dir: Path, *extra: str) -> subprocess.Popen:
    args = ["experiment=smoke", "dataset.cache_dir=null", "dataset.width=80", "dataset.height=60", "dataset.num_frames=10",
            "data.max_frames=10", "trainer.progress_bar=false", f"hydra.run.dir={run_dir}", *extra]
    env = dict(os.environ, PYTHONUNBUFFERED="1", OMP_NUM_THREADS="1")
    return subprocess.Popen([sys.executable, "-m", "tivne.train", *args], cwd=REPO, env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)


def locked_by(run: Path, procs: dict[int, subprocess.Popen]) -> int | None:
    """The pid of ``procs`` written in ``run``'s lock file (None while there is none)."""
    try:
        text = (run / LOCK_NAME).read_text().strip()
    except FileNotFoundError:
        return None
    return int(text) if text.isdigit() and int(text) in procs else None


def test_two_runs_into_one_folder_the_second_is_refused_the_first_is_whole(tmp_path):
    """Two runs started at once (each spends ~10 s starting its interpreter and importing torch and
    Lightning, which two cores do side by side): the first to take the folder is "first", whichever
    it is, the other "second"; each run's own override tells the two apart in the folder."""
    run = tmp_path / "run"
    marked = [(start(run, marker), marker) for marker in ("output.image_every=0", "output.image_every=7")]
    procs = {proc.pid: proc for proc, _ in marked}
    try:
        deadline = time.monotonic() + 240
        while (holder := locked_by(run, procs)) is None:  # the first holds the folder
            assert any(proc.poll() is None for proc in procs.values()), [proc.communicate()[1][-2000:] for proc in procs.values()]
            assert time.monotonic() < deadline, "no run took the folder in time"
            time.sleep(0.1)
        (first, first_marker), (second, second_marker) = marked if marked[0][0].pid == holder else marked[::-1]
        # Stopped while it holds the folder, so the second meets the lock however fast this machine runs the first.
        os.kill(first.pid, signal.SIGSTOP)
        try:
            _, err2 = second.communicate(timeout=240)
        finally:
            os.kill(first.pid, signal.SIGCONT)
        _, err1 = first.communicate(timeout=400)
    finally:
        for proc in procs.values():
            end(proc)
    errors = [line for line in err2.splitlines() if line.startswith("error:")]
    assert second.returncode == 2 and "Traceback" not in err2, err2[-2000:]
    assert len(errors) == 1 and f"another run (pid {first.pid}) is writing into this folder" in errors[0], err2[-2000:]
    assert first.returncode == 0, err1[-2000:]
    metrics = json.loads((run / "metrics.json").read_text())
    assert metrics["complete"] is True and metrics["frames"] == 10
    overrides = yaml.safe_load((run / ".hydra" / "overrides.yaml").read_text())
    assert first_marker in overrides and second_marker not in overrides
    events = [p.name for p in (run / "tb").rglob("events.out.tfevents.*")]
    assert events and all(f".{first.pid}." in name for name in events), events  # written by the first run only
    assert len([line for line in (run / "trajectory.txt").read_text().splitlines() if not line.startswith("#")]) == 10
    assert not (run / LOCK_NAME).exists()
