"""Size limits before the first frame (tivne.limits): numbers and the fix in one line."""

from __future__ import annotations

import pytest

from tivne.limits import KEYFRAME_BYTES_PER_PIXEL, MAX_FRAME_PIXELS, available_memory, check_run_size, memory_need, suggested_size
from tivne.settings import ConfigError

GB = 2**30


def test_memory_need_counts_stored_keyframes_map_and_working_set():
    need = memory_need(640, 480, frames=2000, keyframe_every=5, max_stored=250, max_capacity=2_000_000, embed_dim=16)
    assert need.stored_keyframes == 250 and need.keyframes == 250 * 640 * 480 * KEYFRAME_BYTES_PER_PIXEL
    assert need.map == 2_000_000 * 16 * 16
    assert memory_need(640, 480, 12, 5, 250, 1, 1).stored_keyframes == 4  # frames 0, 5, 10 and the first
    assert need.total == need.keyframes + need.map + need.working


def test_suggested_size_keeps_the_aspect_ratio():
    assert suggested_size(4000, 3000) == (640, 480)
    assert suggested_size(1920, 1080) == (640, 360)
    assert suggested_size(320, 240) == (320, 240)  # never upscales


def test_frames_larger_than_the_limit_are_refused_with_the_fix():
    with pytest.raises(ConfigError, match=r"data.resize: frames of 4000x3000 \(12.0 Mpx\).*set data.resize=\[640,480\]"):
        check_run_size(4000, 3000, 2, 5, 250, 2_000_000, 16, available=1000 * GB)
    assert 2048 * 2048 == MAX_FRAME_PIXELS
    check_run_size(2048, 2048, 2, 5, 250, 2_000_000, 16, available=1000 * GB)  # at the limit: accepted


def test_memory_beyond_what_is_available_is_refused_naming_the_part():
    with pytest.raises(ConfigError, match=r"data.resize: the run needs about 4.2 GB \(250 keyframes of 1920x1080.* but 2.0 GB is available; "
                                          r"set data.resize=\[640,360\]"):
        check_run_size(1920, 1080, 5000, 5, 250, 1000, 16, available=2 * GB)
    with pytest.raises(ConfigError, match=r"field.max_capacity: .* set field.max_capacity=\d+ or less"):
        check_run_size(64, 48, 5, 5, 250, 10**12, 16, available=2 * GB)
    assert check_run_size(640, 480, 5000, 5, 250, 2_000_000, 16, available=8 * GB).total < 8 * GB


def test_available_memory_is_the_lower_of_meminfo_and_the_cgroup_limit(tmp_path):
    (tmp_path / "meminfo").write_text("MemTotal: 16000000 kB\nMemAvailable:    8000000 kB\n")
    (tmp_path / "memory.max").write_text("3000000000\n")
    (tmp_path / "memory.current").write_text("1000000000\n")
    assert available_memory(tmp_path / "meminfo", tmp_path) == 2_000_000_000
    (tmp_path / "memory.max").write_text("max\n")
    assert available_memory(tmp_path / "meminfo", tmp_path) == 8_000_000 * 1024
    assert available_memory(tmp_path / "none", tmp_path / "none") is None
