"""The geometric (model-free) provider on known synthetic scenes: map and frames sources, predict, revise."""

from __future__ import annotations

import dataclasses
import sys
from pathlib import Path
from types import SimpleNamespace

import pytest
import torch

from data_modules.frame import Intrinsics
from tivne.config import RenderConfig
from tivne.masks.base import DatasetMasks, MaskContext, RecordingMasks
from tivne.masks.geometric import GeometricMasks
from tivne.masks.settings import build_provider

sys.path.insert(0, str(Path(__file__).parent))
from mask_scenes import CONF, H, W, box_depth, make_frame  # noqa: E402


def test_geometric_config_builds_through_the_checked_settings():
    from hydra import compose, initialize_config_dir
    from omegaconf import OmegaConf

    from tivne.config import ConfigError
    from tivne.masks.settings import check_provider

    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        cfg = compose(config_name="config", overrides=["masks=geometric"])
    node = OmegaConf.to_container(cfg.masks.provider, resolve=True)
    provider = build_provider(node)
    assert isinstance(provider, GeometricMasks) and provider.reference == "last_mapped"
    with pytest.raises(ConfigError, match=r"^masks\.provider\.stride=0: must be >= 1$"):
        build_provider(node | {"stride": 0})
    with pytest.raises(ConfigError, match=r"^masks\.provider\.revise_lags=\[30, 5\]"):
        check_provider(node | {"revise_lags": [30, 5]})
    with pytest.raises(ConfigError, match=r"^masks\.provider\._target_='os\.system': not a TivNe mask provider"):
        build_provider(node | {"_target_": "os.system"})  # only the project's own providers are ever built


class BoxField(torch.nn.Module):
    """Analytic map in the camera frame of an identity pose: a plane z = 3 m and a box at its
    *previous* place; SDF in truncation units like TimeVaryingField, unallocated beyond 4 m."""

    def __init__(self, box_min, box_max, truncation: float = 0.05) -> None:
        super().__init__()
        self.box_min, self.box_max, self.tr = torch.tensor(box_min), torch.tensor(box_max), truncation
        self.taus: list[float] = []

    def forward(self, points, tau):
        self.taus.append(float(tau[0]))
        c, half = (self.box_min + self.box_max) / 2, (self.box_max - self.box_min) / 2
        q = (points - c).abs() - half
        box = q.clamp_min(0).norm(dim=-1) + q.max(dim=-1).values.clamp_max(0)
        sdf = torch.minimum(3.0 - points[:, 2], box)
        return SimpleNamespace(
            sdf=(sdf / self.tr).clamp(-1, 1), rgb=torch.full_like(points, 0.5), valid=points[:, 2] < 4.0,
        )


@pytest.mark.parametrize("stride", [1, 2])
def test_geometric_provider_finds_the_moved_object_only(stride):
    K = Intrinsics(50.0, 50.0, W / 2, H / 2, W, H).K()
    field = BoxField([-0.5, -0.3, 1.5], [-0.1, 0.1, 1.9])  # the box was here in the map
    depth, now = box_depth(K, -0.3, 0.1, -0.3, 0.1, 1.5)  # it moved 0.2 m to the right
    _, before = box_depth(K, -0.5, -0.1, -0.3, 0.1, 1.5)
    provider = GeometricMasks(source="map", stride=stride, min_area=4, step=0.02, far=4.0)
    ctx = MaskContext(field, torch.eye(4), K, 0.5, RenderConfig(), 1, last_mapped_tau=0.4)
    first = provider(make_frame(0, depth=depth), MaskContext(field, torch.eye(4), K, 0.0, RenderConfig(), 0))
    assert first.shape == (H, W) and not first.any()  # no map yet: all static
    mask = provider(make_frame(1, depth=depth), ctx)
    assert mask.dtype == torch.bool and mask.shape == (H, W)
    iou = (mask & now).sum() / (mask | now).sum()
    assert iou > 0.8, float(iou)
    assert not (mask & before & ~now).any()  # the disoccluded background stays static
    assert field.taus[-1] == pytest.approx(0.4)  # queried at the last mapped time
    assert provider.timings_ms


def test_geometric_reference_time_choices():
    K = Intrinsics(50.0, 50.0, W / 2, H / 2, W, H).K()
    depth, _ = box_depth(K, -0.3, 0.1, -0.3, 0.1, 1.5)
    for reference, expected in (("frame", 0.5), ("first", 0.0), ("last_mapped", 0.3)):
        field = BoxField([-0.5, -0.3, 1.5], [-0.1, 0.1, 1.9])
        provider = GeometricMasks(source="map", reference=reference, stride=4)
        provider(make_frame(0, depth=depth), MaskContext(field, torch.eye(4), K, 0.3, RenderConfig(), 0))
        provider(make_frame(1, depth=depth), MaskContext(field, torch.eye(4), K, 0.5, RenderConfig(), 1))
        assert field.taus[-1] == pytest.approx(expected)  # last_mapped falls back to the previous frame's τ
    with pytest.raises(ValueError, match=r"masks\.provider\.reference="):
        GeometricMasks(reference="later")
    with pytest.raises(ValueError, match=r"masks\.provider\.source="):
        GeometricMasks(source="flow")


def test_geometric_frames_source_segments_the_moved_object():
    K = Intrinsics(50.0, 50.0, W / 2, H / 2, W, H).K()
    provider = GeometricMasks(source="frames", stride=1, min_area=4)
    ctx = lambda k: MaskContext(None, torch.eye(4), K, k / 30, RenderConfig(), k)  # noqa: E731
    first = provider(make_frame(0, depth=box_depth(K, -0.5, -0.1, -0.3, 0.1, 1.5)[0]), ctx(0))
    assert not first.any()
    depth, now = box_depth(K, -0.3, 0.1, -0.3, 0.1, 1.5)
    mask = provider(make_frame(1, depth=depth), ctx(1))
    assert (mask & now).sum() / (mask | now).sum() > 0.8
    # It stopped: no new seeds, but temporal consistency keeps it while it stays put.
    assert (provider(make_frame(2, depth=depth), ctx(2)) & now).sum() > 0.8 * now.sum()


@pytest.mark.parametrize("stride", [1, 4])
def test_geometric_mask_of_an_object_entering_at_the_border_reaches_the_border(stride):
    # The object tracker starts no track from a view the border cuts (tivne.slam.objects.instances.touches_border);
    # a mask stopping a stride short of the edge hid every such view from it.
    from tivne.slam.objects.instances import touches_border

    K = Intrinsics(50.0, 50.0, W / 2, H / 2, W, H).K()
    provider = GeometricMasks(source="frames", stride=stride, min_area=4)
    ctx = lambda k: MaskContext(None, torch.eye(4), K, k / 30, RenderConfig(), k)  # noqa: E731
    provider(make_frame(0, depth=box_depth(K, 0.8, 2.0, -0.3, 0.3, 1.5)[0]), ctx(0))
    depth, now = box_depth(K, 0.5, 2.0, -0.3, 0.3, 1.5)  # slid 0.3 m into the view, still cut by its right edge
    mask = provider(make_frame(1, depth=depth), ctx(1))
    assert now[:, -1].any() and (mask & now).sum() / (mask | now).sum() > (0.9 if stride == 1 else 0.65)  # nearest upsampling
    assert mask[now[:, -1], -1].sum() >= now[:, -1].sum() - stride and touches_border(mask)


def test_geometric_drops_a_mask_that_leaves_too_little_static_scene():
    K = Intrinsics(50.0, 50.0, W / 2, H / 2, W, H).K()
    ctx = lambda k: MaskContext(None, torch.eye(4), K, k / 30, RenderConfig(), k)  # noqa: E731
    strips = torch.linspace(1.5, 3.5, 5).repeat_interleave(W // 5 + 1)[:W].expand(H, W).clone()  # five surfaces, depth jumps between
    closer = strips.clone()
    closer[:, : 3 * W // 5] -= 0.4  # three of them 40 cm closer (as a pose error would show them): 60 % of the view
    for fraction, expect in ((1.0, True), (0.5, False)):
        provider = GeometricMasks(source="frames", stride=1, min_area=4, max_total_fraction=fraction)
        provider(make_frame(0, depth=strips), ctx(0))
        mask = provider(make_frame(1, depth=closer), ctx(1))
        assert bool(mask[:, : W // 2].float().mean() > 0.8) is expect and not mask[:, 4 * W // 5 :].any()
        assert bool(provider.previous is not None and provider.previous.any()) is expect  # not carried to the next frame either


def test_geometric_predict_gives_tracking_the_previous_mask_grown():
    K = Intrinsics(50.0, 50.0, W / 2, H / 2, W, H).K()
    provider = GeometricMasks(source="frames", stride=1, min_area=4, predict_margin=2)
    ctx = lambda k: MaskContext(None, torch.eye(4), K, k / 30, RenderConfig(), k)  # noqa: E731
    first = make_frame(0, depth=box_depth(K, -0.5, -0.1, -0.3, 0.1, 1.5)[0])
    assert provider.predict(first) is None
    provider(first, ctx(0))
    depth, now = box_depth(K, -0.3, 0.1, -0.3, 0.1, 1.5)
    mask = provider(make_frame(1, depth=depth), ctx(1))
    pred = RecordingMasks(provider).predict(make_frame(2, depth=depth))
    assert pred.shape == (H, W) and (pred & mask).sum() == mask.sum() and pred.sum() > mask.sum()


def test_geometric_revise_masks_an_earlier_keyframe_once_the_object_has_left():
    from tivne.render.rays import View

    K = Intrinsics(50.0, 50.0, W / 2, H / 2, W, H).K()
    then_d, then = box_depth(K, -0.5, -0.1, -0.3, 0.1, 1.5)  # the keyframe saw the box here, unmasked
    now_d, _ = box_depth(K, 0.2, 0.6, -0.3, 0.1, 1.5)  # it has left that place since
    rgb = torch.full((H, W, 3), 0.5)
    keyframe = View(0, 0.0, rgb, then_d, torch.zeros(H, W, dtype=torch.bool), torch.eye(4))
    too_recent = View(8, 8 / 30, rgb, then_d, None, torch.eye(4))
    current = View(10, 10 / 30, rgb, now_d, torch.zeros(H, W, dtype=torch.bool), torch.eye(4))
    provider = GeometricMasks(source="frames", stride=1, min_area=4, revise_lags=(5, 30))
    grown = provider.revise([keyframe, too_recent], current, K)
    assert list(grown) == [0]  # 2 frames back (too_recent): outside revise_lags
    mask = grown[0]
    assert (mask & then).sum() / (mask | then).sum() > 0.8
    assert not keyframe.dynamic.any()  # the View is not changed: the caller stores the grown mask
    keyframe = dataclasses.replace(keyframe, dynamic=mask)
    assert provider.revise([keyframe], current, K) == {}  # only grows
    assert GeometricMasks(revise_lags=None).revise([keyframe], current, K) == {}
    assert DatasetMasks().revise([keyframe], current, K) == {}
    assert RecordingMasks(provider).revise([keyframe], current, K) == {}
