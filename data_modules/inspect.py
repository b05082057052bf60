"""Inspect any dataset: ``python -m data_modules.inspect dataset=cube [data.max_frames=N] [format=json]``.

Prints a summary (frames, duration, resolution, intrinsics, sampled depth range, % valid depth,
% dynamic pixels, GT availability); optionally writes the GT camera trajectory in TUM format
(``gt_out=PATH``) and a PNG contact sheet (``sheet_out=PATH``: one row per frame, rgb | depth | mask).
``colour_camera=true`` also estimates, over the sampled frames, the colour camera of a sensor whose
colour is not registered to its depth (:mod:`data_modules.registration`; the value for
``dataset.colour_camera``); on registered colour it returns about the depth camera.

Bad input (a :class:`DatasetError`, a missing mandatory config value such as ``dataset.root=???``,
an output that cannot be written: any OSError, named by its path) prints one line
``error: <message>`` to stderr and exits with status 2. Reader warnings (missing
calibration, a short KLG frame count, dropped frames, ...) print as one line ``warning: <message>``
each on stderr; the summary itself stays alone on stdout.
"""

from __future__ import annotations

import contextlib
import json
import logging
import math
import sys
import warnings
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import torch

from data_modules.errors import EXIT_BAD_INPUT, error_line, find_cause, overrides_checked
from data_modules.frame import DatasetError
from data_modules.sequence import SequenceDataset, SequenceView
from data_modules.tables import write_tum_trajectory

SHEET_PANEL_MAX_WIDTH = 320


def sample_indices(n: int, k: int) -> np.ndarray:
    """Up to ``k`` evenly spaced distinct indices in ``[0, n)`` (first and last included)."""
    if n <= 0 or k <= 0:
        return np.zeros(0, dtype=np.int64)
    return np.unique(np.linspace(0, n - 1, min(n, k)).round().astype(np.int64))


def summarize(view: SequenceDataset, max_sampled: int = 20) -> dict[str, object]:
    """Summary of a sequence; depth / mask statistics over up to ``max_sampled`` evenly spaced frames.

    Returns a flat dict with snake_case keys and units: name, frames, duration_s, fps, width, height,
    fx, fy, cx, cy, depth_min_m, depth_max_m, valid_depth_pct, dynamic_pct (None without masks),
    has_gt_poses, has_masks, frames_sampled (depth_* are None when no sampled pixel is valid).
    """
    n = len(view)
    ts = np.asarray(view.timestamps, dtype=np.float64)
    duration = float(ts[-1] - ts[0]) if n else 0.0
    intr = view.intrinsics
    idx = sample_indices(n, max_sampled)
    dmin, dmax = math.inf, -math.inf
    valid = total = dynamic = masked_total = 0
    for i in idx:
        frame = view[int(i)]
        d = frame.depth
        ok = d > 0
        nvalid = int(ok.sum())
        if nvalid:
            dmin = min(dmin, float(d[ok].min()))
            dmax = max(dmax, float(d[ok].max()))
        valid += nvalid
        total += d.numel()
        if frame.mask is not None:
            dynamic += int(frame.mask.sum())
            masked_total += frame.mask.numel()
    return {
        "name": view.name,
        "frames": n,
        "duration_s": duration,
        "fps": (n - 1) / duration if n > 1 and duration > 0 else None,
        "width": intr.width,
        "height": intr.height,
        "fx": intr.fx,
        "fy": intr.fy,
        "cx": intr.cx,
        "cy": intr.cy,
        "depth_min_m": dmin if math.isfinite(dmin) else None,
        "depth_max_m": dmax if math.isfinite(dmax) else None,
        "valid_depth_pct": 100.0 * valid / total if total else None,
        "dynamic_pct": 100.0 * dynamic / masked_total if masked_total else None,
        "has_gt_poses": bool(view.has_gt_poses),
        "has_masks": bool(view.has_masks),
        "frames_sampled": int(len(idx)),
    }


def colour_camera_summary(view: SequenceDataset, max_sampled: int = 20) -> dict[str, object]:
    """The colour camera estimated over up to ``max_sampled`` evenly spaced frames
    (:func:`data_modules.registration.estimate_colour_camera`): colour_camera [fx, fy, cx, cy],
    edge_contrast_registered / _estimated."""
    from data_modules.registration import edge_frame, estimate_colour_camera

    frames = [view[int(i)] for i in sample_indices(len(view), max_sampled)]
    evidence = [edge_frame(f.rgb.numpy(), f.depth.numpy(), view.intrinsics) for f in frames]
    try:
        est = estimate_colour_camera(evidence, view.intrinsics)
    except ValueError as exc:
        raise DatasetError(f"dataset {view.name}", str(exc)) from None
    return {"colour_camera": list(est.colour_camera), "edge_contrast_registered": est.contrast_registered,
            "edge_contrast_estimated": est.contrast_estimated}


def format_summary(s: dict[str, object]) -> str:
    """Human-readable multi-line rendering of :func:`summarize`'s dict."""

    def num(v, fmt: str, unit: str = "") -> str:
        return "n/a" if v is None else f"{v:{fmt}}{unit}"

    lines = [
        f"name:         {s['name']}",
        f"frames:       {s['frames']}",
        f"duration:     {num(s['duration_s'], '.3f', ' s')} ({num(s['fps'], '.2f', ' fps')})",
        f"resolution:   {s['width']} x {s['height']}",
        f"intrinsics:   fx={s['fx']:.3f} fy={s['fy']:.3f} cx={s['cx']:.3f} cy={s['cy']:.3f}",
        f"depth range:  {num(s['depth_min_m'], '.3f')} - {num(s['depth_max_m'], '.3f', ' m')}"
        f" (sampled {s['frames_sampled']} of {s['frames']} frames)",
        f"valid depth:  {num(s['valid_depth_pct'], '.1f', ' %')}",
        f"dynamic:      {num(s['dynamic_pct'], '.2f', ' %') if s['has_masks'] else 'n/a (no masks)'}",
        f"GT poses:     {'yes' if s['has_gt_poses'] else 'no'}",
        f"GT masks:     {'yes' if s['has_masks'] else 'no'}",
    ]
    return "\n".join(lines)


def gt_trajectory(view: SequenceView) -> tuple[np.ndarray, torch.Tensor]:
    """Timestamps (N,) and GT camera-to-world poses (N, 4, 4) float64 of every frame of ``view``.

    Uses the base dataset's ``camera_pose(i)`` when it has one (no image is read), otherwise reads
    the frames. Raises :class:`DatasetError` when the dataset has no GT poses.
    """
    if not view.has_gt_poses:
        raise DatasetError(f"dataset {view.name}", "has no ground-truth camera poses (gt_out needs them)")
    base = getattr(view, "base", None)
    indices = getattr(view, "source_indices", None)
    if base is not None and indices is not None and callable(getattr(base, "camera_pose", None)):
        poses = [torch.as_tensor(base.camera_pose(int(j)), dtype=torch.float64) for j in indices]
    else:
        poses = []
        for i in range(len(view)):
            pose = view[i].gt_pose
            if pose is None:
                raise DatasetError(f"dataset {view.name}", f"frame {i} has no ground-truth pose")
            poses.append(pose.to(torch.float64))
    if not poses:
        raise DatasetError(f"dataset {view.name}", "no frames to write")
    return np.asarray(view.timestamps, dtype=np.float64), torch.stack(poses)


def contact_sheet(view: SequenceDataset, rows: int = 4, panel_max_width: int = SHEET_PANEL_MAX_WIDTH) -> np.ndarray:
    """BGR uint8 image: one row per evenly spaced frame with rgb | depth (turbo, invalid black) | mask.

    Panels are the frame size scaled down to at most ``panel_max_width`` wide; the sheet is
    ``3 * pw`` x ``rows * ph``. Frames without a mask get a grey "no mask" panel.
    """
    import cv2

    idx = sample_indices(len(view), rows)
    if len(idx) == 0:
        raise DatasetError(f"dataset {view.name}", "has no frames for a contact sheet")
    frames = [view[int(i)] for i in idx]
    W, H = view.intrinsics.width, view.intrinsics.height
    scale = min(1.0, panel_max_width / W)
    pw, ph = max(1, round(W * scale)), max(1, round(H * scale))
    valid = [f.depth[f.depth > 0] for f in frames]
    valid = torch.cat(valid) if valid else torch.zeros(0)
    lo = float(valid.min()) if valid.numel() else 0.0
    hi = float(valid.max()) if valid.numel() else 1.0
    hi = hi if hi > lo else lo + 1.0
    font_scale = max(0.3, 0.45 * pw / 320)
    out_rows = []
    for f in frames:
        rgb = (f.rgb.clamp(0, 1).numpy()[..., ::-1] * 255).round().astype(np.uint8)
        d = f.depth.numpy()
        norm = np.clip((d - lo) / (hi - lo), 0, 1)
        depth = cv2.applyColorMap((norm * 255).astype(np.uint8), cv2.COLORMAP_TURBO)
        depth[d <= 0] = 0
        if f.mask is not None:
            mask = np.repeat((f.mask.numpy().astype(np.uint8) * 255)[..., None], 3, axis=2)
        else:
            mask = np.full((H, W, 3), 128, dtype=np.uint8)
        panels = [np.ascontiguousarray(cv2.resize(p, (pw, ph), interpolation=cv2.INTER_AREA if scale < 1 else cv2.INTER_NEAREST)) for p in (rgb, depth, mask)]
        label = f"#{f.index} t={f.timestamp:.3f}s"
        for color, thick in (((0, 0, 0), 3), ((255, 255, 255), 1)):
            cv2.putText(panels[0], label, (4, max(10, int(16 * font_scale / 0.45))), cv2.FONT_HERSHEY_SIMPLEX, font_scale, color, thick, cv2.LINE_AA)
        if f.mask is None:
            cv2.putText(panels[2], "no mask", (4, ph // 2), cv2.FONT_HERSHEY_SIMPLEX, font_scale, (255, 255, 255), 1, cv2.LINE_AA)
        out_rows.append(np.concatenate(panels, axis=1))
    return np.concatenate(out_rows, axis=0)


def write_contact_sheet(path: str | Path, view: SequenceDataset, rows: int = 4) -> tuple[int, int]:
    """Write :func:`contact_sheet` as a PNG; returns (width, height) of the image."""
    import cv2

    img = contact_sheet(view, rows)
    path = Path(path)
    if path.parent and not path.parent.exists():
        raise DatasetError(path, "output folder does not exist")
    if not cv2.imwrite(str(path), img):
        raise DatasetError(path, "could not write the PNG")
    return img.shape[1], img.shape[0]


class _WarningLines(logging.Handler):
    """Writes each record as one ``warning: <message>`` line to the current ``sys.stderr``."""

    def emit(self, record: logging.LogRecord) -> None:
        _print_warning(record.getMessage())


def _print_warning(message: object) -> None:
    text = str(message).strip()
    print(f"warning: {text.splitlines()[0] if text else type(message).__name__}", file=sys.stderr)


@contextlib.contextmanager
def reader_warnings_on_stderr() -> Iterator[None]:
    """Within the block, show the readers' warnings as ``warning: ...`` lines on stderr.

    Catches WARNING records of the ``data_modules`` loggers (also when Hydra's logging config has
    silenced or disabled them) and Python warnings; restores every setting afterwards.
    """
    parent = logging.getLogger("data_modules")
    loggers = [parent] + [
        lg for name, lg in logging.root.manager.loggerDict.items() if name.startswith("data_modules.") and isinstance(lg, logging.Logger)
    ]
    was_disabled = [lg.disabled for lg in loggers]
    level, propagate = parent.level, parent.propagate
    handler = _WarningLines(logging.WARNING)
    for lg in loggers:
        lg.disabled = False  # Hydra's job_logging=disabled switches off the loggers that exist already
    parent.setLevel(logging.WARNING)
    parent.propagate = False  # one line per warning, not another copy through the root handlers
    parent.addHandler(handler)
    try:
        with warnings.catch_warnings():
            warnings.showwarning = lambda message, *args, **kwargs: _print_warning(message)
            yield
    finally:
        parent.removeHandler(handler)
        parent.setLevel(level)
        parent.propagate = propagate
        for lg, disabled in zip(loggers, was_disabled):
            lg.disabled = disabled


def check_outputs(cfg) -> None:
    """The output and count keys, before any data is read: ``sheet_out`` a .png path (the sheet is
    a PNG; OpenCV would pick the format by the suffix, or fail), counts integers >= 1."""
    if cfg.sheet_out and Path(str(cfg.sheet_out)).suffix.lower() != ".png":
        raise DatasetError("sheet_out", f"{cfg.sheet_out!r}: must be a .png path (the contact sheet is a PNG)")
    for key in ("sheet_frames", "max_sampled"):
        value = cfg.get(key, 1)
        if isinstance(value, bool) or not isinstance(value, int) or value < 1:
            raise DatasetError(key, f"must be an integer >= 1, got {value!r}")


def run(cfg) -> int:
    """The CLI body (Hydra-free apart from ``cfg``); returns the exit status."""
    import hydra.utils
    from omegaconf import OmegaConf

    try:
        if cfg.format not in ("text", "json"):
            raise DatasetError("format", f"must be 'text' or 'json', got {cfg.format!r}")
        check_outputs(cfg)
        with reader_warnings_on_stderr():
            ds = hydra.utils.instantiate(cfg.dataset)
            data = OmegaConf.to_container(cfg.data, resolve=True)
            view = SequenceView(ds, **data)
            summary = summarize(view, cfg.get("max_sampled", 20))
            if cfg.gt_out:
                ts, poses = gt_trajectory(view)
                out = Path(str(cfg.gt_out))
                if not out.parent.exists():
                    raise DatasetError(out, "output folder does not exist")
                write_tum_trajectory(out, ts, poses)
                summary["gt_out"] = str(out)
            if cfg.sheet_out:
                write_contact_sheet(str(cfg.sheet_out), view, int(cfg.sheet_frames))
                summary["sheet_out"] = str(cfg.sheet_out)
            if cfg.get("colour_camera", False):
                summary.update(colour_camera_summary(view, cfg.get("max_sampled", 20)))
    except Exception as exc:  # noqa: BLE001 -- only bad-input errors are turned into one line
        root = find_cause(exc)
        if root is None:
            raise
        print(error_line(root), file=sys.stderr)
        return EXIT_BAD_INPUT
    if cfg.format == "json":
        print(json.dumps(summary))
    else:
        print(format_summary(summary))
        if "colour_camera" in summary:
            cam = ", ".join(f"{v:.1f}" for v in summary["colour_camera"])
            print(f"colour camera: [{cam}] (colour-edge strength on depth edges {summary['edge_contrast_registered']:.2f} "
                  f"as registered -> {summary['edge_contrast_estimated']:.2f}; over {summary['frames_sampled']} frames)")
            print(f"  unregistered colour: dataset.colour_camera=[{cam}]")
        for key in ("gt_out", "sheet_out"):
            if key in summary:
                print(f"wrote {key}:{' ' * (8 - len(key))}{summary[key]}")
    return 0


def _main() -> None:
    import hydra

    @overrides_checked
    @hydra.main(config_path="../conf", config_name="inspect", version_base="1.3")
    def main(cfg) -> None:
        status = run(cfg)
        if status:
            sys.exit(status)

    main()


if __name__ == "__main__":
    _main()
