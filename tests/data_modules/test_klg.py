"""KLG log reader on tiny self-written logs."""

import struct
import sys
import zlib
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parent))
from fixtures import H, W, klg_record, make_klg  # noqa: E402

from data_modules.frame import DatasetError  # noqa: E402
from data_modules.klg import KLGSequence  # noqa: E402


def _open(path, **kw):
    return KLGSequence(path, width=W, height=H, fx=20, fy=20, cx=16, cy=12, **kw)


def test_round_trip_mixed_frames(tmp_path):
    truth = make_klg(tmp_path / "teddy.klg")
    ds = _open(tmp_path / "teddy.klg")
    assert ds.name == "teddy" and len(ds) == 3
    assert not ds.has_gt_poses and not ds.has_masks
    np.testing.assert_array_equal(ds.timestamps, np.array(truth.ts_us) / 1e6)
    assert ds.offsets.tolist() == truth.offsets
    for i in range(3):
        f = ds[i]
        assert f.mask is None and f.gt_pose is None and f.source is None  # one log file, no file per frame
        np.testing.assert_array_equal(f.depth.numpy(), truth.depth_mm[i].astype(np.float32) / 1000.0)
        rgb8 = np.round(f.rgb.numpy() * 255).astype(int)
        if truth.modes[i][1] == "jpeg":
            # Logger2 JPEG: with the default swap the true colours come back (lossy codec)
            assert np.abs(rgb8 - truth.rgb[i]).max() <= 8
        else:
            np.testing.assert_array_equal(rgb8, truth.rgb[i])


def test_jpeg_swap_switch(tmp_path):
    truth = make_klg(tmp_path / "a.klg", modes=[("raw", "jpeg"), ("raw", "raw")])
    ds = _open(tmp_path / "a.klg", jpeg_swap_rb=False, raw_swap_rb=True)
    rgb8 = np.round(ds[0].rgb.numpy() * 255).astype(int)
    assert np.abs(rgb8 - truth.rgb[0][:, :, ::-1]).max() <= 8
    np.testing.assert_array_equal(np.round(ds[1].rgb.numpy() * 255).astype(int), truth.rgb[1][:, :, ::-1])


def test_header_count_zero_reads_to_eof(tmp_path, caplog):
    make_klg(tmp_path / "a.klg", header_count=0)
    ds = _open(tmp_path / "a.klg")
    assert len(ds) == 3 and ds.header_count == 0
    assert "header says 0 frames" in caplog.text


def test_lazy_reads_only_one_record(tmp_path, monkeypatch):
    make_klg(tmp_path / "a.klg", modes=[("raw", "raw")] * 4)
    ds = _open(tmp_path / "a.klg")
    import builtins

    reads = []
    real_open = builtins.open

    class Spy:
        def __init__(self, f):
            self.f = f

        def __enter__(self):
            return self

        def __exit__(self, *a):
            self.f.close()

        def seek(self, *a):
            return self.f.seek(*a)

        def read(self, n=-1):
            assert n >= 0, "must not read the whole file"
            data = self.f.read(n)
            reads.append(len(data))
            return data

    monkeypatch.setattr(builtins, "open", lambda *a, **k: Spy(real_open(*a, **k)))
    ds[2]
    assert sum(reads) == W * H * 2 + W * H * 3


def test_defaults_are_teddy(tmp_path):
    truth = make_klg(tmp_path / "big.klg", modes=[("zlib", "none")], w=640, h=480)
    ds = KLGSequence(tmp_path / "big.klg")
    k = ds.intrinsics
    assert (k.fx, k.fy, k.cx, k.cy, k.width, k.height) == (528, 528, 320, 240, 640, 480)
    np.testing.assert_array_equal(ds[0].depth.numpy(), truth.depth_mm[0] / np.float32(1000))


# ----------------------------------------------------------------------------------- bad input


def test_principal_point_outside_the_image(tmp_path):
    make_klg(tmp_path / "a.klg")
    with pytest.raises(DatasetError, match=rf"^dataset: principal point \(cx=5000, cy=12\) is outside the {W}x{H} image"):
        KLGSequence(tmp_path / "a.klg", width=W, height=H, fx=20, fy=20, cx=5000, cy=12)
    with pytest.raises(DatasetError, match=r"^dataset: principal point \(cx=320, cy=240\) is outside"):
        KLGSequence(tmp_path / "a.klg", width=W, height=H)  # teddy defaults are for 640x480


def test_missing_file(tmp_path):
    with pytest.raises(DatasetError, match=r"teddy\.klg: KLG log not found"):
        _open(tmp_path / "teddy.klg")
    with pytest.raises(DatasetError, match=r"is not a regular file"):
        _open(tmp_path)


def test_truncated_depth_payload(tmp_path):
    make_klg(tmp_path / "teddy.klg", modes=[("raw", "raw")] * 3)
    data = (tmp_path / "teddy.klg").read_bytes()
    rec = 16 + W * H * 5
    cut = 4 + 2 * rec + 16 + 20
    (tmp_path / "teddy.klg").write_bytes(data[:cut])
    with pytest.raises(DatasetError) as e:
        _open(tmp_path / "teddy.klg")
    assert str(e.value).endswith(f"teddy.klg: frame 2: depth payload truncated (expected {W * H * 2} bytes, 20 left)")


def test_truncated_colour_and_header(tmp_path):
    make_klg(tmp_path / "a.klg", modes=[("raw", "raw")] * 2)
    data = (tmp_path / "a.klg").read_bytes()
    (tmp_path / "a.klg").write_bytes(data[:-5])
    with pytest.raises(DatasetError, match=rf"a\.klg: frame 1: colour payload truncated \(expected {W * H * 3} bytes, {W * H * 3 - 5} left\)"):
        _open(tmp_path / "a.klg")
    rec = 16 + W * H * 5
    (tmp_path / "a.klg").write_bytes(data[: 4 + rec + 7])
    with pytest.raises(DatasetError, match=r"a\.klg: frame 1: record header truncated \(expected 16 bytes, 7 left\)"):
        _open(tmp_path / "a.klg")
    (tmp_path / "a.klg").write_bytes(b"\x01\x00")
    with pytest.raises(DatasetError, match=r"a\.klg: too short for a KLG header"):
        _open(tmp_path / "a.klg")


def test_header_count_larger_than_file(tmp_path):
    make_klg(tmp_path / "a.klg", header_count=5)
    with pytest.raises(DatasetError, match=r"a\.klg: frame 3: missing: the header says 5 frames but the file ends after 3"):
        _open(tmp_path / "a.klg")


def test_wrong_resolution(tmp_path):
    make_klg(tmp_path / "a.klg", modes=[("raw", "raw")])
    with pytest.raises(DatasetError, match=r"a\.klg: frame 0: depth size 1536 bytes is impossible for 16x12"):
        KLGSequence(tmp_path / "a.klg", width=16, height=12, cx=8, cy=6)


def test_bad_zlib_and_inflate_size(tmp_path):
    depth = np.ones((H, W), np.uint16)
    bad = struct.pack("<qii", 5, 10, 0) + b"\x78\x01garbage!"
    short = zlib.compress(np.ones(10, np.uint16).tobytes(), 1)
    rec2 = struct.pack("<qii", 6, len(short), 0) + short
    (tmp_path / "a.klg").write_bytes(struct.pack("<i", 3) + bad + rec2 + klg_record(7, depth, None, "raw", "none"))
    ds = _open(tmp_path / "a.klg")
    with pytest.raises(DatasetError, match=r"a\.klg: frame 0: depth payload is neither raw"):
        ds[0]
    with pytest.raises(DatasetError, match=rf"a\.klg: frame 1: depth inflates to 20 bytes, expected {W * H * 2}"):
        ds[1]
    assert ds[2].depth.max() == pytest.approx(0.001)


def test_colour_neither_raw_nor_jpeg(tmp_path):
    depth = np.ones((H, W), np.uint16).tobytes()
    (tmp_path / "a.klg").write_bytes(struct.pack("<i", 1) + struct.pack("<qii", 1, len(depth), 4) + depth + b"abcd")
    with pytest.raises(DatasetError, match=r"a\.klg: frame 0: colour payload of 4 bytes is neither raw"):
        _open(tmp_path / "a.klg")


def test_non_monotonic_timestamps(tmp_path):
    depth = np.ones((H, W), np.uint16)
    recs = [klg_record(ts, depth, None, "raw", "none") for ts in (100, 200, 150)]
    (tmp_path / "a.klg").write_bytes(struct.pack("<i", 3) + b"".join(recs))
    with pytest.raises(DatasetError, match=r"a\.klg \(frame timestamps\): timestamps are not strictly increasing at entry 2"):
        _open(tmp_path / "a.klg")


def test_config_instantiates(tmp_path):
    from fixtures import instantiate_dataset

    truth = make_klg(tmp_path / "teddy-handover.klg", modes=[("zlib", "none")], w=640, h=480)
    ds = instantiate_dataset("teddy", tmp_path / "teddy-handover.klg")
    assert isinstance(ds, KLGSequence) and ds.name == "teddy" and len(ds) == 1
    assert (ds.intrinsics.fx, ds.intrinsics.width) == (528.0, 640)
    np.testing.assert_array_equal(ds[0].depth.numpy(), truth.depth_mm[0] / np.float32(1000))
    with pytest.raises(DatasetError, match=r"wrong\.klg: KLG log not found"):
        instantiate_dataset("teddy", tmp_path / "wrong.klg")


# the fixture's small image needs a principal point inside it (teddy.yaml is for 640x480)
SMALL_CAMERA = (f"dataset.width={W}", f"dataset.height={H}", "dataset.fx=20", "dataset.fy=20", "dataset.cx=16", "dataset.cy=12")


def test_inspect_summarize_and_cli(tmp_path, capsys):
    import json

    from fixtures import run_inspect_inprocess

    from data_modules.inspect import summarize

    truth = make_klg(tmp_path / "t.klg")
    s = summarize(_open(tmp_path / "t.klg"))
    valid = sum(int((d > 0).sum()) for d in truth.depth_mm) / (3 * W * H)
    assert (s["frames"], s["width"], s["height"]) == (3, W, H)
    assert not s["has_gt_poses"] and not s["has_masks"] and s["dynamic_pct"] is None
    assert s["valid_depth_pct"] == pytest.approx(100 * valid)
    assert s["duration_s"] == pytest.approx(2 * 0.033333)
    status = run_inspect_inprocess(
        "dataset=teddy", f"dataset.root={tmp_path / 't.klg'}", *SMALL_CAMERA, "format=json"
    )
    out = capsys.readouterr()
    assert status == 0, out.err
    cli = json.loads(out.out.strip().splitlines()[-1])
    assert (cli["frames"], cli["width"], cli["has_gt_poses"]) == (3, W, False)
    assert cli["valid_depth_pct"] == pytest.approx(100 * valid)
    # truncated log: one line naming the file and the frame
    data = (tmp_path / "t.klg").read_bytes()
    (tmp_path / "t.klg").write_bytes(data[:-3])
    status = run_inspect_inprocess("dataset=teddy", f"dataset.root={tmp_path / 't.klg'}", *SMALL_CAMERA)
    assert status == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"error: {tmp_path / 't.klg'}: frame 2: depth payload truncated")
