"""Masks from a folder of PNGs (tivne.masks.folder): by index, by the frames' source file stem, errors."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from data_modules.frame import DatasetError
from data_modules.io import write_mask_png
from tivne.masks.folder import FolderMasks, mask_file_name

sys.path.insert(0, str(Path(__file__).parent))
from mask_scenes import H, W, make_frame, square  # noqa: E402


def test_folder_masks_by_index_and_stem(tmp_path):
    m = square(3, 4, 8)
    write_mask_png(tmp_path / "000007.png", m)
    write_mask_png(tmp_path / "12.png", ~m)
    write_mask_png(tmp_path / "rgb_0042.png", m)
    provider = FolderMasks(root=str(tmp_path))
    assert torch.equal(provider(make_frame(7), None), m)
    assert torch.equal(provider(make_frame(12), None), ~m)  # other zero padding
    stem = FolderMasks(root=str(tmp_path), match="stem")
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
    provider = FolderMasks(root=str(tmp_path / "masks"), match="stem")
    for k, stem in enumerate(stems):
        frame = sequence[k]
        assert frame.source == f"{stem}.png"
        assert torch.equal(provider(frame, None), masks[stem])
    # A frame that was not read from a file (a KLG log, the cube) cannot be matched by stem.
    with pytest.raises(DatasetError, match=r"^masks\.match: 'stem' needs the file each frame was read from, but frame 4 has none"):
        provider(make_frame(4), None)


def test_folder_masks_clear_errors(tmp_path):
    provider = FolderMasks(root=str(tmp_path))
    with pytest.raises(DatasetError, match=r"000003\.png: mask for frame 3 not found"):
        provider(make_frame(3), None)
    assert FolderMasks(root=str(tmp_path), missing="none")(make_frame(3), None) is None
    (tmp_path / "000004.png").write_bytes(b"not a png")
    with pytest.raises(DatasetError, match=r"000004\.png: cannot decode image"):
        provider(make_frame(4), None)
    write_mask_png(tmp_path / "000005.png", torch.zeros(10, 10, dtype=torch.bool))
    with pytest.raises(DatasetError, match=r"000005\.png: mask is 10x10 but the frame is 64x48"):
        provider(make_frame(5), None)
    with pytest.raises(DatasetError, match="mask folder not found"):
        FolderMasks(root=str(tmp_path / "nope"))
