"""Mask providers: contract, folder reader, preprocessing CLI, and the geometric segmenter."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from data_modules.frame import DatasetError, Frame, Intrinsics
from data_modules.io import write_mask_png
from tivne.make_masks import make_masks
from tivne.masks.base import DatasetMasks, MaskContext, NoMasks, RecordingMasks
from tivne.masks.folder import FolderMasks, mask_file_name
from tivne.masks.geometric import GeometricMasks
from tivne.masks.seeds import free_space_seeds, residual_seeds
from tivne.masks.segments import clean_mask, depth_segments
from tivne.config import RenderConfig

CONF = Path(__file__).resolve().parents[3] / "conf"
H, W = 48, 64


def make_frame(index: int = 0, mask: torch.Tensor | None = None, depth: torch.Tensor | None = None) -> Frame:
    depth = torch.full((H, W), 2.0) if depth is None else depth
    return Frame(index=index, timestamp=index / 30.0, rgb=torch.full((H, W, 3), 0.5), depth=depth, mask=mask)


def square(y0: int, x0: int, size: int, h: int = H, w: int = W) -> torch.Tensor:
    m = torch.zeros(h, w, dtype=torch.bool)
    m[y0 : y0 + size, x0 : x0 + size] = True
    return m


# ---- simple providers and the contract ---------------------------------------------------------


def test_none_and_dataset_providers():
    gt = square(5, 5, 10)
    frame = make_frame(mask=gt)
    assert NoMasks()(frame, None) is None
    assert torch.equal(DatasetMasks()(frame, None), gt)
    assert DatasetMasks()(make_frame(), None) is None
    assert not NoMasks.needs_tracked_pose and GeometricMasks.needs_tracked_pose


@pytest.mark.parametrize("name", ["dataset", "none", "folder", "maskrcnn", "geometric"])
def test_every_mask_config_names_a_provider(name):
    from omegaconf import OmegaConf

    cfg = OmegaConf.load(CONF / "masks" / f"{name}.yaml")
    target = cfg.provider._target_
    module, cls = target.rsplit(".", 1)
    import importlib

    assert hasattr(importlib.import_module(module), cls)


def test_geometric_config_instantiates_with_hydra():
    from hydra import compose, initialize_config_dir
    from hydra.utils import instantiate

    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        cfg = compose(config_name="config", overrides=["masks=geometric"])
    provider = instantiate(cfg.masks.provider)
    assert isinstance(provider, GeometricMasks) and provider.reference == "last_mapped"


# ---- folder ------------------------------------------------------------------------------------


def test_folder_masks_by_index_and_stem(tmp_path):
    m = square(3, 4, 8)
    write_mask_png(tmp_path / "000007.png", m)
    write_mask_png(tmp_path / "12.png", ~m)
    write_mask_png(tmp_path / "rgb_0042.png", m)
    provider = FolderMasks(str(tmp_path))
    assert torch.equal(provider(make_frame(7), None), m)
    assert torch.equal(provider(make_frame(12), None), ~m)  # other zero padding
    stem = FolderMasks(str(tmp_path), match="stem")
    frame = make_frame(99)
    frame.source = "rgb_0042.jpg"  # a reader that records its source file
    assert torch.equal(stem(frame, None), m)


def write_folder_sequence(root: Path, stems: list[str]) -> None:
    """A data_modules.folder sequence (rgb/, depth/, intrinsics.txt) with colour images named by ``stems``."""
    import cv2

    for d in ("rgb", "depth"):
        (root / d).mkdir(parents=True)
    for stem in stems:
        assert cv2.imwrite(str(root / "rgb" / f"{stem}.png"), np.full((H, W, 3), 128, np.uint8))
        assert cv2.imwrite(str(root / "depth" / f"{stem}.png"), np.full((H, W), 2000, np.uint16))
    (root / "intrinsics.txt").write_text(f"50 50 {W / 2} {H / 2}\n")


def test_folder_masks_by_stem_use_the_readers_source_file(tmp_path):
    from data_modules.folder import FolderSequence

    stems = ["shot_a", "shot_b", "shot_c"]
    write_folder_sequence(tmp_path / "rec", stems)
    masks = {stem: square(2 + 4 * k, 3 + 5 * k, 6) for k, stem in enumerate(stems)}
    for k, stem in enumerate(stems):
        write_mask_png(tmp_path / "masks" / f"{stem}.png", masks[stem])
        write_mask_png(tmp_path / "masks" / mask_file_name(k), ~masks[stem])  # index names: must not be used
    sequence = FolderSequence(tmp_path / "rec")
    provider = FolderMasks(str(tmp_path / "masks"), match="stem")
    for k, stem in enumerate(stems):
        frame = sequence[k]
        assert frame.source == f"{stem}.png"
        assert torch.equal(provider(frame, None), masks[stem])
    # A frame that was not read from a file (a KLG log, the cube) cannot be matched by stem.
    with pytest.raises(DatasetError, match=r"^masks\.match: 'stem' needs the file each frame was read from, but frame 4 has none"):
        provider(make_frame(4), None)


def test_folder_masks_clear_errors(tmp_path):
    provider = FolderMasks(str(tmp_path))
    with pytest.raises(DatasetError, match=r"000003\.png: mask for frame 3 not found"):
        provider(make_frame(3), None)
    assert FolderMasks(str(tmp_path), missing="none")(make_frame(3), None) is None
    (tmp_path / "000004.png").write_bytes(b"not a png")
    with pytest.raises(DatasetError, match=r"000004\.png: cannot decode image"):
        provider(make_frame(4), None)
    write_mask_png(tmp_path / "000005.png", torch.zeros(10, 10, dtype=torch.bool))
    with pytest.raises(DatasetError, match=r"000005\.png: mask is 10x10 but the frame is 64x48"):
        provider(make_frame(5), None)
    with pytest.raises(DatasetError, match="mask folder not found"):
        FolderMasks(str(tmp_path / "nope"))


# ---- make_masks ----------------------------------------------------------------------------------


class TinyView:
    intrinsics = Intrinsics(50.0, 50.0, W / 2, H / 2, W, H)

    def __init__(self, n: int = 4) -> None:
        self.frames = [make_frame(10 + i, mask=square(2 + i, 3 + i, 6)) for i in range(n)]

    def __len__(self) -> int:
        return len(self.frames)

    def __getitem__(self, i: int) -> Frame:
        return self.frames[i]


class CountingProvider(DatasetMasks):
    def __init__(self) -> None:
        self.calls = 0

    def __call__(self, frame, context):
        self.calls += 1
        return super().__call__(frame, context)


def test_make_masks_writes_resumes_and_round_trips(tmp_path):
    view = TinyView()
    provider = CountingProvider()
    counts = make_masks(provider, view, tmp_path, progress=False)
    assert counts == {"written": 4, "skipped": 0, "empty": 0}
    assert sorted(p.name for p in tmp_path.glob("*.png")) == ["000010.png", "000011.png", "000012.png", "000013.png"]
    assert not list(tmp_path.glob(".*tmp"))
    (tmp_path / "000012.png").write_bytes(b"half-written")  # an interrupted write
    (tmp_path / "000013.png").unlink()
    counts = make_masks(provider, view, tmp_path, progress=False)
    assert counts == {"written": 2, "skipped": 2, "empty": 0} and provider.calls == 6
    folder = FolderMasks(str(tmp_path))
    for f in view.frames:
        assert torch.equal(folder(f, None), f.mask)


def test_make_masks_refuses_pose_providers(tmp_path):
    with pytest.raises(DatasetError, match="needs the tracked pose"):
        make_masks(GeometricMasks(), TinyView(), tmp_path, progress=False)


def compose_make_masks(overrides):
    from hydra import compose, initialize_config_dir

    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        return compose(config_name="make_masks", overrides=overrides)


def test_make_masks_cli_needs_out():
    from omegaconf.errors import MissingMandatoryValue

    from tivne import make_masks as cli

    with pytest.raises(MissingMandatoryValue):
        cli.run(compose_make_masks(["masks=none", "dataset.num_frames=2"]))


def test_make_masks_cli_writes_a_folder(tmp_path):
    from tivne import make_masks as cli

    out = tmp_path / "masks"
    cfg = compose_make_masks([
        "masks=dataset", "dataset.num_frames=3", "dataset.width=32", "dataset.height=24",
        "dataset.cache_dir=null", f"out={out}", "progress=false",
    ])
    assert cli.run(cfg)["written"] == 3
    assert sorted(p.name for p in out.glob("*.png")) == ["000000.png", "000001.png", "000002.png"]


# ---- geometric: pure functions -------------------------------------------------------------------


def scene_depth(obj: torch.Tensor | None, background: float = 3.0, obj_depth: float = 1.5) -> torch.Tensor:
    """Tilted background plane plus an optional fronto-parallel object."""
    y = torch.arange(H, dtype=torch.float32)[:, None].expand(H, W)
    d = background + 0.01 * y
    if obj is not None:
        d = torch.where(obj, torch.full_like(d, obj_depth), d)
    return d


def test_residual_seeds_sign_and_known_space():
    old, new = square(10, 10, 12), square(10, 16, 12)
    observed, rendered = scene_depth(new), scene_depth(old)
    known = torch.ones(H, W, dtype=torch.bool)
    seeds = residual_seeds(observed, rendered, known)
    # Only the object's current pixels where the map had background: not the disoccluded strip.
    assert torch.equal(seeds, new & ~old)
    unknown = known.clone()
    unknown[:, 20:] = False
    assert not (residual_seeds(observed, rendered, unknown)[:, 20:]).any()
    noisy = rendered + 0.01 * torch.randn(H, W)  # within k·σ(z)
    assert not residual_seeds(noisy, rendered, known).any()


def test_depth_segments_split_object_from_background():
    obj = square(10, 10, 12)
    labels, n = depth_segments(scene_depth(obj).numpy())
    assert n == 2
    inner = labels[obj.numpy()]
    assert len(set(inner[inner > 0].tolist())) == 1


def test_clean_mask_grows_seeds_drops_speckle_and_keeps_temporal():
    obj = square(10, 10, 14)
    depth = scene_depth(obj).numpy()
    seeds = np.zeros((H, W), bool)
    seeds[10:24, 20:24] = True  # a 4-px leading-edge strip of the object
    seeds[40, 50] = seeds[5, 55] = True  # speckle on the background
    out = clean_mask(seeds, depth)
    assert (out == obj.numpy()).mean() > 0.99 and out[obj.numpy()].all()
    # No seeds this frame: the object survives through the previous frame's mask, only then.
    none = np.zeros_like(seeds)
    assert not clean_mask(none, depth).any()
    assert clean_mask(none, depth, previous=obj.numpy()).sum() == obj.sum()
    # A segment covering most of the frame (the background) is never dynamic.
    assert not clean_mask(np.ones_like(seeds), scene_depth(None).numpy()).any()



def test_clean_mask_segment_score_catches_slow_motion_but_not_a_pose_error():
    moving, still = square(8, 8, 12), square(30, 40, 10)  # two objects in front of the background
    depth = scene_depth(moving | still).numpy()
    rng = np.random.default_rng(0)
    noise = np.abs(rng.normal(size=(H, W)))  # |residual| / σ of a static scene: median ~0.67
    none = np.zeros((H, W), bool)
    slow = np.where(moving.numpy(), 4.0 + noise, noise)  # 4σ on the object: no single pixel seeds
    out = clean_mask(none, depth, motion_score=slow, min_area=4)
    assert (out == moving.numpy()).mean() > 0.99 and not out[still.numpy()].any()
    assert not clean_mask(none, depth, motion_score=slow, min_area=4, score_threshold=6.0).any()
    # A pose error moves everything, the still object too: the background's own score raises the bar.
    pose_error = noise + 3.5
    assert not clean_mask(none, depth, motion_score=pose_error, min_area=4).any()
    # Unknown residuals (NaN) do not count; a segment mostly unknown is not judged.
    unknown = np.where(moving.numpy(), np.nan, slow)
    assert not clean_mask(none, depth, motion_score=unknown, min_area=4).any()


# ---- geometric provider on a known synthetic map ---------------------------------------------------


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


def box_depth(K: torch.Tensor, x0: float, x1: float, y0: float, y1: float, z: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Observed depth of a fronto-parallel square at depth z in front of the z = 3 plane."""
    v, u = torch.meshgrid(torch.arange(H, dtype=torch.float32), torch.arange(W, dtype=torch.float32), indexing="ij")
    x, y = (u - K[0, 2]) / K[0, 0] * z, (v - K[1, 2]) / K[1, 1] * z
    inside = (x >= x0) & (x <= x1) & (y >= y0) & (y <= y1)
    return torch.where(inside, torch.full((H, W), z), torch.full((H, W), 3.0)), inside


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
    with pytest.raises(ValueError, match="reference"):
        GeometricMasks(reference="later")
    with pytest.raises(ValueError, match="source"):
        GeometricMasks(source="flow")


def test_free_space_seeds_against_an_earlier_frame_with_camera_motion():
    K = Intrinsics(50.0, 50.0, W / 2, H / 2, W, H).K()
    before_d, before = box_depth(K, -0.5, -0.1, -0.3, 0.1, 1.5)
    now_d, now = box_depth(K, -0.3, 0.1, -0.3, 0.1, 1.5)
    seeds, known, _ = free_space_seeds(now_d, torch.eye(4), before_d, torch.eye(4), K)
    # the object's new pixels (less one pixel next to the old place, from the 3x3 min); not the
    # disoccluded wall
    grown = torch.nn.functional.max_pool2d(before[None, None].float(), 3, 1, 1)[0, 0] > 0
    assert not (seeds & ~(now & ~before)).any() and not ((now & ~grown) & ~seeds).any()
    # A static scene seen from a moved camera: nothing fires (3x3 min keeps silhouettes quiet).
    pose = torch.eye(4)
    pose[0, 3] = 0.05
    ref_d, _ = box_depth(K, -0.55, -0.15, -0.3, 0.1, 1.5)  # the same scene from the moved camera
    seeds, known, _ = free_space_seeds(before_d, torch.eye(4), ref_d, pose, K)
    assert known.float().mean() > 0.8 and seeds.sum() <= 2


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


def test_recording_wrapper_keeps_masks():
    rec = RecordingMasks(DatasetMasks())
    gt = square(1, 1, 4)
    assert torch.equal(rec(make_frame(3, mask=gt), None), gt)
    assert torch.equal(rec.masks[3], gt) and torch.equal(rec.gt[3], gt) and rec.timestamps[3] == 3 / 30.0
    assert not hasattr(RecordingMasks, "instances")  # no global registry: callers keep their object


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
    assert provider.revise([keyframe, too_recent], current, K) == 1
    assert (keyframe.dynamic & then).sum() / (keyframe.dynamic | then).sum() > 0.8
    assert too_recent.dynamic is None  # 2 frames back: outside revise_lags
    before = keyframe.dynamic.clone()
    assert provider.revise([keyframe], current, K) == 0 and torch.equal(keyframe.dynamic, before)  # only grows
    assert GeometricMasks(revise_lags=None).revise([keyframe], current, K) == 0
    assert DatasetMasks().revise([keyframe], current, K) == 0
    assert RecordingMasks(provider).revise([keyframe], current, K) == 0
