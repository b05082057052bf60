"""Size limits, checked once the sequence is open and before the first frame: a run that cannot fit
stops in one line with the numbers and the fix, instead of swapping for hours or writing
gigabyte checkpoints.

Two rules (no silent downscaling: the fix is named, ``data.resize=[w,h]``):

* a frame (after ``data.resize``) has at most :data:`MAX_FRAME_PIXELS` pixels (2048 x 2048): the
  tracker, the mask providers and the keyframe store all work at frame resolution, and TivNe's
  settings are made for VGA-sized sensors;
* the memory the run will need -- the keyframe store (:data:`KEYFRAME_BYTES_PER_PIXEL` per pixel of
  every stored keyframe), the map at its capacity cap (``field.max_capacity`` rows of
  ``field.embed_dim`` float32, with gradient and two Adam moments) and the per-frame working set
  (:data:`WORK_BYTES_PER_PIXEL`, frames, pyramids, odometry) -- fits in the memory this machine has
  available (MemAvailable, or the cgroup limit when lower). Where that cannot be read the memory
  rule is skipped.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

from tivne.settings import ConfigError

MAX_FRAME_PIXELS = 2048 * 2048
KEYFRAME_BYTES_PER_PIXEL = 8  # uint8 colour (3), float32 depth (4), bool mask (1)
WORK_BYTES_PER_PIXEL = 200  # an estimate: float frames, two odometry pyramids, normals, residuals
MAP_BYTES_PER_VALUE = 16  # float32 parameter, gradient and two Adam moments
SUGGESTED_LONG_SIDE = 640


@dataclass(frozen=True)
class MemoryNeed:
    """Bytes a run will need, by part."""

    keyframes: int
    stored_keyframes: int
    map: int
    working: int

    @property
    def total(self) -> int:
        return self.keyframes + self.map + self.working


def memory_need(width: int, height: int, frames: int, keyframe_every: int, max_stored: int, max_capacity: int, embed_dim: int) -> MemoryNeed:
    """The memory of a run over ``frames`` frames of ``width`` x ``height``: keyframes stored (one
    every ``keyframe_every`` frames and the first, at most ``max_stored``), the map at its cap."""
    pixels = int(width) * int(height)
    stored = min(int(max_stored), math.ceil(int(frames) / int(keyframe_every)) + 1)
    return MemoryNeed(stored * pixels * KEYFRAME_BYTES_PER_PIXEL, stored, int(max_capacity) * int(embed_dim) * MAP_BYTES_PER_VALUE,
                      pixels * WORK_BYTES_PER_PIXEL)


def suggested_size(width: int, height: int, long_side: int = SUGGESTED_LONG_SIDE) -> tuple[int, int]:
    """The frame size with the same aspect ratio whose longer side is ``long_side`` (never larger than the frame)."""
    scale = min(1.0, long_side / max(width, height))
    return max(1, round(width * scale)), max(1, round(height * scale))


def available_memory(meminfo: Path = Path("/proc/meminfo"), cgroup: Path = Path("/sys/fs/cgroup")) -> int | None:
    """Bytes this process may still allocate: MemAvailable, or the cgroup v2 limit minus its usage
    when that is lower; None where neither can be read (not Linux)."""
    found: list[int] = []
    try:
        for line in meminfo.read_text().splitlines():
            if line.startswith("MemAvailable:"):
                found.append(int(line.split()[1]) * 1024)
    except (OSError, ValueError, IndexError):
        pass
    try:
        limit = (cgroup / "memory.max").read_text().strip()
        if limit.isdigit():
            found.append(int(limit) - int((cgroup / "memory.current").read_text().strip()))
    except (OSError, ValueError):
        pass
    return min(found) if found else None


def gb(n: int) -> str:
    return f"{n / 2**30:.1f} GB"


def check_run_size(width: int, height: int, frames: int, keyframe_every: int, max_stored: int, max_capacity: int, embed_dim: int,
                   available: int | None = None) -> MemoryNeed:
    """Refuse (one :class:`ConfigError` line with the numbers and the fix) a run whose frames are
    larger than :data:`MAX_FRAME_PIXELS` or whose memory need exceeds ``available`` bytes (default:
    :func:`available_memory`); returns the need."""
    w, h = suggested_size(width, height)
    fix = f"set data.resize=[{w},{h}]"
    if width * height > MAX_FRAME_PIXELS:
        raise ConfigError(f"data.resize: frames of {width}x{height} ({width * height / 1e6:.1f} Mpx) are larger than TivNe processes "
                          f"({MAX_FRAME_PIXELS / 1e6:.1f} Mpx, e.g. 2048x2048); {fix}")
    need = memory_need(width, height, frames, keyframe_every, max_stored, max_capacity, embed_dim)
    available = available_memory() if available is None else available
    if available is None or need.total <= available:
        return need
    numbers = (f"the run needs about {gb(need.total)} ({need.stored_keyframes} keyframes of {width}x{height}: {gb(need.keyframes)}, "
               f"map of field.max_capacity={max_capacity}: {gb(need.map)}, working set: {gb(need.working)}) but {gb(available)} is available")
    if need.map > need.keyframes + need.working:  # the map's cap is what does not fit: name that key
        fits = max(1, (available - need.keyframes - need.working) // (embed_dim * MAP_BYTES_PER_VALUE))
        raise ConfigError(f"field.max_capacity: {numbers}; set field.max_capacity={fits} or less")
    raise ConfigError(f"data.resize: {numbers}; {fix}, or lower keyframe.max_stored")
