"""What every command-line entry point shares: the default config nodes and the one-line errors.

Bad input -- a missing or corrupt file, a setting outside its range, a missing mandatory value, a
file that cannot be written (full disk, read-only folder: any OSError, named by its path) -- ends a
command with one line ``error: <where>: <problem>`` on stderr and exit status 2, never a
traceback; a run whose result is unusable (:class:`tivne.utils.RunFailed`, e.g. most frames not
tracked) ends with one such line and exit status 3, after its results are written.
:func:`one_line_errors` wraps a Hydra task function to do that; the exceptions it turns into such a
line are :data:`BAD_INPUT` (also when Hydra's ``instantiate`` wrapped them). :class:`RunDirGuard`
applies the run-directory rules of ``tivne.train`` before Hydra writes into the folder.
"""

from __future__ import annotations

import functools
import re
import sys
from collections.abc import Callable
from typing import Any

from hydra.core.config_store import ConfigStore
from hydra.experimental.callback import Callback
from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import MissingMandatoryValue

from data_modules.frame import DatasetError
from tivne.config import (
    SECTIONS,
    ConfigError,
    MeshConfig,
    MeshEvalSettings,
    RunDirConfig,
    default_tree,
)
from tivne.slam.checkpoint import check_resumable
from tivne.slam.outputs import RunDir, check_run_dir
from tivne.utils import RunFailed

EXIT_BAD_INPUT = 2
BAD_INPUT: tuple[type[BaseException], ...] = (DatasetError, ConfigError, MissingMandatoryValue, OSError)


def register_defaults() -> None:
    """Make the defaults of :mod:`tivne.config` available to the YAML files in ``conf/`` as the
    nodes ``tivne_defaults`` (every SLAM section), ``tivne_mesh`` (``mesh``) and ``tivne_evaluate``
    (``mesh`` + ``settings``). Untyped on purpose: values are checked by the dataclasses, which
    give one-line errors, rather than by OmegaConf."""
    store = ConfigStore.instance()
    store.store(name="tivne_defaults", node=default_tree(SECTIONS))
    store.store(name="tivne_mesh", node=default_tree((MeshConfig,)))
    store.store(name="tivne_evaluate", node=default_tree((MeshConfig, MeshEvalSettings)))


def bad_input_cause(exc: BaseException) -> BaseException | None:
    """The first :data:`BAD_INPUT` exception in ``exc``'s cause/context chain, or None."""
    seen: set[int] = set()
    current: BaseException | None = exc
    while current is not None and id(current) not in seen:
        seen.add(id(current))
        if isinstance(current, BAD_INPUT):
            return current
        current = current.__cause__ or current.__context__
    return None


def error_line(exc: BaseException) -> str:
    """``error: ...`` in one line for a bad-input exception."""
    if isinstance(exc, MissingMandatoryValue):
        key = getattr(exc, "full_key", None) or ""
        text = f"missing mandatory config value {key!r} (set it on the command line: {key}=...)" if key else str(exc)
    elif isinstance(exc, OSError) and exc.filename is not None:
        text = f"{exc.filename}: {exc.strerror or type(exc).__name__}"
    else:
        text = str(exc) or type(exc).__name__
    first = text.strip().splitlines()[0] if text.strip() else type(exc).__name__
    return "error: " + re.sub(r"\s+", " ", first).strip()


def one_line_errors(task: Callable[..., Any]) -> Callable[..., Any]:
    """Wrap a command's body: bad input becomes :func:`error_line` and exit status 2."""

    @functools.wraps(task)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        try:
            return task(*args, **kwargs)
        except RunFailed as exc:
            print(error_line(exc), file=sys.stderr)
            sys.exit(exc.exit_code)
        except Exception as exc:  # noqa: BLE001 -- only bad input is turned into one line
            report_bad_input(exc)
            raise

    return wrapper


def report_bad_input(exc: BaseException) -> None:
    """Exit with :func:`error_line` and status 2 when ``exc`` is bad input; otherwise do nothing."""
    cause = bad_input_cause(exc)
    if cause is not None:
        print(error_line(cause), file=sys.stderr)
        sys.exit(EXIT_BAD_INPUT)


class RunDirGuard(Callback):
    """Hydra callback of ``tivne.train`` (``hydra.callbacks`` in conf/config.yaml): the rules of
    :func:`tivne.slam.outputs.check_run_dir` before Hydra writes ``.hydra/`` and the log into the run
    directory, so a refused folder keeps its earlier config and results untouched, and a resume is
    compared with the config the run was started with."""

    def on_run_start(self, config: DictConfig, **kwargs: Any) -> None:
        try:
            run = RunDir(OmegaConf.select(config, "hydra.run.dir"))
            options = RunDirConfig.from_mapping({key: config.get(key, False) for key in ("resume", "overwrite")})
            saved = current = None
            if options.resume and run.config.is_file():
                saved = OmegaConf.to_container(OmegaConf.load(run.config), resolve=False)
                current = {k: v for k, v in OmegaConf.to_container(config, resolve=False).items() if k != "hydra"}
            check_run_dir(run, options.resume, options.overwrite, saved, current)
            if options.resume:
                check_resumable(run.checkpoint)
        except Exception as exc:  # noqa: BLE001 -- bad input becomes one line; anything else is a bug
            report_bad_input(exc)
            raise


def mesh_settings(node: DictConfig) -> MeshConfig:
    """The ``mesh`` section as a checked MeshConfig (a single time may be given without brackets)."""
    values = OmegaConf.to_container(node, resolve=True)
    if values.get("times") is not None and not isinstance(values["times"], list):
        values["times"] = [values["times"]]  # mesh.times=1.5
    return MeshConfig.from_mapping(values)
