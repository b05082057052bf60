"""What every command-line entry point shares: the default config nodes and the one-line errors.

Bad input -- a missing or corrupt file, a setting outside its range, a missing mandatory value, a
file that cannot be written (full disk, read-only folder: any OSError, named by its path) -- ends a
command with one line ``error: <where>: <problem>`` on stderr and exit status 2, never a
traceback; a run whose result is unusable (:class:`tivne.utils.RunFailed`, e.g. most frames not
tracked) ends with one such line and exit status 3, after its results are written.
:func:`one_line_errors` wraps a Hydra task function to do that; the exceptions it turns into such a
line are :data:`BAD_INPUT` (also when Hydra's ``instantiate`` wrapped them). In a multirun (``-m``)
the line is printed and :class:`JobFailed` raised instead of exiting, so the launcher records that
one job as failed (an Optuna trial as FAIL) and the other jobs still run. :class:`RunDirGuard`
applies the run-directory rules of ``tivne.train`` before Hydra writes into the folder.
"""

from __future__ import annotations

import functools
import os
import re
import sys
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

from hydra.core.config_store import ConfigStore
from hydra.core.hydra_config import HydraConfig
from hydra.experimental.callback import Callback
from hydra.types import RunMode
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

from data_modules.errors import BAD_INPUT as DATA_BAD_INPUT
from data_modules.errors import EXIT_BAD_INPUT, error_line, find_cause
from data_modules.sequence import SequenceView
from tivne import runlock
from tivne.config import (
    SECTIONS,
    ConfigError,
    MeshConfig,
    MeshEvalSettings,
    RenderConfig,
    ReportConfig,
    RunDirConfig,
    default_tree,
)
from tivne.inputs import RUN_KEYS, check_known_keys, check_run_inputs, check_stream_inputs  # noqa: F401 (the commands use them through cli)
from tivne.masks.settings import default_nodes
from tivne.readers import DataConfig, check_dataset_node
from tivne.slam.checkpoint import check_resumable
from tivne.slam.outputs import RunDir, check_run_dir
from tivne.utils import RunFailed

BAD_INPUT: tuple[type[BaseException], ...] = (*DATA_BAD_INPUT, ConfigError)
THREADS_RESOLVER = "tivne.threads_per_job"


class JobFailed(Exception):
    """One job of a multirun failed; the message is its ``error: ...`` line."""


def register_defaults() -> None:
    """Make the defaults of :mod:`tivne.config` available to the YAML files in ``conf/`` as the
    nodes ``tivne_defaults`` (every SLAM section), ``tivne_mesh`` (``mesh``), ``tivne_evaluate``
    (``mesh`` + ``settings``) and ``tivne_report`` (``report``), and register the resolver
    ``${tivne.threads_per_job:}`` (:func:`threads_per_job`). Untyped on purpose: values are checked
    by the dataclasses, which give one-line errors, rather than by OmegaConf."""
    store = ConfigStore.instance()
    store.store(name="tivne_defaults", node=default_tree(SECTIONS))
    store.store(name="tivne_mesh", node=default_tree((MeshConfig,)))
    store.store(name="tivne_evaluate", node=default_tree((MeshConfig, MeshEvalSettings)))
    store.store(name="tivne_report", node=default_tree((ReportConfig,)))
    for name, node in default_nodes().items():  # conf/masks/<name>.yaml: the provider and its defaults
        store.store(group="tivne_masks", name=name, node=node)
    if not OmegaConf.has_resolver(THREADS_RESOLVER):
        OmegaConf.register_new_resolver(THREADS_RESOLVER, lambda: threads_per_job(current_launcher(), usable_cores()))


def usable_cores() -> int:
    """CPU cores this process may run on (its affinity mask, e.g. a Slurm or container limit)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


def current_launcher() -> Mapping[str, Any]:
    """The running job's ``hydra.launcher`` node ({} outside a Hydra job, e.g. the compose API)."""
    if not HydraConfig.initialized():
        return {}
    return HydraConfig.get().get("launcher") or {}


def threads_per_job(launcher: Mapping[str, Any], cores: int) -> int | None:
    """torch threads for one job of a launcher that runs several at once, so they share the cores
    instead of oversubscribing them: ``cpus_per_task`` (submitit, Slurm) when set; 1 under
    submitit's local launcher without it (it starts every job of the sweep at once); cores //
    ``n_jobs`` (joblib; -1 = all cores, -2 = all but one, as in joblib); None (torch's default, all
    cores) for a launcher that runs one job at a time. ``runtime.threads=N`` overrides this."""
    if launcher.get("cpus_per_task"):
        return int(launcher["cpus_per_task"])
    if str(launcher.get("_target_", "")).endswith("submitit_launcher.LocalLauncher"):
        return 1
    n_jobs = launcher.get("n_jobs")
    if not n_jobs:
        return None
    concurrent = int(n_jobs) if n_jobs > 0 else max(1, cores + 1 + int(n_jobs))
    return max(1, cores // concurrent)


def run_sequence(run_dir: str | Path) -> tuple[SequenceView, RenderConfig]:
    """The sequence as a run streamed it and the run's render settings, rebuilt from its own
    run_dir/.hydra/config.yaml -- data, never code: the dataset node must name one of TivNe's
    readers with checked arguments (:func:`tivne.readers.check_dataset_node`) before anything is
    instantiated, and ``data`` / ``render`` are checked sections."""
    root = Path(run_dir)
    if not root.is_dir():
        raise FileNotFoundError(f"{root}: run directory not found")
    config = root / ".hydra" / "config.yaml"
    if not config.is_file():
        raise FileNotFoundError(f"{config}: run config not found")
    cfg = OmegaConf.load(config)
    if "dataset" not in cfg:
        raise ConfigError(f"{config}: no dataset node; not a config written by tivne.train")
    dataset, data, render = (saved_section(cfg, config, key) for key in ("dataset", "data", "render"))
    check_dataset_node(dataset)
    view = DataConfig.from_mapping(data).view_kwargs()
    return SequenceView(instantiate(cfg.dataset), **view), RenderConfig.from_mapping(render)


# Top-level keys of a training config besides the checked sections (tivne.config.SECTIONS).
def saved_section(cfg: DictConfig, config: Path, key: str) -> dict[str, Any]:
    """``cfg[key]`` of a saved run config as plain values ({} when absent), refused in one line
    naming the file when it is not a mapping or does not resolve."""
    if key not in cfg:
        return {}
    node = cfg[key]
    if not isinstance(node, DictConfig):
        raise ConfigError(f"{config}: {key}={node!r}: must be a mapping")
    try:
        return OmegaConf.to_container(node, resolve=True, throw_on_missing=False)  # type: ignore[return-value]
    except OmegaConfBaseException as exc:
        raise ConfigError(f"{config}: {key}: " + str(exc).splitlines()[0]) from None


def bad_input_cause(exc: BaseException) -> BaseException | None:
    """The first :data:`BAD_INPUT` exception in ``exc``'s cause/context chain, or None."""
    return find_cause(exc, BAD_INPUT)


def in_multirun() -> bool:
    """True inside a job of ``python -m ... -m`` (a sweep)."""
    return HydraConfig.initialized() and HydraConfig.get().mode == RunMode.MULTIRUN


def fail(line: str, exit_code: int) -> None:
    """Print ``line``; exit with ``exit_code``, or in a multirun raise :class:`JobFailed` (exiting
    would end the whole sweep, and a launcher's worker process with it)."""
    print(line, file=sys.stderr)
    if in_multirun():
        raise JobFailed(line) from None
    sys.exit(exit_code)


def one_line_errors(task: Callable[..., Any]) -> Callable[..., Any]:
    """Wrap a command's body: bad input becomes :func:`error_line` and exit status 2 (see :func:`fail`)."""

    @functools.wraps(task)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        try:
            return task(*args, **kwargs)
        except RunFailed as exc:
            fail(error_line(exc), exc.exit_code)
        except Exception as exc:  # noqa: BLE001 -- only bad input is turned into one line
            report_bad_input(exc)
            raise

    return wrapper


def report_bad_input(exc: BaseException) -> None:
    """Exit (see :func:`fail`) with :func:`error_line` and status 2 when ``exc`` is bad input; otherwise do nothing."""
    cause = bad_input_cause(exc)
    if cause is not None:
        fail(error_line(cause), EXIT_BAD_INPUT)


class RunDirGuard(Callback):
    """Hydra callback of ``tivne.train`` (``hydra.callbacks`` in conf/config.yaml): the rules of
    :func:`tivne.slam.outputs.check_run_dir` before Hydra writes ``.hydra/`` and the log into the run
    directory, so a refused folder keeps its earlier config and results untouched, and a resume is
    compared with the config the run was started with."""

    def on_run_start(self, config: DictConfig, **kwargs: Any) -> None:
        try:
            run = RunDir(OmegaConf.select(config, "hydra.run.dir"))
            runlock.check_free(run.root)  # a live writer is named first, whatever the folder holds
            options = RunDirConfig.from_mapping({key: config.get(key, False) for key in ("resume", "overwrite")})
            saved = current = None
            if options.resume and run.config.is_file():
                saved = OmegaConf.to_container(OmegaConf.load(run.config), resolve=False)
                current = {k: v for k, v in OmegaConf.to_container(config, resolve=False).items() if k != "hydra"}
            check_run_dir(run, options.resume, options.overwrite, saved, current)
            if options.resume:
                check_resumable(run.checkpoint)
            runlock.acquire(run.root)  # one writer per folder, before Hydra writes .hydra/ there
            try:  # again under the lock: a run that held it may have written results meanwhile
                check_run_dir(run, options.resume, options.overwrite, saved, current)
            except BaseException:
                runlock.release(run.root)
                raise
        except Exception as exc:  # noqa: BLE001 -- bad input becomes one line; anything else is a bug
            report_bad_input(exc)
            raise

    def on_run_end(self, config: DictConfig, **kwargs: Any) -> None:
        runlock.release(OmegaConf.select(config, "hydra.run.dir"))


def mesh_settings(node: DictConfig) -> MeshConfig:
    """The ``mesh`` section as a checked MeshConfig (a single time may be given without brackets)."""
    values = OmegaConf.to_container(node, resolve=True)
    if values.get("times") is not None and not isinstance(values["times"], list):
        values["times"] = [values["times"]]  # mesh.times=1.5
    return MeshConfig.from_mapping(values)


# ------------------------------------------------------------------------------------------------
# run_dir= as a user copies it (the post-run commands: view, mesh, evaluate, report)
# ------------------------------------------------------------------------------------------------


def quote_run_dir(argv: list[str]) -> list[str]:
    """``argv`` with the value of ``run_dir=...`` quoted for Hydra's override grammar, so a sweep's
    job dir (``multirun/<time>/0_experiment=smoke,seed=0``: ``hydra.sweep.subdir`` names it from
    its overrides) is taken as the path it is, without quoting tricks. A value already quoted is
    left alone; backslashes and single quotes in the path are escaped."""
    out = list(argv[:1])
    for arg in argv[1:]:
        key, sep, value = arg.partition("=")
        if key == "run_dir" and sep and value and value[0] not in "'\"":
            # In Hydra's quoted strings a backslash escapes only before a quote (or the closing one).
            escaped = re.sub(r"(\\*)('|$)", lambda m: m.group(1) * 2 + ("\\'" if m.group(2) else ""), value, count=0)
            arg = f"run_dir='{escaped}'"
        out.append(arg)
    return out
