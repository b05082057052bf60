"""Progress outside a terminal: one plain line every ``trainer.log_every`` frames instead of a
carriage-return progress bar (a log file or CI keeps readable lines, not one long redrawn line)."""

from __future__ import annotations

import sys
import time
from typing import Any, TextIO

import lightning as L


def progress_line(done: int, total: int | None, fps: float | None, ate_cm: float | None, lost: int | None) -> str:
    """``frame 20/60  1.85 fps  ATE 1.23 cm  lost 0`` (unknown parts left out)."""
    parts = [f"frame {done}/{total}" if total else f"frame {done}"]
    if fps is not None:
        parts.append(f"{fps:.2f} fps")
    if ate_cm is not None:
        parts.append(f"ATE {ate_cm:.2f} cm")
    if lost is not None:
        parts.append(f"lost {lost}")
    return "  ".join(parts)


class PlainProgress(L.Callback):
    """Prints :func:`progress_line` every ``every`` frames and after the last one. fps: frames per
    second over the last ``every`` frames; ATE: the latest the run logged (``ate_cm``); lost: frames
    whose tracking was lost or impossible (the tracker's counts, where the module has a loop)."""

    def __init__(self, every: int = 10, stream: TextIO | None = None) -> None:
        self.every = int(every)
        self.stream = stream
        self.last: tuple[int, float] | None = None

    def on_train_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self.last = (0, time.perf_counter())

    def on_train_batch_end(self, trainer: L.Trainer, pl_module: L.LightningModule, outputs: Any, batch: Any, batch_idx: int) -> None:
        total = trainer.num_training_batches if isinstance(trainer.num_training_batches, int) else None
        done = batch_idx + 1
        if done % self.every and done != total:
            return
        now = time.perf_counter()
        start_idx, start_t = self.last or (0, now)
        fps = (done - start_idx) / (now - start_t) if now > start_t and done > start_idx else None
        self.last = (done, now)
        ate = trainer.callback_metrics.get("ate_cm")
        loop = getattr(pl_module, "loop", None)  # the SLAM loop the module adapts: its tracker counts
        counts = getattr(getattr(loop, "tracker", None), "counts", None)
        lost = None if counts is None else int(getattr(counts, "lost", 0)) + int(getattr(counts, "without_tracking", 0))
        start = getattr(trainer.datamodule, "start", 0) if trainer.datamodule is not None else 0
        line = progress_line(start + done, None if total is None else start + total, fps, None if ate is None else float(ate), lost)
        print(line, file=self.stream or sys.stdout, flush=True)


def progress_callbacks(trainer_cfg: Any, is_tty: bool) -> list[L.Callback]:
    """The plain-line callback when the bar is asked for but stdout is not a terminal."""
    return [PlainProgress(trainer_cfg.log_every)] if trainer_cfg.progress_bar and not is_tty else []
