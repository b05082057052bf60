"""The checked settings of every motion-mask provider (``masks.provider.*``) and the providers a
config may name: one allowlist of ``_target_`` values, each with its settings class, so a bad value
is one line naming ``masks.provider.<key>`` and a config (or a run folder's saved one) can only ever
build the project's own providers, never an arbitrary callable."""

from __future__ import annotations

import dataclasses
import importlib
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, ClassVar

from tivne.config import ConfigError, Settings, setting

SECTION = "masks.provider"


@dataclass(frozen=True)
class NoSettings(Settings):
    """A provider without settings (``dataset``: the masks shipped with the data; ``none``)."""

    section: ClassVar[str] = SECTION


@dataclass(frozen=True)
class FolderMasksConfig(Settings):
    """``masks=folder``: one PNG per frame, nonzero = dynamic. root: the folder (mandatory); match:
    'index' (<index:06d>.png, any zero padding) or 'stem' (<stem>.png of the colour image each frame was
    read from: TUM, Bonn, Co-Fusion, folder; not KLG or the cube); missing: 'error' (one line naming
    the file) or 'none' (frames without a PNG get no mask); suffix: the mask files' extension."""

    section: ClassVar[str] = SECTION
    root: str | None = None
    match: str = setting("index", choices=("index", "stem"))
    missing: str = setting("error", choices=("error", "none"))
    suffix: str = ".png"

    def check(self) -> None:
        if not self.root or self.root == "???":
            raise ConfigError(f"{SECTION}.root: the mask folder is required (masks.provider.root=DIR)")


@dataclass(frozen=True)
class GeometricMasksConfig(Settings):
    """``masks=geometric`` (model-free, needs the tracked pose; :mod:`tivne.masks.geometric`): flag
    pixels observed where space was seen free before -- by frames ``lags`` back (source 'frames',
    warped with the tracked poses) or by the map (source 'map', ray-marched at the tracked pose, at
    map time ``reference``: 'last_mapped', 'frame' or 'first') -- then grow them to depth-continuous
    segments. stride: every n-th pixel is tested, the mask upsampled; a residual counts beyond
    max(abs_threshold, k_sigma·σ(z)); color_threshold: source 'map', an optional colour L1 threshold
    where depth agrees; far / step: source 'map', marching range and step (m); open_radius /
    close_radius: morphology of the seeds (low-resolution pixels); segments smaller than min_area are
    never dynamic; a segment is dynamic when seeds cover seed_fraction of it, or keep_fraction of it was
    dynamic in the previous frame (temporal), unless it covers more than max_area_fraction of the valid
    pixels (background); neighbours join a segment if |Δz| <= max(abs_jump, rel_jump·z) and no concave crease
    parts them (crease_sigmas: inverse depth's second difference over crease_span low-resolution pixels beyond this
    many σ of the sensor noise, :func:`tivne.masks.segments.concave_creases`; null = depth jumps only, which leaves an
    object on the floor, or a door, in the background's segment: the door preset's geometric-mask recall was 0.4 %).
    Once creases split the room into floor and walls, max_area_fraction 0.4 let a floor piece that an object leaked
    into be flagged whole (38 % of a three_objects frame), hence 0.25. Tracking (before
    this frame's mask exists) leaves out the previous mask grown by predict_margin; a mask over more than
    max_total_fraction of the valid pixels is dropped (the frame gets none, the next starts afresh); score_threshold /
    score_ratio: a segment whose median |static-world residual|/σ(z) against the first lag reaches the
    threshold and the ratio times the background's is dynamic (null threshold = off); revise_lags (a, b):
    keyframes a..b frames back are re-tested against each new frame and their masks grow (null = off)."""

    section: ClassVar[str] = SECTION
    source: str = setting("frames", choices=("frames", "map"))
    lags: tuple[int, ...] = setting([5, 30], ge=1)
    reference: str = setting("last_mapped", choices=("last_mapped", "frame", "first"))
    stride: int = setting(4, ge=1)
    abs_threshold: float = setting(0.03, gt=0)
    k_sigma: float = setting(6.0, gt=0)
    color_threshold: float | None = setting(None, gt=0)
    far: float = setting(8.0, gt=0)
    step: float = setting(0.04, gt=0)
    open_radius: int = setting(1, ge=0)
    close_radius: int = setting(1, ge=0)
    min_area: int = setting(12, ge=0)
    seed_fraction: float = setting(0.04, ge=0, le=1)
    keep_fraction: float = setting(0.5, ge=0, le=1)
    max_area_fraction: float = setting(0.25, gt=0, le=1)
    rel_jump: float = setting(0.1, ge=0)
    abs_jump: float = setting(0.03, ge=0)
    crease_sigmas: float | None = setting(3.0, gt=0)
    crease_span: int = setting(2, ge=1)
    max_total_fraction: float = setting(0.5, gt=0, le=1)
    temporal: bool = True
    predict_margin: int = setting(2, ge=0)
    score_threshold: float | None = setting(3.0, gt=0)
    score_ratio: float = setting(2.0, gt=0)
    revise_lags: tuple[int, ...] | None = setting([5, 30], ge=0)

    def check(self) -> None:
        if not self.lags:
            raise ConfigError(f"{SECTION}.lags=[]: give at least one lag (frames back)")
        if self.revise_lags is not None and (len(self.revise_lags) != 2 or self.revise_lags[0] > self.revise_lags[1]):
            raise ConfigError(f"{SECTION}.revise_lags={list(self.revise_lags)}: must be [a, b] with a <= b, or null")


@dataclass(frozen=True)
class MaskRCNNConfig(Settings):
    """``masks=maskrcnn`` (torchvision maskrcnn_resnet50_fpn, COCO, from a local weights file; needs
    the ``detect`` extra): weights: the state dict (.pth, mandatory); classes: COCO ids treated as
    dynamic (person, bicycle, car, motorcycle, bus, truck, bird, cat, dog, horse, teddy bear);
    score_threshold / mask_threshold: detections and mask pixels kept; input_size: longest side fed to
    the network (null = the frame size); dilate: grow the mask by this many pixels; device: null = the
    frame's device."""

    section: ClassVar[str] = SECTION
    weights: str | None = None
    classes: tuple[int, ...] = setting([1, 2, 3, 4, 6, 8, 16, 17, 18, 19, 88], ge=1)
    score_threshold: float = setting(0.5, ge=0, le=1)
    mask_threshold: float = setting(0.5, ge=0, le=1)
    input_size: int | None = setting(640, ge=16)
    dilate: int = setting(0, ge=0)
    device: str | None = None


# The only providers a config may build: _target_ -> (short name, settings).
PROVIDERS: dict[str, tuple[str, type[Settings]]] = {
    "tivne.masks.base.DatasetMasks": ("dataset", NoSettings),
    "tivne.masks.base.NoMasks": ("none", NoSettings),
    "tivne.masks.folder.FolderMasks": ("folder", FolderMasksConfig),
    "tivne.masks.geometric.GeometricMasks": ("geometric", GeometricMasksConfig),
    "tivne.masks.maskrcnn.MaskRCNNMasks": ("maskrcnn", MaskRCNNConfig),
}


def check_provider(node: Mapping[str, Any]) -> tuple[str, Settings]:
    """The provider's ``_target_`` (one of :data:`PROVIDERS`) and its checked settings; ConfigError
    (one line naming ``masks.provider.*``) otherwise. Builds nothing."""
    values = dict(node or {})
    target = values.pop("_target_", None)
    if target not in PROVIDERS:
        known = ", ".join(sorted(name for name, _ in PROVIDERS.values()))
        raise ConfigError(f"{SECTION}._target_={target!r}: not a TivNe mask provider (masks= one of {known})")
    return target, PROVIDERS[target][1].from_mapping(values)


def build_provider(node: Mapping[str, Any]):
    """The mask provider a ``masks.provider`` node names, built only after its target and settings are checked."""
    target, settings = check_provider(node)
    module, _, name = target.rpartition(".")
    cls = getattr(importlib.import_module(module), name)
    return cls(**{f.name: getattr(settings, f.name) for f in dataclasses.fields(settings)})


MANDATORY = {"root", "weights"}  # no default: the composed config says ??? until the user gives one


def default_nodes() -> dict[str, dict[str, Any]]:
    """{provider name: {"provider": {"_target_": ..., every default}}}: the nodes conf/masks/*.yaml compose onto."""
    out = {}
    for target, (name, cls) in PROVIDERS.items():
        values: dict[str, Any] = {}
        for f in dataclasses.fields(cls):
            value = f.default_factory() if f.default_factory is not dataclasses.MISSING else f.default
            values[f.name] = "???" if f.name in MANDATORY else list(value) if isinstance(value, tuple) else value
        out[name] = {"provider": {"_target_": target, **values}}
    return out
