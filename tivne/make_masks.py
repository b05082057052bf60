"""Write a mask folder for a sequence with any provider that needs no tracked pose.

``python -m tivne.make_masks dataset=<name> [dataset.root=...] masks=maskrcnn masks.provider.weights=PATH out=DIR``

One PNG per frame named by frame index (``000123.png``, 255 = dynamic), written atomically; frames
whose PNG already exists and is valid are skipped, so an interrupted run resumes.
"""

from __future__ import annotations

from pathlib import Path

import hydra
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf

from data_modules.errors import overrides_checked
from data_modules.frame import DatasetError
from data_modules.io import read_mask_png, write_mask_png
from data_modules.sequence import SequenceView
from tivne.cli import check_known_keys, check_stream_inputs, one_line_errors
from tivne.masks.base import MaskProvider
from tivne.masks.folder import mask_file_name
from tivne.masks.settings import build_provider


def make_masks(provider: MaskProvider, view, out: str | Path, overwrite: bool = False, progress: bool = True) -> dict[str, int]:
    """Run ``provider`` over every frame of ``view`` and write ``out/<index:06d>.png``.

    Returns counts: written, skipped (valid PNG already there), empty (provider gave None -> all static).
    """
    if provider.needs_tracked_pose:
        raise DatasetError(f"masks={provider.name}", "needs the tracked pose and the map; run it inside SLAM (python -m tivne.train)")
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    size = (view.intrinsics.width, view.intrinsics.height)
    counts = {"written": 0, "skipped": 0, "empty": 0}
    from tqdm import tqdm

    for i in tqdm(range(len(view)), desc=f"masks ({provider.name})", unit="frame", disable=not progress):
        frame = view[i]
        path = out / mask_file_name(frame.index)
        if path.is_file() and not overwrite:
            try:
                read_mask_png(path, size)
                counts["skipped"] += 1
                continue
            except DatasetError:
                pass  # corrupt or wrong size: rewrite it
        mask = provider(frame, None)
        if mask is None:
            counts["empty"] += 1
            import torch

            mask = torch.zeros(frame.height, frame.width, dtype=torch.bool)
        write_mask_png(path, mask)
        counts["written"] += 1
    return counts


def run(cfg: DictConfig) -> dict[str, int]:
    out = cfg.out  # raises MissingMandatoryValue when not given
    check_known_keys(cfg, ("paths", "data", "dataset", "masks", "out", "overwrite", "progress"))
    data = check_stream_inputs(cfg)
    dataset = instantiate(cfg.dataset)
    view = SequenceView(dataset, **data.view_kwargs())
    provider = build_provider(OmegaConf.to_container(cfg.masks.provider, resolve=True))
    return make_masks(provider, view, out, bool(cfg.overwrite), bool(cfg.progress))


@overrides_checked
@hydra.main(config_path="../conf", config_name="make_masks", version_base="1.3")
@one_line_errors
def main(cfg: DictConfig) -> None:
    counts = run(cfg)
    print(f"{counts['written']} written, {counts['skipped']} skipped, {counts['empty']} without a mask -> {cfg.out}")


if __name__ == "__main__":
    main()
