"""KLG logs (Kintinuous / ElasticFusion / Co-Fusion raw logs), e.g. Co-Fusion's ``teddy-handover.klg``.

Byte layout (little-endian, no magic, no resolution field; dataset-formats.md §2)::

    int32 N                                  number of frames (0 or too small after a crash)
    N x { int64 timestamp_us, int32 depthSize, int32 imageSize,
          depthSize bytes depth, imageSize bytes colour }

Depth: ``depthSize == W*H*2`` -> raw uint16 LE millimetres, else a zlib stream inflating to that.
Colour: ``imageSize == W*H*3`` -> raw R,G,B; ``0`` -> no colour (black); else JPEG. Logger2 wrote
its RGB buffer to the JPEG encoder as if it were BGR, so a standard decoder returns R and B swapped;
``jpeg_swap_rb=True`` (default) undoes that. ``raw_swap_rb`` swaps raw payloads (default False).

The file is never read whole: the constructor scans the record headers once (seeking past the
payloads) and keeps one offset per frame; :meth:`load_frame` opens, seeks and reads one record.
"""

from __future__ import annotations

import logging
import struct
import zlib
from pathlib import Path

import cv2
import numpy as np
import torch

from data_modules.frame import DatasetError, Frame, intrinsics_from
from data_modules.io import require_file
from data_modules.sequence import SequenceDataset
from data_modules.timestamps import check_monotonic_timestamps

log = logging.getLogger(__name__)

_FILE_HEADER = struct.Struct("<i")
_FRAME_HEADER = struct.Struct("<qii")


class KLGSequence(SequenceDataset):
    """A KLG log file.

    Args:
        root: path to the ``.klg`` file.
        width, height: image size (the format does not store it).
        fx, fy, cx, cy: intrinsics in pixels (Teddy defaults: Co-Fusion's 528, 528, 320, 240).
        depth_scale: depth units per metre (1000 = millimetres).
        jpeg_swap_rb: undo Logger2's red/blue swap in JPEG colour payloads.
        raw_swap_rb: swap red/blue in raw colour payloads (logs from other tools).
        name: sequence name (default: the file name without extension).
        readout_s: the camera's rolling-shutter readout in seconds (0 = a global shutter; the Xtion: 0.03).
    """

    def __init__(
        self,
        root: str | Path,
        width: int = 640,
        height: int = 480,
        fx: float = 528.0,
        fy: float = 528.0,
        cx: float = 320.0,
        cy: float = 240.0,
        depth_scale: float = 1000.0,
        jpeg_swap_rb: bool = True,
        raw_swap_rb: bool = False,
        name: str | None = None,
        readout_s: float = 0.0,
    ) -> None:
        self.path = require_file(root, "KLG log")
        self.name = name or self.path.stem
        self.intrinsics = intrinsics_from("dataset", fx, fy, cx, cy, width, height, readout_s)
        if not depth_scale > 0:
            raise DatasetError("dataset.depth_scale", f"must be > 0, got {depth_scale}")
        self.depth_scale = float(depth_scale)
        self.jpeg_swap_rb = bool(jpeg_swap_rb)
        self.raw_swap_rb = bool(raw_swap_rb)
        self.has_gt_poses = False
        self.has_masks = False
        self._index()

    # ------------------------------------------------------------------------------------------
    def _err(self, frame: int | None, problem: str) -> DatasetError:
        """``<file>: <problem>`` or ``<file>: frame <k>: <problem>``."""
        return DatasetError(self.path if frame is None else f"{self.path}: frame {frame}", problem)

    def _index(self) -> None:
        w, h = self.intrinsics.width, self.intrinsics.height
        raw_depth, raw_rgb = w * h * 2, w * h * 3
        size = self.path.stat().st_size
        offsets: list[int] = []
        stamps: list[int] = []
        sizes: list[tuple[int, int]] = []
        with open(self.path, "rb") as f:
            head = f.read(_FILE_HEADER.size)
            if len(head) < _FILE_HEADER.size:
                raise self._err(None, f"too short for a KLG header ({size} bytes)")
            (count,) = _FILE_HEADER.unpack(head)
            if count < 0:
                raise self._err(None, f"negative frame count {count} in the header")
            pos = _FILE_HEADER.size
            k = 0
            while pos < size:
                left = size - pos
                if left < _FRAME_HEADER.size:
                    raise self._err(k, f"record header truncated (expected {_FRAME_HEADER.size} bytes, {left} left)")
                f.seek(pos)
                ts, dsize, isize = _FRAME_HEADER.unpack(f.read(_FRAME_HEADER.size))
                if dsize <= 0 or dsize > raw_depth:
                    raise self._err(
                        k, f"depth size {dsize} bytes is impossible for {w}x{h} (must be 1..{raw_depth}; wrong width/height or corrupt file?)"
                    )
                if isize < 0:
                    raise self._err(k, f"negative colour size {isize}")
                left -= _FRAME_HEADER.size
                if dsize > left:
                    raise self._err(k, f"depth payload truncated (expected {dsize} bytes, {left} left)")
                left -= dsize
                if isize > left:
                    raise self._err(k, f"colour payload truncated (expected {isize} bytes, {left} left)")
                if isize not in (0, raw_rgb):
                    f.seek(pos + _FRAME_HEADER.size + dsize)
                    if f.read(2) != b"\xff\xd8":
                        raise self._err(k, f"colour payload of {isize} bytes is neither raw {w}x{h}x3 nor a JPEG")
                offsets.append(pos)
                stamps.append(ts)
                sizes.append((dsize, isize))
                pos += _FRAME_HEADER.size + dsize + isize
                k += 1
        if not offsets:
            raise self._err(None, "contains no frames")
        if count > len(offsets):
            raise self._err(len(offsets), f"missing: the header says {count} frames but the file ends after {len(offsets)}")
        if count != len(offsets):
            log.warning("%s: header says %d frames, found %d (unfinished recording?); using all", self.path, count, len(offsets))
        self.header_count = count
        self.offsets = np.asarray(offsets, dtype=np.int64)
        self.payload_sizes = np.asarray(sizes, dtype=np.int64)
        self.timestamps_us = np.asarray(stamps, dtype=np.int64)
        self.timestamps = check_monotonic_timestamps(self.timestamps_us / 1e6, f"{self.path} (frame timestamps)")

    def _read_record(self, i: int) -> tuple[bytes, bytes]:
        dsize, isize = (int(v) for v in self.payload_sizes[i])
        with open(self.path, "rb") as f:
            f.seek(int(self.offsets[i]) + _FRAME_HEADER.size)
            depth = f.read(dsize)
            colour = f.read(isize)
        if len(depth) != dsize or len(colour) != isize:
            raise self._err(i, "file changed since it was indexed (payload truncated)")
        return depth, colour

    def decode_depth(self, i: int, payload: bytes) -> np.ndarray:
        w, h = self.intrinsics.width, self.intrinsics.height
        n = w * h * 2
        if len(payload) != n:
            try:
                payload = zlib.decompress(payload)
            except zlib.error as e:
                raise self._err(i, f"depth payload is neither raw ({n} bytes) nor valid zlib ({e})") from None
            if len(payload) != n:
                raise self._err(i, f"depth inflates to {len(payload)} bytes, expected {n} for {w}x{h} (wrong width/height?)")
        raw = np.frombuffer(payload, dtype="<u2").reshape(h, w)
        return (raw.astype(np.float32) / np.float32(self.depth_scale)).astype(np.float32)

    def decode_colour(self, i: int, payload: bytes) -> np.ndarray:
        w, h = self.intrinsics.width, self.intrinsics.height
        if len(payload) == 0:
            return np.zeros((h, w, 3), dtype=np.float32)
        if len(payload) == w * h * 3:
            rgb = np.frombuffer(payload, dtype=np.uint8).reshape(h, w, 3)
            if self.raw_swap_rb:
                rgb = rgb[:, :, ::-1]
        else:
            bgr = cv2.imdecode(np.frombuffer(payload, dtype=np.uint8), cv2.IMREAD_COLOR)
            if bgr is None:
                raise self._err(i, "cannot decode the JPEG colour payload")
            if bgr.shape[:2] != (h, w):
                raise self._err(i, f"JPEG colour is {bgr.shape[1]}x{bgr.shape[0]}, expected {w}x{h}")
            # standard RGB is bgr[..., ::-1]; Logger2 swapped R and B, so undoing that gives bgr as is
            rgb = bgr if self.jpeg_swap_rb else bgr[:, :, ::-1]
        return np.ascontiguousarray(rgb).astype(np.float32) / np.float32(255.0)

    def load_frame(self, i: int) -> Frame:
        depth_b, colour_b = self._read_record(i)
        depth = self.decode_depth(i, depth_b)
        rgb = self.decode_colour(i, colour_b)
        frame = Frame(
            index=i,
            timestamp=float(self.timestamps[i]),
            rgb=torch.from_numpy(np.ascontiguousarray(rgb)),
            depth=torch.from_numpy(np.ascontiguousarray(depth)),
        )
        return frame.validate(f"{self.path}: frame {i}", self.intrinsics)

    def describe(self) -> dict[str, object]:
        d = super().describe()
        d["header_frame_count"] = int(self.header_count)
        return d
