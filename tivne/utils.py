"""Process-level CPU settings measured to matter on small CPUs: threads and the glibc allocator."""

from __future__ import annotations

import contextlib
import ctypes
import ctypes.util
import signal
import threading
from collections.abc import Iterator

import torch
from lightning.pytorch import Callback

from tivne.settings import ConfigError

# glibc mallopt parameters
_M_TRIM_THRESHOLD = -1
_M_TOP_PAD = -2
_M_MMAP_MAX = -4


def tune_allocator() -> bool:
    """Keep freed activations in the heap instead of mmap/munmap-ing them every step.

    Measured 1.1-3x faster optimiser steps on CPU for multi-MB activations; a no-op off glibc.
    """
    name = ctypes.util.find_library("c")
    if name is None:
        return False
    try:
        libc = ctypes.CDLL(name)
        ok = libc.mallopt(_M_MMAP_MAX, 0) and libc.mallopt(_M_TRIM_THRESHOLD, 2**31 - 1) and libc.mallopt(_M_TOP_PAD, 256 << 20)
        return bool(ok)
    except (OSError, AttributeError):
        return False


def configure_runtime(threads: int | None = None, allocator: bool = True) -> dict[str, object]:
    """Set torch's thread count (None = leave it) and the allocator; returns what was applied.

    (OpenMP's wait policy is set where it takes effect: in ``tivne/__init__.py``, before torch loads.)
    """
    if threads:
        torch.set_num_threads(int(threads))
    return {"threads": torch.get_num_threads(), "allocator_tuned": tune_allocator() if allocator else False}


@contextlib.contextmanager
def torch_threads(threads: int | None) -> Iterator[None]:
    """torch's intra-op threads of the calling thread set to ``threads`` for the block (None: as they
    are), then set back."""
    before = torch.get_num_threads()
    if threads and threads != before:
        torch.set_num_threads(int(threads))
    try:
        yield
    finally:
        if torch.get_num_threads() != before:
            torch.set_num_threads(before)


class RunInterrupted(BaseException):
    """Raised in the main thread by SIGINT / SIGTERM (see :func:`interrupt_signals`).

    A BaseException, like KeyboardInterrupt, so that no ``except Exception`` on the way swallows it;
    not a KeyboardInterrupt, so that Lightning re-raises it instead of exiting on its own.
    """

    def __init__(self, signum: int) -> None:
        self.signum = int(signum)
        super().__init__(signal.Signals(self.signum).name)

    @property
    def exit_code(self) -> int:
        """128 + the signal number (130 for SIGINT, 143 for SIGTERM), as a shell reports it."""
        return 128 + self.signum


# A signal that arrives inside :func:`deferred_interrupts` waits here until the block ends.
_deferral: dict[str, int | None] = {"depth": 0, "pending": None}


@contextlib.contextmanager
def interrupt_signals(signums: tuple[int, ...] = (signal.SIGINT, signal.SIGTERM)):
    """Within the block, the given signals raise :class:`RunInterrupted` (the previous handlers
    come back afterwards) -- at once, or at the end of a :func:`deferred_interrupts` block;
    outside the main thread this is a no-op."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def handler(signum, frame):
        if _deferral["depth"] and _deferral["pending"] is None:
            _deferral["pending"] = signum  # the block ends first; a second signal does not wait
            return
        raise RunInterrupted(signum)

    previous = {s: signal.signal(s, handler) for s in signums}
    _installed.update({s: handler for s in signums})
    try:
        yield
    finally:
        for s, h in previous.items():
            _installed.pop(s, None)
            signal.signal(s, h)


# The handlers :func:`interrupt_signals` installed, while its block runs.
_installed: dict[int, object] = {}


def reinstall_interrupt_signals() -> list[int]:
    """Put :func:`interrupt_signals`' handlers back in place of whatever replaced them (Lightning's
    ``Trainer.fit`` wraps SIGTERM in its own handler, which flags the trainer before ours runs and
    ends the fit loop with its own SystemExit); returns the signals re-installed. Main thread only."""
    if threading.current_thread() is not threading.main_thread():
        return []
    for signum, handler in _installed.items():
        signal.signal(signum, handler)
    return list(_installed)


class InterruptSignalsFirst(Callback):
    """Lightning callback: at ``on_train_start`` -- after ``Trainer.fit`` installed its SIGTERM
    handler, before the first frame -- TivNe's handlers win again (:func:`reinstall_interrupt_signals`);
    Lightning restores them itself when fit ends."""

    def on_train_start(self, trainer, pl_module) -> None:
        reinstall_interrupt_signals()


@contextlib.contextmanager
def deferred_interrupts() -> Iterator[None]:
    """Within the block, a first SIGINT / SIGTERM (under :func:`interrupt_signals`) is held until
    the block ends and raised there, so the state it leaves is whole (one frame of a run: a
    checkpoint written on the interruption can be resumed); a second one is raised at once."""
    _deferral["depth"] += 1
    try:
        yield
    finally:
        _deferral["depth"] -= 1
        pending = _deferral["pending"]
        if not _deferral["depth"] and pending is not None:
            _deferral["pending"] = None
            raise RunInterrupted(pending)


def interrupt_pending() -> bool:
    """Whether a signal is being held by :func:`deferred_interrupts` (the state is mid-step)."""
    return _deferral["pending"] is not None


def require_device(device: str) -> str:
    """``device`` ('cpu', 'cuda', 'cuda:1', 'gpu', 'auto') checked against this torch build; 'gpu'
    means 'cuda' and 'auto' picks one. Raises :class:`ConfigError` (one line) when CUDA is asked
    for and absent."""
    name = str(device).strip().lower()
    if name == "auto":
        return "cuda" if torch.cuda.is_available() else "cpu"
    name = "cuda" + name[3:] if name.startswith("gpu") else name
    if name.startswith("cuda") and not torch.cuda.is_available():
        build = "a CPU-only build" if torch.version.cuda is None else "no CUDA device is visible"
        raise ConfigError(f"device={device}: CUDA is not available (torch {torch.__version__}, {build}); use device=cpu")
    if not (name == "cpu" or name.startswith("cuda")):
        raise ConfigError(f"device={device}: must be cpu, cuda[:N], gpu or auto")
    return name


class RunFailed(RuntimeError):
    """The run went through but its result is not usable (e.g. most frames could not be tracked);
    the message is one line saying why. Commands exit with status 3 on it, after writing what they have."""

    exit_code = 3
