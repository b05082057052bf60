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
