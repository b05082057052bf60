"""The Dockerfile, checked without Docker: what it copies exists and is not ignored, both torch
builds are there, it runs as a non-root user with HOME and MPLBACKEND set, its command is the README's
main command, and the README's docker lines match its layout."""

from __future__ import annotations

import fnmatch
import json
import re
import shlex
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def instructions(path: Path) -> list[tuple[str, str]]:
    """(INSTRUCTION, arguments) in order; comments dropped, continuation lines joined."""
    out: list[tuple[str, str]] = []
    pending = ""
    for line in path.read_text().splitlines():
        if line.strip().startswith("#") or not line.strip():
            continue
        pending += line.rstrip()
        if pending.endswith("\\"):
            pending = pending[:-1] + " "
            continue
        word, _, rest = pending.strip().partition(" ")
        out.append((word.upper(), rest.strip()))
        pending = ""
    return out


DOCKERFILE = instructions(REPO / "Dockerfile")


def of(kind: str) -> list[str]:
    return [args for word, args in DOCKERFILE if word == kind]


def readme_section(title: str) -> str:
    text = (REPO / "README.md").read_text()
    start = text.index(f"## {title}\n")
    end = text.find("\n## ", start + 1)
    return text[start : end if end > 0 else None]


def readme_main_command() -> str:
    """The command of the README's first code block: what its first line runs after the set-up."""
    block = re.search(r"```bash\n(.*?)```", (REPO / "README.md").read_text(), re.S).group(1)
    first = next(line for line in block.splitlines() if line.strip() and not line.lstrip().startswith("#"))
    return first.split("&&")[-1].strip()


def test_every_copied_path_exists_and_is_in_the_build_context():
    ignored = [p.strip() for p in (REPO / ".dockerignore").read_text().splitlines() if p.strip() and not p.startswith("#")]
    copied = []
    for args in of("COPY"):
        words = [w for w in shlex.split(args) if not w.startswith("--")]
        assert not any(w.startswith("--from") for w in shlex.split(args)), "copies between stages need no check here"
        copied += words[:-1]
    assert copied, "the Dockerfile copies nothing"
    for source in copied:
        assert (REPO / source).exists(), f"COPY {source}: not in the repository"
        assert not any(fnmatch.fnmatch(source, pattern) for pattern in ignored), f"COPY {source}: excluded by .dockerignore"
    assert {"conf", "tivne", "data_modules", "pyproject.toml"} <= set(copied)  # the configs are inside the image


def test_cpu_and_cuda_builds():
    stages = {m.group(2): m.group(1) for m in (re.match(r"(\S+)\s+AS\s+(\S+)", a, re.I) for a in of("FROM")) if m}
    assert {"torch-cpu", "torch-cuda"} <= set(stages)
    assert stages["app"] == "torch-${VARIANT}" and any(a.startswith("VARIANT=cpu") for a in of("ARG"))
    runs = " ".join(of("RUN"))
    assert "download.pytorch.org/whl/cpu" in runs and "download.pytorch.org/whl/${CUDA_WHEELS}" in runs
    pins = set(re.findall(r'"torch==([\d.]+)"', runs))
    assert pins == set(re.findall(r'"torch==([\d.]+)"', (REPO / ".ci" / "run").read_text())), "the image's torch is CI's"


def test_runs_as_a_user_with_home_and_a_headless_matplotlib():
    assert of("USER") and of("USER")[-1] not in ("root", "0")
    env = " ".join(of("ENV"))
    home = re.search(r"\bHOME=(\S+)", env)
    assert home and home.group(1) == of("WORKDIR")[-1] and "MPLBACKEND=Agg" in env  # the writable run folder
    assert "chmod -R a+rwX " + home.group(1) in " ".join(of("RUN"))


def test_command_is_the_readme_main_command():
    assert readme_main_command() == "python -m tivne.train"
    assert " ".join(json.loads(of("CMD")[-1])) == readme_main_command()


def test_readme_docker_lines_match_the_image():
    section = readme_section("Docker")
    workdir = of("WORKDIR")[-1]
    assert "docker build -t tivne ." in section and "--build-arg VARIANT=cuda" in section
    runs = [line for line in section.splitlines() if line.startswith("docker run")]
    assert runs and all(f":{workdir}/outputs" in line for line in runs)  # results land on the host
    assert any(":ro" in line for line in runs)  # a dataset mounted read-only
