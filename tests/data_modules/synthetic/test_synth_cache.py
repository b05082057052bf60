"""Frame cache: keyed folders, atomic round trips, misses on bad files, a warning when unwritable."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from data_modules.synthetic.cache import FrameCache, render_key

PARAMS = {"version": 2, "scene": "cube", "seed": 0, "width": 8, "height": 6, "sensor": {"axial": 1.0}}


def _arrays(seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    return (rng.integers(0, 256, (6, 8, 3), dtype=np.uint8), rng.random((6, 8), dtype=np.float32),
            rng.integers(0, 3, (6, 8), dtype=np.uint8))


def test_round_trip_in_a_keyed_folder(tmp_path):
    cache = FrameCache(tmp_path, "cube", PARAMS)
    assert cache.read(3, 6, 8) is None
    arrays = _arrays()
    cache.write(3, *arrays)
    assert cache.folder == tmp_path / f"cube-{render_key(PARAMS)}" and (cache.folder / "params.json").is_file()
    assert sorted(p.name for p in cache.folder.iterdir()) == ["frame_00003.npz", "params.json"]  # no temp files left
    back = FrameCache(str(tmp_path), "cube", dict(PARAMS)).read(3, 6, 8)
    assert back is not None and all(np.array_equal(a, b) and a.dtype == b.dtype for a, b in zip(arrays, back))


def test_every_parameter_changes_the_key():
    keys = {render_key(PARAMS)}
    for k, v in (("version", 3), ("seed", 1), ("width", 9), ("sensor", {"axial": 0.5})):
        keys.add(render_key({**PARAMS, k: v}))
    assert len(keys) == 5 and render_key(dict(reversed(list(PARAMS.items())))) == render_key(PARAMS)


def test_bad_files_are_misses(tmp_path):
    cache = FrameCache(tmp_path, "cube", PARAMS)
    cache.write(0, *_arrays())
    path = cache.path(0)
    good = path.read_bytes()
    for bad in (b"not a zip file", good[: len(good) // 2], good[:-40]):
        path.write_bytes(bad)
        assert cache.read(0, 6, 8) is None
    path.write_bytes(good)
    assert cache.read(0, 6, 9) is None  # another image size
    assert FrameCache(None, "cube", PARAMS).read(0, 6, 8) is None


def test_unwritable_cache_warns_once(tmp_path):
    blocker = tmp_path / "a_file"
    blocker.write_text("not a folder")  # the cache folder cannot be created under a file (even as root)
    cache = FrameCache(blocker / "cache", "cube", PARAMS)
    with pytest.warns(UserWarning, match="cannot write the frame cache"):
        cache.write(0, *_arrays())
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        cache.write(1, *_arrays())  # silent the second time
    assert cache.read(0, 6, 8) is None
