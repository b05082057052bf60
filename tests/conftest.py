"""Shared test fixtures (kept small: tests should build what they need themselves)."""

from __future__ import annotations

import pytest


@pytest.fixture(scope="session")
def tiny_cube():
    """Noise-free 80x60 moving-cube sequence with 6 frames and no cache (renders in milliseconds)."""
    from data_modules.synthetic import SyntheticSequence

    return SyntheticSequence(
        scene="cube", name="cube", num_frames=6, width=80, height=60, depth_noise=False, rgb_noise=0.0, cache_dir=None
    )


@pytest.fixture(scope="session", autouse=True)
def tivne_config_defaults():
    """conf/*.yaml compose onto the defaults of tivne.config (the CLIs register them on import)."""
    from tivne.cli import register_defaults

    register_defaults()
