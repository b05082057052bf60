"""Shared readers in data_modules.io: images, EXR, text tables, intrinsics files."""

import sys
from pathlib import Path

import numpy as np
import pytest
import torch

sys.path.insert(0, str(Path(__file__).parent))
from fixtures import (  # noqa: E402
    random_pose,
    write_exr,
    write_png8,
    write_png16,
    write_png_rgb,
    write_poses,
)

from data_modules.frame import DatasetError  # noqa: E402
from data_modules.io import (
    read_depth_png,
    read_exr_depth,
    read_mask_png,
    read_rgb,
    require_dir,
    sanitize_depth,
    write_mask_png,
)
from data_modules.tables import (
    finite_float,
    integer,
    read_intrinsics_file,
    read_pose_table,
    read_table,
    read_tum_trajectory,
    write_tum_trajectory,
)


def test_rgb_png_round_trip(tmp_path):
    rgb = np.random.default_rng(0).integers(0, 256, (6, 5, 3), dtype=np.uint8)
    write_png_rgb(tmp_path / "a.png", rgb)
    out = read_rgb(tmp_path / "a.png")
    assert out.dtype == np.float32 and out.shape == (6, 5, 3)
    np.testing.assert_array_equal(np.round(out * 255).astype(np.uint8), rgb)


def test_rgb_gray_and_16bit(tmp_path):
    write_png8(tmp_path / "g.png", np.full((3, 4), 51, np.uint8))
    assert np.allclose(read_rgb(tmp_path / "g.png"), 0.2)
    write_png16(tmp_path / "c16.png", np.full((3, 4, 3), 65535, np.uint16))
    assert np.allclose(read_rgb(tmp_path / "c16.png"), 1.0)


def test_depth_png16(tmp_path):
    raw = np.array([[0, 5000], [10000, 65535]], np.uint16)
    write_png16(tmp_path / "d.png", raw)
    d = read_depth_png(tmp_path / "d.png", 5000.0)
    assert d.dtype == np.float32
    np.testing.assert_allclose(d, raw / 5000.0, rtol=1e-7)


def test_depth_png_8bit_rejected(tmp_path):
    write_png8(tmp_path / "d.png", np.ones((3, 3), np.uint8))
    with pytest.raises(DatasetError, match=r"d\.png: depth image is uint8, expected 16-bit"):
        read_depth_png(tmp_path / "d.png", 1000.0)


def test_unreadable_png(tmp_path):
    (tmp_path / "bad.png").write_bytes(b"\x89PNG garbage")
    with pytest.raises(DatasetError, match=r"bad\.png: cannot decode image") as e:
        read_rgb(tmp_path / "bad.png")
    assert "\n" not in str(e.value)
    (tmp_path / "empty.png").write_bytes(b"")
    with pytest.raises(DatasetError, match="empty"):
        read_depth_png(tmp_path / "empty.png", 1000.0)
    with pytest.raises(DatasetError, match="not found"):
        read_rgb(tmp_path / "nope.png")


def test_mask_png(tmp_path):
    m = np.array([[0, 1], [255, 0]], np.uint8)
    write_png8(tmp_path / "m.png", np.repeat(m[:, :, None], 3, axis=2))
    np.testing.assert_array_equal(read_mask_png(tmp_path / "m.png"), m != 0)


def test_mask_png_round_trip_colour_and_size(tmp_path):
    m = np.zeros((6, 8), bool)
    m[1:3, 2:5] = True
    write_mask_png(tmp_path / "w.png", torch.from_numpy(m))
    assert not list(tmp_path.glob(".*tmp"))  # written atomically
    np.testing.assert_array_equal(read_mask_png(tmp_path / "w.png", size=(8, 6)), m)
    red = np.zeros((6, 8, 3), np.uint8)
    red[m] = (255, 0, 0)  # red on black: OpenCV's channel 0 (blue) is empty
    write_png_rgb(tmp_path / "red.png", red)
    np.testing.assert_array_equal(read_mask_png(tmp_path / "red.png"), m)
    with pytest.raises(DatasetError, match=r"w\.png: mask is 8x6 but the frame is 6x8"):
        read_mask_png(tmp_path / "w.png", size=(6, 8))


@pytest.mark.parametrize("half", [False, True])
@pytest.mark.parametrize("chans", ["Y", "RGB", "Z", "only"])
def test_exr_channels(tmp_path, half, chans):
    d = np.arange(12, dtype=np.float32).reshape(3, 4) / 4
    other = np.full_like(d, 7.0)
    channels = {
        "Y": {"Y": d},
        "RGB": {"R": d, "G": other, "B": other},
        "Z": {"Z": d},
        "only": {"depthmap": d},
    }[chans]
    write_exr(tmp_path / "d.exr", channels, half=half)
    out = read_exr_depth(tmp_path / "d.exr")
    assert out.dtype == np.float32
    np.testing.assert_array_equal(out, d)


def test_exr_y_preferred_over_r(tmp_path):
    d = np.ones((2, 2), np.float32)
    write_exr(tmp_path / "d.exr", {"R": d * 2, "Y": d})
    np.testing.assert_array_equal(read_exr_depth(tmp_path / "d.exr"), d)


def test_exr_without_usable_channel(tmp_path):
    d = np.ones((2, 2), np.float32)
    write_exr(tmp_path / "d.exr", {"foo": d, "bar": d})
    with pytest.raises(DatasetError, match=r"d\.exr: no usable depth channel \(have \['bar', 'foo'\]"):
        read_exr_depth(tmp_path / "d.exr")


def test_exr_garbage(tmp_path):
    (tmp_path / "d.exr").write_bytes(b"not an exr")
    with pytest.raises(DatasetError, match=r"d\.exr: cannot read EXR file") as e:
        read_exr_depth(tmp_path / "d.exr")
    assert "\n" not in str(e.value)


def test_sanitize_depth():
    d = np.array([1.0, np.nan, np.inf, -np.inf, -1.0, 0.0, 150.0, 99.0], np.float32)
    np.testing.assert_array_equal(sanitize_depth(d, 100.0), [1, 0, 0, 0, 0, 0, 0, 99])


def test_read_table_types_and_comments(tmp_path):
    p = tmp_path / "t.txt"
    p.write_text("# header\n\n1.5 a.png\n2,b.png\n")
    rows = read_table(p, [("t", finite_float), ("name", str)])
    assert [r.values for r in rows] == [(1.5, "a.png"), (2.0, "b.png")]
    assert [r.lineno for r in rows] == [3, 4]


@pytest.mark.parametrize(
    "text,pattern",
    [
        ("1 2\nx y\n", r"t\.txt:2: bad a 'x'"),
        ("1 2\n3\n", r"t\.txt:2: expected 2 fields \(a b\), got 1"),
        ("1 2 3\n", r"t\.txt:1: expected 2 fields"),
        ("nan 1\n", r"t\.txt:1: bad a 'nan'"),
        ("# only comments\n", r"t\.txt: file has no data lines"),
    ],
)
def test_read_table_errors(tmp_path, text, pattern):
    p = tmp_path / "t.txt"
    p.write_text(text)
    with pytest.raises(DatasetError, match=pattern):
        read_table(p, [("a", finite_float), ("b", finite_float)])


def test_integer_converter():
    assert integer("12") == 12 and integer("12.0") == 12
    with pytest.raises(ValueError):
        integer("1.5")


def test_pose_table_round_trip(tmp_path):
    rng = np.random.default_rng(1)
    poses = [random_pose(rng) for _ in range(3)]
    write_poses(tmp_path / "p.txt", ["1", "2", "5"], poses)
    keys, out = read_pose_table(tmp_path / "p.txt", key="frame")
    assert keys.tolist() == [1, 2, 5]
    assert out.dtype == torch.float64
    np.testing.assert_allclose(out.numpy(), np.stack(poses), atol=1e-9)


@pytest.mark.parametrize(
    "line,pattern",
    [
        ("2 0 0 0 0 0 0", r"p\.txt:3: expected 8 fields"),
        ("2 0 0 zero 0 0 0 1", r"p\.txt:3: bad tz 'zero'"),
        ("2 0 0 0 0 0 0 0", r"p\.txt:3: zero quaternion"),
        ("1 0 0 0 0 0 0 1", r"p\.txt:3: timestamp 1\.0 is not after"),
    ],
)
def test_pose_table_malformed(tmp_path, line, pattern):
    p = tmp_path / "p.txt"
    p.write_text(f"# ts tx ty tz qx qy qz qw\n1 0 0 0 0 0 0 1\n{line}\n")
    with pytest.raises(DatasetError, match=pattern):
        read_pose_table(p)


class TestTumTrajectory:
    def test_write_read_round_trip(self, tmp_path):
        rng = np.random.default_rng(12)
        T = torch.from_numpy(np.stack([random_pose(rng) for _ in range(25)]))
        T[:, :3, 3] *= 3.0
        ts = 1305031102.175304 + np.cumsum(np.random.default_rng(0).uniform(0.02, 0.05, 25))
        path = tmp_path / "traj.txt"
        write_tum_trajectory(path, ts, T)
        ts2, T2 = read_tum_trajectory(path)
        assert ts2.dtype == np.float64 and T2.dtype == torch.float64 and T2.shape == (25, 4, 4)
        assert np.abs(ts2 - ts).max() < 1e-6
        assert (T2 - T).abs().max() < 1e-8
        assert [p.name for p in tmp_path.iterdir()] == ["traj.txt"]  # atomic_write left no temporary file

    def test_comments_blank_lines_and_commas(self, tmp_path):
        path = tmp_path / "t.txt"
        path.write_text("# timestamp tx ty tz qx qy qz qw\n\n  # indented comment\n1.0 1 2 3 0 0 0 1\n2.0,0,0,0,0,0,1,0\n")
        ts, T = read_tum_trajectory(path)
        assert ts.tolist() == [1.0, 2.0]
        assert T[0, :3, 3].tolist() == [1.0, 2.0, 3.0]
        assert torch.allclose(T[1, :3, :3], torch.diag(torch.tensor([-1.0, -1.0, 1.0], dtype=torch.float64)))

    @pytest.mark.parametrize(
        "bad",
        ["1.0 1 2 3 0 0 0", "1.0 1 2 3 0 0 0 x", "1.0 1 2 nan 0 0 0 1", "1.0 1 2 3 0 0 0 0"],
        ids=["seven_fields", "not_a_number", "nan", "zero_quaternion"],
    )
    def test_malformed_line_names_file_and_line(self, tmp_path, bad):
        path = tmp_path / "bad.txt"
        path.write_text(f"# header\n0.5 0 0 0 0 0 0 1\n{bad}\n")
        with pytest.raises(DatasetError) as exc:
            read_tum_trajectory(path)
        assert exc.value.where == f"{path}:3"
        assert "\n" not in str(exc.value)

    def test_missing_file(self, tmp_path):
        with pytest.raises(DatasetError, match="not found"):
            read_tum_trajectory(tmp_path / "nope.txt")

    def test_empty_file(self, tmp_path):
        path = tmp_path / "empty.txt"
        path.write_text("# only a comment\n")
        with pytest.raises(DatasetError, match="no poses"):
            read_tum_trajectory(path)

    def test_length_mismatch(self, tmp_path):
        with pytest.raises(ValueError):
            write_tum_trajectory(tmp_path / "x.txt", [0.0, 1.0], torch.eye(4, dtype=torch.float64)[None])


def test_intrinsics_files(tmp_path):
    (tmp_path / "c.txt").write_text("360 361 320 240 640 480\n")
    k = read_intrinsics_file(tmp_path / "c.txt")
    assert (k.fx, k.fy, k.cx, k.cy, k.width, k.height) == (360, 361, 320, 240, 640, 480)
    (tmp_path / "c4.txt").write_text("36 36 32 24\n")
    assert read_intrinsics_file(tmp_path / "c4.txt", width=64, height=48).width == 64
    with pytest.raises(DatasetError, match="image size unknown"):
        read_intrinsics_file(tmp_path / "c4.txt")
    (tmp_path / "c3.txt").write_text("360 360 320\n")
    with pytest.raises(DatasetError, match=r"c3\.txt:1: expected 4 to 6 fields"):
        read_intrinsics_file(tmp_path / "c3.txt", width=1, height=1)
    (tmp_path / "c5.txt").write_text("360 360 320 240 640\n")
    with pytest.raises(DatasetError, match=r"c5\.txt:1: expected 4 or 6 numbers"):
        read_intrinsics_file(tmp_path / "c5.txt")
    (tmp_path / "k.json").write_text('{"fx": 1, "fy": 2, "cx": 3, "cy": 4}')
    assert read_intrinsics_file(tmp_path / "k.json", 8, 6).cy == 4
    (tmp_path / "bad.json").write_text('{"fx": 1}')
    with pytest.raises(DatasetError, match=r"bad\.json: missing key\(s\) fy, cx, cy"):
        read_intrinsics_file(tmp_path / "bad.json", 8, 6)
    (tmp_path / "neg.txt").write_text("-1 360 320 240 640 480\n")
    with pytest.raises(DatasetError, match=r"neg\.txt: focal lengths must be positive"):
        read_intrinsics_file(tmp_path / "neg.txt")


def test_require_dir(tmp_path):
    with pytest.raises(DatasetError, match=r"nowhere: folder not found"):
        require_dir(tmp_path / "nowhere")
    (tmp_path / "f").write_text("")
    with pytest.raises(DatasetError, match="is not a directory"):
        require_dir(tmp_path / "f")
    with pytest.raises(DatasetError, match="no path given"):
        require_dir("???")
