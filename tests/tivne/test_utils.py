"""Runtime settings (tivne/utils.py, tivne/__init__.py)."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest


@pytest.mark.parametrize("package", ["tivne", "data_modules"])
def test_openmp_wait_policy_is_passive_before_torch_loads(package):
    env = {k: v for k, v in os.environ.items() if k != "OMP_WAIT_POLICY"}
    # set by the package's __init__, which runs before anything of it imports torch
    code = f"import os, {package}; print(os.environ.get('OMP_WAIT_POLICY'))"
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
