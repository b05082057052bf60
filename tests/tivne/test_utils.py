"""Runtime settings (tivne/utils.py, tivne/__init__.py)."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

# In a new interpreter: the policy when torch is first imported (read by a finder that then ends the
# process: the rest of the import, Lightning for data_modules, takes ~8 s), or after the package's
# import when that never imports torch.
POLICY_WHEN_TORCH_LOADS = """
import os, sys

class PolicyWhenTorchLoads:
    def find_spec(self, name, path=None, target=None):
        if name == "torch":
            print(os.environ.get("OMP_WAIT_POLICY"), flush=True)
            os._exit(0)

sys.meta_path.insert(0, PolicyWhenTorchLoads())
import {package}
print(os.environ.get("OMP_WAIT_POLICY"))
"""


@pytest.mark.parametrize("package", ["tivne", "data_modules"])
def test_openmp_wait_policy_is_passive_before_torch_loads(package):
    env = {k: v for k, v in os.environ.items() if k != "OMP_WAIT_POLICY"}
    # set by the package's __init__, which runs before anything of it imports torch
    code = POLICY_WHEN_TORCH_LOADS.format(package=package)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.strip() == "PASSIVE"


def test_an_explicit_wait_policy_is_kept():
    env = dict(os.environ, OMP_WAIT_POLICY="ACTIVE")
    out = subprocess.run([sys.executable, "-c", "import tivne, os; print(os.environ['OMP_WAIT_POLICY'])"], capture_output=True, text=True, env=env, timeout=120)
    assert out.stdout.strip() == "ACTIVE"


def test_configure_runtime_sets_threads():
    import torch

    from tivne.utils import configure_runtime

    before = torch.get_num_threads()
    try:
        applied = configure_runtime(threads=1, allocator=False)
        assert applied == {"threads": 1, "allocator_tuned": False} and torch.get_num_threads() == 1
    finally:
        torch.set_num_threads(before)


def test_torch_threads_sets_the_count_for_the_block_and_restores_it():
    import torch

    from tivne.utils import torch_threads

    before = torch.get_num_threads()
    try:
        torch.set_num_threads(2)
        with torch_threads(1):
            assert torch.get_num_threads() == 1
        assert torch.get_num_threads() == 2
        with pytest.raises(RuntimeError), torch_threads(1):
            raise RuntimeError("a failing block restores them too")
        assert torch.get_num_threads() == 2
        with torch_threads(None):
            assert torch.get_num_threads() == 2
    finally:
        torch.set_num_threads(before)


def test_a_signal_inside_deferred_interrupts_waits_for_the_end_of_the_block():
    import signal

    from tivne.utils import RunInterrupted, deferred_interrupts, interrupt_pending, interrupt_signals

    reached = []
    with interrupt_signals(), pytest.raises(RunInterrupted) as info:
        with deferred_interrupts():
            os.kill(os.getpid(), signal.SIGTERM)
            assert interrupt_pending()
            reached.append("end of the block")  # the state is whole when the signal takes effect
    assert reached == ["end of the block"] and info.value.exit_code == 143 and not interrupt_pending()
    with interrupt_signals(), pytest.raises(RunInterrupted):  # a second signal does not wait
        with deferred_interrupts():
            os.kill(os.getpid(), signal.SIGINT)
            os.kill(os.getpid(), signal.SIGINT)
            reached.append("never")
    assert reached == ["end of the block"] and not interrupt_pending()


def test_require_device():
    import torch

    from tivne.config import ConfigError
    from tivne.utils import require_device

    assert require_device("cpu") == "cpu" and require_device("auto") in ("cpu", "cuda")
    with pytest.raises(ConfigError, match="must be cpu"):
        require_device("tpu")
    if not torch.cuda.is_available():
        with pytest.raises(ConfigError, match="device=gpu: CUDA is not available"):
            require_device("gpu")


def fit_and_signal(callbacks: list) -> tuple[object, BaseException | None]:
    """A one-step Lightning fit under interrupt_signals whose step sends this process SIGTERM."""
    import signal

    import lightning as L
    import torch

    from tivne.utils import RunInterrupted, interrupt_signals

    class Step(L.LightningModule):
        def __init__(self) -> None:
            super().__init__()
            self.w = torch.nn.Parameter(torch.zeros(1))
            self.handler_in_step = None

        def training_step(self, batch, _):
            self.handler_in_step = signal.getsignal(signal.SIGTERM)
            os.kill(os.getpid(), signal.SIGTERM)
            return (self.w - 1).pow(2).sum()

        def configure_optimizers(self):
            return torch.optim.SGD(self.parameters(), lr=0.1)

        def train_dataloader(self):
            return torch.utils.data.DataLoader(torch.zeros(2, 1), batch_size=1)

    trainer = L.Trainer(max_epochs=1, logger=False, enable_checkpointing=False, enable_progress_bar=False,
                        enable_model_summary=False, accelerator="cpu", callbacks=callbacks)
    raised = None
    try:
        with interrupt_signals():
            trainer.fit(Step())
    except RunInterrupted as exc:
        raised = exc
    return trainer, raised


def test_tivne_signal_handlers_win_over_lightnings_sigterm_handler():
    """Lightning's fit wraps SIGTERM in its own handler (it flags the trainer and ends the fit loop
    with its SIGTERMException); with InterruptSignalsFirst TivNe's handler alone runs from the first step."""
    import signal

    from tivne.utils import InterruptSignalsFirst

    before = signal.getsignal(signal.SIGTERM)
    trainer, raised = fit_and_signal([InterruptSignalsFirst()])
    assert raised is not None and raised.exit_code == 143
    assert trainer.received_sigterm is False  # Lightning's handler never saw the signal
    assert signal.getsignal(signal.SIGTERM) == before  # every handler is restored afterwards
    trainer, _ = fit_and_signal([])
    assert trainer.received_sigterm is True  # without it, Lightning's handler runs first
