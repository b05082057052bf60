"""TivNeSLAM: the LightningModule that adapts a :class:`~tivne.slam.loop.SlamLoop` to a Trainer.
``training_step`` is one ``loop.step(frame)``, the periodic writes and the logging of its report;
``on_train_end`` is the final pass and the results. Nothing here owns state of the run."""

from __future__ import annotations

import math
from typing import Any

import lightning as L

from data_modules.frame import Frame
from tivne.field.object_state import load_objects_into
from tivne.slam.checkpoint import load_field_state, set_global_rng_state, to_device
from tivne.slam.loop import SlamLoop
from tivne.slam.results import RunWriter, render_panels
from tivne.slam.state import FrameReport
from tivne.utils import deferred_interrupts


class TivNeSLAM(L.LightningModule):
    """Online dynamic RGB-D SLAM over a stream of :class:`Frame` (batch size 1, time order).

    ``image_every``: log rendered images every n frames (0 = never)."""

    def __init__(self, loop: SlamLoop, writer: RunWriter, image_every: int = 0) -> None:
        super().__init__()
        self.automatic_optimization = False
        self.loop, self.writer, self.image_every = loop, writer, image_every
        self.field = loop.field  # registered: Lightning moves the map to the device
        self.resume_payload: dict[str, Any] | None = None  # restored once the module is on its device
        self.pending_rng: dict[str, Any] | None = None  # set just before the next frame
        self.held: Frame | None = None  # the latest frame from the stream, processed at the next step

    def configure_optimizers(self):
        return self.loop.mapper.optimizer  # registered so Lightning knows the map's optimiser

    def transfer_batch_to_device(self, batch: Frame, device, dataloader_idx: int) -> Frame:
        return batch.to(device)

    # ---- resume ---------------------------------------------------------------------------------
    def resume_from(self, payload: dict[str, Any]) -> int:
        """Continue from a checkpoint payload (:func:`tivne.slam.checkpoint.load_resume_state`) once
        training starts; returns the number of frames it has processed (the stream starts there)."""
        self.resume_payload = payload
        return int(payload["resume"]["position"])

    def on_train_start(self) -> None:
        if self.resume_payload is not None:
            self.pending_rng = restore(self.loop, self.resume_payload)
            self.resume_payload = None

    def _apply_pending_rng(self) -> None:
        # after the data loader has drawn its seed from the global RNG, before the next frame
        if self.pending_rng is not None:
            set_global_rng_state(self.pending_rng)
            self.pending_rng = None

    # ---- the per-frame loop -----------------------------------------------------------------------
    def training_step(self, frame: Frame, batch_idx: int) -> None:
        # One frame behind the stream: the frame that arrives is the next one of the frame processed
        # now, so the loop can track it while it maps (tracking.overlap). A checkpoint's position
        # counts processed frames only, so a resumed stream starts at the held one again.
        self._apply_pending_rng()
        held, self.held = self.held, frame
        if held is not None:
            self._step(held, frame)
        trainer = self._trainer
        if trainer is not None and batch_idx + 1 >= trainer.num_training_batches:
            self.flush()  # the stream's last frame, while the Trainer still takes self.log

    def _step(self, frame: Frame, next_frame: Frame | None, progress: bool = True) -> None:
        # SIGINT / SIGTERM take effect once the frame is whole, its logging too: raised inside TensorBoard's
        # queue.put, a signal left the event writer's task count off and the run ended with a traceback (exit 1).
        with deferred_interrupts():
            report = self.loop.step(frame, next_frame)
            self.writer.after_frame(self.loop, report)
            self.log_report(report, progress)

    def log_report(self, report: FrameReport, progress: bool = True) -> None:
        """Per-frame scalars (against the frame index), every 10th frame the ATE so far, every
        ``image_every`` frames the renders; ``progress``: fps and ATE to the progress bar too."""
        k, scalars = report.index, report.scalars()
        ate = self.loop.ate() if k % 10 == 0 else None
        if ate is not None:
            scalars["eval/ate_rmse_m"] = float(ate.rmse)
        logger = getattr(self.logger, "experiment", None) if self.logger is not None else None
        if logger is not None and hasattr(logger, "add_scalar"):
            for name, value in scalars.items():
                if value is not None and math.isfinite(value):
                    logger.add_scalar(name, value, k)
            if self.image_every and k % self.image_every == 0:
                for name, img in render_panels(self.loop, report.view, stride=2).items():
                    logger.add_image(f"render/{name}", img, k, dataformats="HWC")
        if not progress:
            return
        self.log("fps", 1.0 / max(report.seconds, 1e-6), prog_bar=True, on_step=True, batch_size=1)
        if ate is not None:
            self.log("ate_cm", 100 * float(ate.rmse), prog_bar=True, on_step=True, batch_size=1)

    def flush(self, progress: bool = True) -> None:
        """Process the held frame now, with no next frame (the end of a stream)."""
        held, self.held = self.held, None
        if held is not None:
            self._step(held, None, progress)

    def on_train_end(self) -> None:
        self._apply_pending_rng()
        self.flush(progress=False)  # a stream of unknown length ends here (Lightning takes no self.log now)
        self.writer.finish(self.loop, getattr(self.logger, "experiment", None) if self.logger is not None else None)


def restore(loop: SlamLoop, payload: dict[str, Any]) -> dict[str, Any]:
    """Put ``loop`` (freshly built from the same config, on its device) where the checkpoint
    ``payload`` left it. Returns the global RNG state, to be set just before the next frame (the
    data loader draws from the torch RNG when it starts)."""
    state = payload["resume"]
    load_field_state(loop.field, to_device(payload["field_state"], loop.device))
    load_objects_into(loop.field, payload.get("extra"))  # field=objects: before the optimiser state
    loop.load_state_dict(to_device({k: v for k, v in state.items() if k not in ("rng", "generator")}, loop.device) | {"generator": state["generator"]})
    return state["rng"]
