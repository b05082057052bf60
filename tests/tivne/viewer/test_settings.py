"""The viewer's checked settings: viewer=rerun without rerun-sdk is one line naming the extra;
watching a run is no reason to refuse resuming it."""

from __future__ import annotations

import importlib.util

import pytest

from tivne.config import ConfigError, ViewerConfig
from tivne.slam.outputs import config_differences


def test_viewer_rerun_without_the_sdk_names_the_extra(monkeypatch):
    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "rerun" else real(name, *a))
    with pytest.raises(ConfigError, match=r"pip install -e '\.\[viewer\]'"):
        ViewerConfig.from_mapping({"kind": "rerun"})
    assert ViewerConfig.from_mapping({"kind": "none"}).kind == "none"  # nobody asked for it: no error


@pytest.mark.parametrize("key, value", [("sink", "window"), ("map_points", -1), ("grpc_port", 70000), ("kind", "viser")])
def test_bad_viewer_settings_are_refused(key, value):
    with pytest.raises(ConfigError, match=f"viewer.{key}"):
        ViewerConfig.from_mapping({key: value})


def test_a_viewer_does_not_change_what_resume_compares():
    saved = {"viewer": {"kind": "none"}, "mapping": {"iters": 3}}
    assert config_differences(saved, {"viewer": {"kind": "rerun", "sink": "serve"}, "mapping": {"iters": 3}}) == []
    assert config_differences(saved, {"viewer": {"kind": "rerun"}, "mapping": {"iters": 4}}) == [("mapping.iters", 3, 4)]
