"""One writer per run folder: a lock held for the life of a run.

``tivne.train`` takes ``<run_dir>/.tivne.lock`` before Hydra writes the folder's ``.hydra/`` and holds
it until the process ends; a second run into the same folder is refused with one line naming the
pid that holds it (:class:`RunLocked`), so two runs never interleave their logs, metrics and
checkpoints. The lock is an ``flock`` on that file: the kernel drops it with its holder whatever
the way out (exit, exception, SIGKILL), so a file left by a dead process is a stale lock and is
simply taken over. A process releases its locks at exit (``atexit``); the file is removed then.
Within one process the lock is counted (the Hydra callback and :func:`tivne.train.run` both take it).
"""

from __future__ import annotations

import atexit
import contextlib
import fcntl
import os
import time
from collections.abc import Iterator
from pathlib import Path

from data_modules.frame import DatasetError

LOCK_NAME = ".tivne.lock"


class RunLocked(DatasetError):
    """Another live process writes into this run folder (``str()``: one line naming its pid)."""


# lock path -> [file descriptor, hold count, folder created by the lock]
_HELD: dict[Path, list] = {}


def lock_path(run_dir: str | Path) -> Path:
    return Path(run_dir).absolute() / LOCK_NAME


def holder_pid(path: Path) -> str:
    """The pid written in a lock file ("unknown" while its holder has not written it yet)."""
    for _ in range(3):
        try:
            text = path.read_text().strip()
        except OSError:
            text = ""
        if text.isdigit():
            return text
        time.sleep(0.05)
    return "unknown"


def _open_locked(path: Path, run_dir: str | Path) -> int:
    """A descriptor of ``path`` holding its flock, or :class:`RunLocked`. Retries when the file it
    locked was removed meanwhile by a releasing holder (the lock must be on the file at the path)."""
    while True:
        try:
            fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o644)
        except OSError as exc:  # a read-only folder: name the folder, as the other checks do
            raise OSError(exc.errno, exc.strerror, str(run_dir)) from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(fd)
            raise RunLocked(run_dir, f"another run (pid {holder_pid(path)}) is writing into this folder; "
                                     "wait for it to end or choose another hydra.run.dir") from None
        try:
            same = os.fstat(fd).st_ino == os.stat(path).st_ino
        except FileNotFoundError:
            same = False
        if same:
            return fd
        os.close(fd)


def check_free(run_dir: str | Path) -> None:
    """Raise :class:`RunLocked` when another process holds the lock of ``run_dir``; changes nothing
    (a probe: the lock file is opened read-only, never created)."""
    path = lock_path(run_dir)
    if path in _HELD:
        return
    try:
        fd = os.open(path, os.O_RDONLY | os.O_CLOEXEC)
    except OSError:
        return  # no lock file (or none readable): nobody holds it
    try:
        fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
    except BlockingIOError:
        raise RunLocked(run_dir, f"another run (pid {holder_pid(path)}) is writing into this folder; "
                                 "wait for it to end or choose another hydra.run.dir") from None
    finally:
        os.close(fd)


def acquire(run_dir: str | Path) -> Path:
    """Take (or count once more) the lock of ``run_dir``, creating the folder when needed."""
    path = lock_path(run_dir)
    if path in _HELD:
        _HELD[path][1] += 1
        return path
    created = not path.parent.exists()
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OSError(exc.errno, exc.strerror, str(run_dir)) from None
    fd = _open_locked(path, run_dir)
    os.ftruncate(fd, 0)
    os.write(fd, f"{os.getpid()}\n".encode())
    _HELD[path] = [fd, 1, created]
    return path


def release(run_dir: str | Path, force: bool = False) -> None:
    """Count one hold off (all of them with ``force``); the last removes the file (and the folder
    when the lock made it and nothing else was written there) and drops the flock."""
    path = lock_path(run_dir)
    held = _HELD.get(path)
    if held is None:
        return
    held[1] = 0 if force else held[1] - 1
    if held[1] > 0:
        return
    del _HELD[path]
    with contextlib.suppress(OSError):
        path.unlink()  # while still locked: a waiting run then locks a new file, never this one
    os.close(held[0])
    if held[2]:
        with contextlib.suppress(OSError):
            path.parent.rmdir()  # only succeeds when empty


def release_all() -> None:
    for path in list(_HELD):
        release(path.parent, force=True)


def is_held(run_dir: str | Path) -> bool:
    """Whether this process holds the lock of ``run_dir``."""
    return lock_path(run_dir) in _HELD


@contextlib.contextmanager
def run_lock(run_dir: str | Path) -> Iterator[Path]:
    """The lock of ``run_dir`` within the block (see :func:`acquire`)."""
    path = acquire(run_dir)
    try:
        yield path
    finally:
        release(run_dir)


atexit.register(release_all)
