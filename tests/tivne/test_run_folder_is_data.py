"""Opening a run folder never executes code from it: a shared folder whose .hydra/config.yaml names
another target is refused in one line before anything is instantiated, and what it targets is untouched."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from tivne.cli import run_sequence
from tivne.settings import ConfigError


def hostile_run(root: Path, dataset: dict) -> Path:
    (root / ".hydra").mkdir(parents=True)
    (root / ".hydra" / "config.yaml").write_text(yaml.safe_dump({"dataset": dataset, "data": {"stride": 1}}))
    return root


@pytest.mark.parametrize("make_node, key", [
    (lambda f: {"_target_": "builtins.open", "_args_": [str(f), "w"]}, "dataset._target_='builtins.open'"),
    (lambda f: {"_target_": "data_modules.folder.FolderSequence", "root": "x",
                "intrinsics": {"_target_": "builtins.open", "_args_": [str(f), "w"]}}, "dataset.intrinsics._target_='builtins.open'"),
    (lambda f: {"_target_": "pathlib.Path.write_text", "_args_": [str(f), ""]}, "dataset._target_='pathlib.Path.write_text'"),
])
def test_a_hostile_run_config_is_refused_and_its_target_untouched(tmp_path, make_node, key):
    precious = tmp_path / "precious.txt"
    precious.write_bytes(b"keep me\n")
    run = hostile_run(tmp_path / "run", make_node(precious))
    with pytest.raises(ConfigError, match=key.replace("(", r"\(").replace(".", r"\.")):
        run_sequence(run)
    assert precious.read_bytes() == b"keep me\n"


def test_saved_data_and_render_sections_are_checked(tmp_path):
    run = hostile_run(tmp_path / "run", {"_target_": "data_modules.synthetic.SyntheticSequence", "num_frames": 3})
    config = run / ".hydra" / "config.yaml"
    config.write_text(yaml.safe_dump({"dataset": {"_target_": "data_modules.synthetic.SyntheticSequence"}, "data": {"stride": 1.5}}))
    with pytest.raises(ConfigError, match=r"data.stride=1.5"):
        run_sequence(run)
    config.write_text(yaml.safe_dump({"dataset": {"_target_": "data_modules.synthetic.SyntheticSequence"}, "data": "everything"}))
    with pytest.raises(ConfigError, match=r"config.yaml: data='everything': must be a mapping"):
        run_sequence(run)
    config.write_text(yaml.safe_dump({"data": {}}))
    with pytest.raises(ConfigError, match=r"no dataset node"):
        run_sequence(run)
