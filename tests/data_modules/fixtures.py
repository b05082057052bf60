"""Writers that create tiny datasets on disk in each supported format (for the reader tests).

Every ``make_*`` function writes a sequence under the given path and returns a ``SimpleNamespace``
with the ground truth the reader must reproduce (uint8 colour, depth in metres, masks, poses, ...).
"""

from __future__ import annotations

import struct
import zlib
from pathlib import Path
from types import SimpleNamespace

import cv2
import numpy as np
import OpenEXR
import torch

from data_modules.poses import matrix_to_quat

W, H = 32, 24
# TUM / Bonn camera presets are for 640x480 (a principal point near (320, 240) must lie in the image)
TUM_W, TUM_H = 640, 480


# ------------------------------------------------------------------------------ primitive writers


def write_png_rgb(path: Path, rgb: np.ndarray) -> None:
    """(H, W, 3) uint8 RGB -> PNG (or JPG by suffix)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    assert cv2.imwrite(str(path), np.ascontiguousarray(rgb[:, :, ::-1]))


def write_png16(path: Path, img: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    assert img.dtype == np.uint16
    assert cv2.imwrite(str(path), img)


def write_png8(path: Path, img: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    assert cv2.imwrite(str(path), img.astype(np.uint8))


def write_exr(path: Path, channels: dict[str, np.ndarray], half: bool = False) -> None:
    """Write an EXR with the given named channels (FLOAT, or HALF with ``half=True``)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    dtype = np.float16 if half else np.float32
    chans = {k: np.ascontiguousarray(v.astype(dtype)) for k, v in channels.items()}
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    OpenEXR.File(header, chans).write(str(path))


def random_rgb(rng: np.random.Generator, h: int = H, w: int = W) -> np.ndarray:
    return rng.integers(0, 256, size=(h, w, 3), dtype=np.uint8)


def blocky(rng: np.random.Generator, shape: tuple[int, ...], high: int, dtype, block: int = 8) -> np.ndarray:
    """Random values in [0, high) constant over ``block`` x ``block`` tiles: full-size images that
    PNG-encode in milliseconds (noise at 640x480 is slow to write and read)."""
    h, w = shape[:2]
    small = rng.integers(0, high, size=(-(-h // block), -(-w // block), *shape[2:])).astype(dtype)
    return np.ascontiguousarray(small.repeat(block, 0).repeat(block, 1)[:h, :w])


def random_pose(rng: np.random.Generator) -> np.ndarray:
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    x, y, z, w = q
    R = np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = rng.uniform(-2, 2, size=3)
    return T


def pose_line(key: str, T: np.ndarray) -> str:
    q = matrix_to_quat(torch.from_numpy(np.asarray(T[:3, :3], dtype=np.float64))).numpy()
    vals = [*T[:3, 3], *q]
    return key + " " + " ".join(f"{v:.12f}" for v in vals)


def write_poses(path: Path, keys: list[str], poses: list[np.ndarray], header: str | None = "# key tx ty tz qx qy qz qw") -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    lines = [header] if header else []
    lines += [pose_line(k, T) for k, T in zip(keys, poses)]
    path.write_text("\n".join(lines) + "\n")


# ------------------------------------------------------------------------------------- Co-Fusion


def make_cofusion(
    root: Path,
    n: int = 3,
    first: int = 1,
    calib: str | None = "20 21 15.5 11.5 32 24",
    exr: str = "Y",  # "Y" | "RGB" | "Z"
    half: bool = False,
    masks: str | None = "mask_id",
    mask_channels: int = 1,
    original: bool = False,
    seed: int = 0,
) -> SimpleNamespace:
    """A Co-Fusion folder with frames ``first..first+n-1``, GT camera and one object trajectory.

    Depth values are multiples of 1/8 m (exact in HALF); pixel (0, 0) of each depth holds an
    absurd value (1e10 / NaN / inf cycling) that must read back as 0. The object file
    ``gt-car-2.txt`` covers all frames but the first.
    """
    rng = np.random.default_rng(seed)
    root.mkdir(parents=True, exist_ok=True)
    if calib is not None:
        (root / "calibration.txt").write_text(calib + "\n")
    truth = SimpleNamespace(rgb=[], depth=[], mask_ids=[], poses=[], numbers=list(range(first, first + n)))
    absurd = [1e10, np.nan, np.inf] if not half else [np.inf, np.nan, 1000.0]
    for k, num in enumerate(truth.numbers):
        rgb = random_rgb(rng)
        write_png_rgb(root / "colour" / f"Color{num:04d}.png", rgb)
        depth = rng.integers(4, 40, size=(H, W)).astype(np.float32) / 8.0
        stored = depth.copy()
        stored[0, 0] = absurd[k % 3]
        depth[0, 0] = 0.0
        chans = {"Y": stored} if exr == "Y" else {"Z": stored} if exr == "Z" else {"R": stored, "G": stored, "B": stored}
        write_exr(root / "depth_noise" / f"Depth{num:04d}.exr", chans, half=half)
        if original:
            write_exr(root / "depth_original" / f"Depth{num:04d}.exr", {"R": stored, "G": stored, "B": stored}, half=half)
        if masks:
            ids = np.zeros((H, W), np.uint8)
            ids[5:10, 3 + k : 9 + k] = 1
            ids[15:20, 20:26] = 2
            img = ids if mask_channels == 1 else np.repeat(ids[:, :, None], 3, axis=2)
            write_png8(root / masks / f"Mask{num:04d}.png", img)
            truth.mask_ids.append(ids)
        truth.rgb.append(rgb)
        truth.depth.append(depth)
        truth.poses.append(random_pose(rng))
    write_poses(
        root / "trajectories" / "gt-cam-0.txt",
        [str(x) for x in truth.numbers],
        truth.poses,
        header="# frame translation_x translation_y translation_z quaternion_x quaternion_y quaternion_z quaternion_w",
    )
    truth.object_poses = [random_pose(rng) for _ in truth.numbers[1:]]
    write_poses(root / "trajectories" / "gt-car-2.txt", [str(x) for x in truth.numbers[1:]], truth.object_poses, header=None)
    return truth


# ------------------------------------------------------------------------------------------- KLG


def klg_record(ts_us: int, depth_mm: np.ndarray, rgb: np.ndarray | None, depth_mode: str = "raw", colour_mode: str = "raw") -> bytes:
    """One KLG frame record.

    colour_mode: ``raw`` (R,G,B bytes), ``jpeg`` (Logger2 style: the RGB buffer handed to an
    encoder that expects BGR, so the file's red plane holds blue) or ``none`` (imageSize 0).
    """
    d = depth_mm.astype("<u2").tobytes()
    if depth_mode == "zlib":
        d = zlib.compress(d, 1)
    if colour_mode == "raw":
        c = np.ascontiguousarray(rgb).tobytes()
    elif colour_mode == "jpeg":
        ok, enc = cv2.imencode(".jpg", np.ascontiguousarray(rgb), [cv2.IMWRITE_JPEG_QUALITY, 100, cv2.IMWRITE_JPEG_SAMPLING_FACTOR, cv2.IMWRITE_JPEG_SAMPLING_FACTOR_444])
        assert ok
        c = enc.tobytes()
    else:
        c = b""
    return struct.pack("<qii", ts_us, len(d), len(c)) + d + c


def make_klg(
    path: Path,
    modes=(("raw", "raw"), ("zlib", "jpeg"), ("zlib", "none")),
    header_count: int | None = None,
    w: int = W,
    h: int = H,
    seed: int = 0,
) -> SimpleNamespace:
    """A KLG file with one frame per (depth_mode, colour_mode). Colour is 8x8-blocky (JPEG friendly)."""
    rng = np.random.default_rng(seed)
    truth = SimpleNamespace(rgb=[], depth_mm=[], ts_us=[], modes=list(modes), offsets=[])
    body = b""
    for k, (dm, cm) in enumerate(modes):
        depth = rng.integers(0, 5000, size=(h, w)).astype(np.uint16)
        block = rng.integers(0, 256, size=(h // 8, w // 8, 3), dtype=np.uint8)
        rgb = np.kron(block, np.ones((8, 8, 1), np.uint8))
        ts = 1_000_000 + 33_333 * k
        truth.offsets.append(4 + len(body))
        body += klg_record(ts, depth, rgb, dm, cm)
        truth.rgb.append(rgb if cm != "none" else np.zeros_like(rgb))
        truth.depth_mm.append(depth)
        truth.ts_us.append(ts)
    count = len(modes) if header_count is None else header_count
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(struct.pack("<i", count) + body)
    return truth


# ----------------------------------------------------------------------------------- TUM / Bonn


def make_tum(
    root: Path,
    n: int = 4,
    t0: float = 1341846313.5,
    dt: float = 1 / 30,
    depth_offsets=(0.011, -0.013, 0.004, 0.5),
    gt: list[tuple[float, np.ndarray]] | None = None,
    size: tuple[int, int] = (TUM_W, TUM_H),
    seed: int = 0,
) -> SimpleNamespace:
    """A TUM-layout folder: n colour frames; depth stamps offset per frame (|offset| >= 0.02 -> unmatched).

    ``gt``: explicit (timestamp, 4x4) groundtruth rows; default: no groundtruth.txt.
    ``size``: (width, height) of the images; the default suits the camera presets.
    """
    rng = np.random.default_rng(seed)
    root.mkdir(parents=True, exist_ok=True)
    rgb_lines = ["# color images", "# file: 'rgbd_dataset_freiburg3_walking_xyz.bag'", "# timestamp filename"]
    depth_lines = ["# depth maps", "# file: 'rgbd_dataset_freiburg3_walking_xyz.bag'", "# timestamp filename"]
    truth = SimpleNamespace(rgb=[], depth=[], rgb_ts=[], matched=[])
    for k in range(n):
        t = t0 + k * dt
        off = depth_offsets[k % len(depth_offsets)]
        td = t + off
        w, h = size
        rgb = random_rgb(rng, h, w) if (w, h) == (W, H) else blocky(rng, (h, w, 3), 256, np.uint8)
        raw = rng.integers(0, 30000, size=(h, w)).astype(np.uint16) if (w, h) == (W, H) else blocky(rng, (h, w), 30000, np.uint16)
        name_r, name_d = f"rgb/{t:.6f}.png", f"depth/{td:.6f}.png"
        write_png_rgb(root / name_r, rgb)
        write_png16(root / name_d, raw)
        rgb_lines.append(f"{t:.6f} {name_r}")
        depth_lines.append(f"{td:.6f} {name_d}")
        if abs(off) < 0.02:
            truth.rgb.append(rgb)
            truth.depth.append(raw.astype(np.float32) / 5000.0)
            truth.rgb_ts.append(float(f"{t:.6f}"))
            truth.matched.append(k)
    (root / "rgb.txt").write_text("\n".join(rgb_lines) + "\n")
    depth_lines[3:] = sorted(depth_lines[3:], key=lambda line: float(line.split()[0]))
    (root / "depth.txt").write_text("\n".join(depth_lines) + "\n")
    if gt is not None:
        write_poses(
            root / "groundtruth.txt",
            [f"{t:.6f}" for t, _ in gt],
            [T for _, T in gt],
            header="# ground truth trajectory\n# file: 'x.bag'\n# timestamp tx ty tz qx qy qz qw",
        )
    return truth


# -------------------------------------------------------------------------------------- folder


def make_folder(
    root: Path,
    n: int = 3,
    naming: str = "index",  # index | timestamp
    timestamps_txt: list[float] | None = None,
    intrinsics: str | None = "intrinsics.txt",
    masks: bool = True,
    poses: list[tuple[float, np.ndarray]] | None = None,
    rgb_ext: str = ".png",
    seed: int = 0,
) -> SimpleNamespace:
    """A folder-layout sequence; ``naming="timestamp"`` names frames ``100.000000.png``, ``100.100000.png`` ..."""
    rng = np.random.default_rng(seed)
    root.mkdir(parents=True, exist_ok=True)
    truth = SimpleNamespace(rgb=[], depth=[], masks=[], stems=[])
    for k in range(n):
        stem = f"{k}" if naming == "index" else f"{100.0 + 0.1 * k:.6f}"
        rgb = random_rgb(rng)
        raw = rng.integers(0, 8000, size=(H, W)).astype(np.uint16)
        write_png_rgb(root / "rgb" / f"{stem}{rgb_ext}", rgb)
        write_png16(root / "depth" / f"{stem}.png", raw)
        if masks:
            m = (rng.random((H, W)) < 0.3).astype(np.uint8) * 255
            write_png8(root / "masks" / f"{stem}.png", m)
            truth.masks.append(m != 0)
        truth.rgb.append(rgb)
        truth.depth.append(raw.astype(np.float32) / 1000.0)
        truth.stems.append(stem)
    if timestamps_txt is not None:
        (root / "timestamps.txt").write_text("\n".join(f"{t:.6f}" for t in timestamps_txt) + "\n")
    if intrinsics == "intrinsics.txt":
        (root / "intrinsics.txt").write_text("20 21 15.5 11.5\n")
    elif intrinsics == "intrinsics.json":
        (root / "intrinsics.json").write_text('{"fx": 20, "fy": 21, "cx": 15.5, "cy": 11.5, "width": 32, "height": 24}')
    if poses is not None:
        write_poses(root / "poses.txt", [f"{t:.6f}" for t, _ in poses], [T for _, T in poses])
    return truth


# ------------------------------------------------------------------------------------- configs

CONF_DIR = Path(__file__).resolve().parents[2] / "conf" / "dataset"


def instantiate_dataset(config: str, root: Path | str, **overrides):
    """Instantiate ``conf/dataset/<config>.yaml`` with ``root`` (and overrides) via Hydra."""
    from hydra.errors import InstantiationException
    from hydra.utils import instantiate
    from omegaconf import OmegaConf

    cfg = OmegaConf.load(CONF_DIR / f"{config}.yaml")
    cfg.root = str(root)
    for k, v in overrides.items():
        cfg[k] = v
    try:
        return instantiate(cfg)
    except InstantiationException as e:  # Hydra wraps the reader's one-line DatasetError
        if e.__cause__ is not None:
            raise e.__cause__ from None
        raise


def run_inspect_inprocess(*overrides: str) -> int:
    """Compose ``conf/inspect.yaml`` with ``overrides`` and run the inspect CLI body in this process
    (same code path as ``python -m data_modules.inspect`` minus interpreter start-up); returns the
    exit status, output goes to stdout/stderr (read it with ``capsys``)."""
    from hydra import compose, initialize_config_dir

    from data_modules.inspect import run

    with initialize_config_dir(config_dir=str(CONF_DIR.parent), version_base="1.3"):
        cfg = compose(config_name="inspect", overrides=list(overrides))
    return run(cfg)
