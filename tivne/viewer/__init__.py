"""A run as a rerun recording (live: :mod:`tivne.viewer.recorder`; finished: :mod:`tivne.viewer.offline`),
read back with :mod:`tivne.viewer.readback`; and progress lines outside a terminal (:mod:`tivne.viewer.progress`).
rerun-sdk is an optional extra (``pip install -e '.[viewer]'``), imported only when a recording is made."""

from __future__ import annotations

from pathlib import Path

from data_modules.frame import Intrinsics
from tivne.config import ViewerConfig
from tivne.slam.observer import NoObserver, RunObserver
from tivne.viewer.progress import PlainProgress, progress_callbacks

__all__ = ["make_observer", "progress_callbacks", "PlainProgress"]


def make_observer(cfg: ViewerConfig, run_dir: str | Path, intrinsics: Intrinsics, image_every: int) -> RunObserver:
    """The run's observer: a :class:`tivne.viewer.recorder.Recorder` for ``viewer=rerun``, else nobody."""
    if cfg.kind == "none":
        return NoObserver()
    from tivne.viewer.recorder import Recorder

    return Recorder(cfg, run_dir, intrinsics, image_every)
