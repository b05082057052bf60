"""The readers a config may name, and the checked settings of every reader and of ``data.*``.

A run folder is data, not code: ``tivne.evaluate`` and ``tivne.report`` rebuild a run's sequence
from the folder's own ``.hydra/config.yaml``, and a shared folder may say anything there. So before
any ``instantiate``, :func:`check_dataset_node` and :func:`check_masks_node` look at every
``_target_`` in the node (at any depth) and accept only the project's own readers
(:data:`READERS`) and mask providers (:data:`MASK_PROVIDERS`); anything else is one
:class:`ConfigError` line naming the key and the target. The reader's arguments are then checked
like every other section (type, range, unknown keys: :mod:`tivne.settings`), as are the ``data.*``
keys (:class:`DataConfig`).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, ClassVar

from tivne.settings import ConfigError, Settings, setting

MISSING = "???"  # OmegaConf's mandatory value, left for instantiate to report with its full key


@dataclass(frozen=True)
class DataConfig(Settings):
    """How a sequence is streamed (:class:`data_modules.sequence.SequenceView`): from the recording's
    ``first_frame``-th frame (0-based) every ``stride``-th frame, at most ``max_frames`` of them,
    resized to ``resize`` = [width, height] (intrinsics scaled to match; null = as recorded), depth
    outside [depth_min, depth_max] metres made invalid; drop_frames = [first, last] leaves those frames
    of the recording out (a dropped stretch, to test what a stalled recorder does to tracking)."""

    section: ClassVar[str] = "data"
    first_frame: int = setting(0, ge=0)
    stride: int = setting(1, ge=1)
    max_frames: int | None = setting(None, ge=1)
    resize: tuple[int, ...] | None = setting(None, ge=1)
    depth_min: float = setting(0.0, ge=0)
    depth_max: float | None = setting(10.0, gt=0)
    drop_frames: tuple[int, ...] | None = setting(None, ge=0)

    def check(self) -> None:
        if self.resize is not None and len(self.resize) != 2:
            raise ConfigError(f"data.resize={list(self.resize)}: must be [width, height]")
        if self.depth_max is not None and self.depth_max <= self.depth_min:
            raise ConfigError(f"data.depth_max={self.depth_max}: must be > data.depth_min ({self.depth_min})")
        if self.drop_frames is not None and (len(self.drop_frames) != 2 or self.drop_frames[1] < self.drop_frames[0]):
            raise ConfigError(f"data.drop_frames={list(self.drop_frames)}: must be [first, last] with first <= last")

    def view_kwargs(self) -> dict[str, Any]:
        """Keyword arguments of SequenceView (``resize`` as a list)."""
        return {"first_frame": self.first_frame, "stride": self.stride, "max_frames": self.max_frames,
                "resize": None if self.resize is None else list(self.resize), "depth_min": self.depth_min, "depth_max": self.depth_max,
                "drop_frames": None if self.drop_frames is None else list(self.drop_frames)}


def _check_numbers(key: str, values: Mapping[str, Any] | None, allowed: tuple[str, ...] | None = None) -> None:
    """A nested mapping of finite numbers, booleans or nulls (intrinsics, sensor switches)."""
    if values is None:
        return
    if not isinstance(values, Mapping):
        raise ConfigError(f"{key}={values!r}: must be a mapping or null")
    for name, value in values.items():
        if allowed is not None and name not in allowed:
            raise ConfigError(f"{key}.{name}: unknown setting (known: {', '.join(allowed)})")
        if value is None or isinstance(value, bool):
            continue
        if not isinstance(value, (int, float)) or not math.isfinite(value):
            raise ConfigError(f"{key}.{name}={value!r}: must be a finite number")


@dataclass(frozen=True)
class TUMReader(Settings):
    """Arguments of :class:`data_modules.tum.TUMSequence` (conf/dataset/tum.yaml documents them)."""

    section: ClassVar[str] = "dataset"
    root: str | None = None
    name: str | None = None
    camera: str | None = None
    fx: float | None = setting(None, gt=0)
    fy: float | None = setting(None, gt=0)
    cx: float | None = None
    cy: float | None = None
    distortion: tuple[float, ...] | None = None
    width: int | None = setting(None, ge=1)
    height: int | None = setting(None, ge=1)
    undistort: bool = True
    depth_scale: float = setting(5000.0, gt=0)
    max_time_diff: float = setting(0.02, ge=0)
    gt_max_gap: float | None = setting(0.1, ge=0)
    gt_file: str = "groundtruth.txt"
    colour_camera: tuple[float, ...] | None = None
    colour_offset: tuple[float, ...] | None = None
    readout_s: float = setting(0.0, ge=0, lt=1)  # the rolling shutter's readout (0 = global)

    def check(self) -> None:
        if self.distortion is not None and len(self.distortion) != 5:
            raise ConfigError(f"dataset.distortion={list(self.distortion)}: must be [k1, k2, p1, p2, k3]")
        if self.colour_camera is not None and (len(self.colour_camera) != 4 or min(self.colour_camera[:2]) <= 0):
            raise ConfigError(f"dataset.colour_camera={list(self.colour_camera)}: must be [fx, fy, cx, cy] of the colour camera, fx and fy > 0")
        if self.colour_offset is not None and (len(self.colour_offset) != 2 or self.colour_camera is None):
            raise ConfigError(f"dataset.colour_offset={list(self.colour_offset)}: must be [x, y] metres, with dataset.colour_camera set")


@dataclass(frozen=True)
class BonnReader(TUMReader):
    """Arguments of :class:`data_modules.tum.BonnSequence`: TUM's and the marker correction."""

    marker_to_camera: bool = True


@dataclass(frozen=True)
class FolderReader(Settings):
    """Arguments of :class:`data_modules.folder.FolderSequence` (conf/dataset/folder.yaml)."""

    section: ClassVar[str] = "dataset"
    root: str | None = None
    name: str | None = None
    depth_scale: float = setting(1000.0, gt=0)
    fps: float = setting(30.0, gt=0)
    timestamps_from: str = setting("auto", choices=("auto", "file", "names", "fps"))
    intrinsics: dict | None = None
    pose_max_gap: float | None = setting(0.1, ge=0)
    max_depth: float | None = setting(None, gt=0)

    def check(self) -> None:
        _check_numbers("dataset.intrinsics", self.intrinsics, ("fx", "fy", "cx", "cy"))


@dataclass(frozen=True)
class CoFusionReader(Settings):
    """Arguments of :class:`data_modules.cofusion.CoFusionSequence` (conf/dataset/room4.yaml)."""

    section: ClassVar[str] = "dataset"
    root: str | None = None
    name: str | None = None
    depth: str = setting("noise", choices=("noise", "original"))
    fps: float = setting(24.0, gt=0)
    timestamps_file: str | None = None
    masks: bool = True
    max_depth: float = setting(100.0, gt=0)
    original_is_ray_distance: Any = setting("auto", choices=("auto", True, False))
    blender_camera_axes: bool = False
    fallback_intrinsics: dict | None = None

    def check(self) -> None:
        if isinstance(self.original_is_ray_distance, (int, float)) and not isinstance(self.original_is_ray_distance, bool):
            raise ConfigError(f"dataset.original_is_ray_distance={self.original_is_ray_distance!r}: must be one of 'auto', True, False")
        _check_numbers("dataset.fallback_intrinsics", self.fallback_intrinsics, ("fx", "fy", "cx", "cy", "width", "height"))


@dataclass(frozen=True)
class KLGReader(Settings):
    """Arguments of :class:`data_modules.klg.KLGSequence` (conf/dataset/teddy.yaml)."""

    section: ClassVar[str] = "dataset"
    root: str | None = None
    name: str | None = None
    width: int = setting(640, ge=1)
    height: int = setting(480, ge=1)
    fx: float = setting(528.0, gt=0)
    fy: float = setting(528.0, gt=0)
    cx: float = 320.0
    cy: float = 240.0
    depth_scale: float = setting(1000.0, gt=0)
    jpeg_swap_rb: bool = True
    raw_swap_rb: bool = False
    readout_s: float = setting(0.0, ge=0, lt=1)  # the rolling shutter's readout (0 = global)


@dataclass(frozen=True)
class SyntheticReader(Settings):
    """Arguments of :class:`data_modules.synthetic.SyntheticSequence` (conf/dataset/synthetic.yaml;
    the scene name and the sensor switches are checked by the reader, which knows the presets)."""

    section: ClassVar[str] = "dataset"
    scene: str = "cube"
    name: str | None = None
    seed: int = setting(0, ge=0)
    scene_seed: int | None = setting(None, ge=0)
    num_frames: int = setting(150, ge=1)
    fps: float = setting(30.0, gt=0)
    width: int = setting(640, ge=16)
    height: int = setting(480, ge=16)
    depth_noise: bool = True
    rgb_noise: float | None = setting(None, ge=0, le=0.5)
    sensor: dict | None = None
    camera_speed: float = 1.0
    object_speed: float = 1.0
    cache_dir: str | None = None

    def check(self) -> None:
        _check_numbers("dataset.sensor", self.sensor)


# The only dataset targets a config may name: the project's readers and their argument checks.
READERS: dict[str, type[Settings]] = {
    "data_modules.tum.TUMSequence": TUMReader,
    "data_modules.tum.BonnSequence": BonnReader,
    "data_modules.folder.FolderSequence": FolderReader,
    "data_modules.cofusion.CoFusionSequence": CoFusionReader,
    "data_modules.klg.KLGSequence": KLGReader,
    "data_modules.synthetic.SyntheticSequence": SyntheticReader,
    "data_modules.synthetic.sequence.SyntheticSequence": SyntheticReader,
}
# The only mask providers a config may name (their arguments are checked by the providers).
MASK_PROVIDERS: tuple[str, ...] = (
    "tivne.masks.base.DatasetMasks",
    "tivne.masks.base.NoMasks",
    "tivne.masks.folder.FolderMasks",
    "tivne.masks.geometric.GeometricMasks",
    "tivne.masks.maskrcnn.MaskRCNNMasks",
)


def targets_in(node: Any, key: str) -> list[tuple[str, Any]]:
    """Every (key, value) of a ``_target_`` (Hydra also reads ``_partial_`` / ``_args_`` targets
    below it) in a plain config tree, depth first; ``key`` names the root."""
    found: list[tuple[str, Any]] = []
    if isinstance(node, Mapping):
        for name, value in node.items():
            if name == "_target_":
                found.append((f"{key}._target_", value))
            else:
                found += targets_in(value, f"{key}.{name}")
    elif isinstance(node, (list, tuple)):
        for i, value in enumerate(node):
            found += targets_in(value, f"{key}[{i}]")
    return found


def check_targets(node: Any, key: str, allowed: Mapping[str, Any] | tuple[str, ...]) -> str:
    """The node's own ``_target_`` once every ``_target_`` in it is one of ``allowed``, its own one
    at the top; raises :class:`ConfigError` naming the key and the target (nothing is imported)."""
    if not isinstance(node, Mapping) or "_target_" not in node:
        raise ConfigError(f"{key}: must be a config node with a _target_ (one of {', '.join(sorted(allowed))})")
    for where, target in targets_in(node, key):
        if not isinstance(target, str) or target not in allowed or where != f"{key}._target_":
            raise ConfigError(f"{where}={target!r}: not one of TivNe's own (allowed: {', '.join(sorted(allowed))}); "
                              "a config never runs other code")
    return node["_target_"]


def check_dataset_node(node: Mapping[str, Any], key: str = "dataset") -> Settings:
    """Refuse any target but :data:`READERS`, any other ``_``-key (``_args_``, ``_partial_``) and
    any reader argument outside its type or range (values still ``???`` are left for instantiate,
    which names them); returns the checked arguments."""
    target = check_targets(node, key, READERS)
    values = {k: v for k, v in node.items() if k != "_target_" and v != MISSING}
    special = sorted(k for k in values if str(k).startswith("_"))
    if special:
        raise ConfigError(f"{key}.{special[0]}: not allowed in a dataset node (only the reader's own arguments)")
    return READERS[target].from_mapping(values)


def check_masks_node(node: Mapping[str, Any], key: str = "masks.provider") -> str:
    """Refuse any mask provider but :data:`MASK_PROVIDERS` (at any depth of the node)."""
    return check_targets(node, key, MASK_PROVIDERS)
