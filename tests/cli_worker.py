"""Several command lines in one fresh interpreter: each ``python -m <module> <args>`` runs through
``runpy`` as ``-m`` runs it (``__main__``, ``sys.argv``), one after another, with its exit status
and its stdout / stderr captured at the file-descriptor level, so torch, Lightning and Hydra are
imported once instead of once per command (~10 s each on 2 cores).

For tests of what commands do with their arguments and files. A test of the process itself (a
signal, a second process) starts its own process. Only the first command of a batch starts with
nothing imported, so a batch puts first the command whose stderr is checked most strictly (it is
the one that would show anything an import prints).

``python tests/cli_worker.py --commands JSON --out FILE`` is the worker; :func:`run_commands`
starts it and waits, :class:`Batch` starts it in the background (its start overlaps the tests that
run meanwhile).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import subprocess
import sys
import tempfile
import traceback
from collections.abc import Iterator, Sequence
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


@contextlib.contextmanager
def captured_fds() -> Iterator[list[str]]:
    """stdout / stderr of this process (file descriptors 1 and 2) into temporary files; the list
    yielded holds [stdout, stderr] once the block ends."""
    files = [tempfile.TemporaryFile(), tempfile.TemporaryFile()]
    saved = [os.dup(1), os.dup(2)]
    sys.stdout.flush(), sys.stderr.flush()
    os.dup2(files[0].fileno(), 1), os.dup2(files[1].fileno(), 2)
    text: list[str] = []
    try:
        yield text
    finally:
        sys.stdout.flush(), sys.stderr.flush()
        os.dup2(saved[0], 1), os.dup2(saved[1], 2)
        for fh, fd in zip(files, saved):
            os.close(fd)
            fh.seek(0)
            text.append(fh.read().decode(errors="replace"))
            fh.close()


def run_module(module: str, args: Sequence[str], patch: contextlib.AbstractContextManager | None = None) -> tuple[int, str, str]:
    """``python -m <module> <args>`` in this process: (exit status, stdout, stderr). An exception
    that escapes is printed as the interpreter prints it, with status 1."""
    import runpy
    import warnings

    sys.argv = [module, *args]
    with captured_fds() as out, warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # runpy: the module was imported before
        with patch if patch is not None else contextlib.nullcontext():
            try:
                runpy.run_module(module, run_name="__main__", alter_sys=True)
                code = 0
            except SystemExit as exc:
                code = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
            except BaseException:  # noqa: BLE001 -- what the interpreter would print
                traceback.print_exc()
                code = 1
    return code, out[0], out[1]


def end(proc: subprocess.Popen) -> None:
    """Kill ``proc`` if it still runs and reap it (a test's cleanup, whatever failed before it)."""
    if proc.poll() is None:
        proc.kill()
        proc.communicate()


class Background:
    """``cmd`` started in ``cwd`` in the background with the repository on its PYTHONPATH (environment
    ``env``, default this one's); its stdout and stderr go to ``logs``.out / .err, not pipes, so it never
    stalls while nothing reads them."""

    def __init__(self, cmd: Sequence[str], cwd: Path, logs: Path, env: dict[str, str] | None = None) -> None:
        env = dict(os.environ if env is None else env)
        env["PYTHONPATH"] = str(REPO) + os.pathsep + env.get("PYTHONPATH", "")
        self.out, self.err = logs.with_suffix(".out"), logs.with_suffix(".err")
        with open(self.out, "w") as stdout, open(self.err, "w") as stderr:
            self.proc = subprocess.Popen(list(cmd), cwd=cwd, env=env, stdout=stdout, stderr=stderr, text=True)

    def finish(self, timeout: float = 600) -> subprocess.CompletedProcess:
        """Wait (killed after ``timeout`` s): its exit status, stdout and stderr."""
        try:
            self.proc.wait(timeout=timeout)
        finally:
            self.stop()
        return subprocess.CompletedProcess(self.proc.args, self.proc.returncode, self.out.read_text(), self.err.read_text())

    def stop(self) -> None:
        end(self.proc)


class Batch:
    """``commands`` ([(module, args), ...]) started in order in one new worker process in ``cwd``
    (environment ``env``, default this one's), in the background: :meth:`results` waits for them."""

    def __init__(self, commands: Sequence[tuple[str, Sequence[str]]], cwd: Path, env: dict[str, str] | None = None,
                 watch: Sequence[Path] = (), timeout: float = 600) -> None:
        self.commands, self.timeout = [(m, list(a)) for m, a in commands], timeout
        self.tmp = tempfile.TemporaryDirectory(prefix="cli-worker-")
        self.out = Path(self.tmp.name) / "results.json"
        cmd = [sys.executable, __file__, "--commands", json.dumps(self.commands), "--out", str(self.out),
               "--watch", json.dumps([str(p) for p in watch])]
        self.worker = Background(cmd, cwd, Path(self.tmp.name) / "worker", env)

    def results(self) -> list[subprocess.CompletedProcess]:
        """One CompletedProcess (returncode, stdout, stderr) per command, whose ``files`` holds the
        text of each ``watch`` path (None when absent) as that command left it."""
        worker = self.worker.finish(self.timeout)
        assert worker.returncode == 0 and self.out.is_file(), worker.stderr[-3000:]
        results = json.loads(self.out.read_text())
        self.tmp.cleanup()
        done = []
        for (module, args), (code, stdout, stderr, files) in zip(self.commands, results):
            done.append(subprocess.CompletedProcess([sys.executable, "-m", module, *args], code, stdout, stderr))
            done[-1].files = {Path(p): text for p, text in files.items()}
        return done

    def stop(self) -> None:
        self.worker.stop()


def run_commands(commands: Sequence[tuple[str, Sequence[str]]], cwd: Path, env: dict[str, str] | None = None,
                 watch: Sequence[Path] = (), timeout: float = 600) -> list[subprocess.CompletedProcess]:
    """Run ``commands`` ([(module, args), ...]) in order in one new worker process started in
    ``cwd`` (environment ``env``, default this one's) and wait for them: :meth:`Batch.results`."""
    return Batch(commands, cwd, env, watch, timeout).results()


def used_in_module(request, fixture: str) -> bool:
    """Whether a selected test of the module of ``request`` (a pytest fixture request) uses
    ``fixture``: a batch started ahead for a module's CLI tests is left out when none runs."""
    return any(fixture in item.fixturenames for item in request.session.items if item.module is request.module)


def read_text(path: str) -> str | None:
    return Path(path).read_text() if Path(path).is_file() else None


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--commands", required=True, help='JSON: [["module", ["arg", ...]], ...]')
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--watch", default="[]", help="JSON: files whose text is recorded after each command")
    opts = parser.parse_args()
    watch = json.loads(opts.watch)
    done = [(*run_module(module, args), {p: read_text(p) for p in watch}) for module, args in json.loads(opts.commands)]
    opts.out.write_text(json.dumps(done))
