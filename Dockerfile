# syntax=docker/dockerfile:1
# TivNe in a container, CPU or CUDA (README "Docker"):
#   docker build -t tivne .                                      CPU: torch's CPU wheel
#   docker build --build-arg VARIANT=cuda -t tivne:cuda .        CUDA: torch's CUDA wheel (CUDA_WHEELS)
# The code and conf/ live in /app; runs write to the working directory /runs (mount your outputs
# folder at /runs/outputs, a dataset read-only anywhere, e.g. /data). CMD runs the built-in
# moving-cube sequence, no download.
ARG VARIANT=cpu

FROM python:3.11-slim AS base
ENV PIP_NO_CACHE_DIR=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1 \
    PYTHONUNBUFFERED=1 \
    OMP_WAIT_POLICY=PASSIVE \
    MPLBACKEND=Agg \
    HOME=/runs
# A non-root user whose home is the run folder (the synthetic-scene cache lands in ~/.cache/tivne
# there); it is writable by any uid too, so `docker run --user "$(id -u):$(id -g)"` (results owned by
# you on the host) works as well.
RUN useradd --no-create-home --home-dir /runs --uid 1000 tivne \
 && mkdir -p /runs/.cache/tivne \
 && chmod -R a+rwX /runs

# torch first and pinned, from the index of the chosen build, so pip never swaps it for another one.
FROM base AS torch-cpu
RUN pip install --index-url https://download.pytorch.org/whl/cpu "torch==2.13.0"

FROM base AS torch-cuda
# The CUDA build of the wheel (pytorch.org lists them); the host needs an NVIDIA driver that supports
# it and the NVIDIA container toolkit (docker run --gpus all).
ARG CUDA_WHEELS=cu128
RUN pip install --index-url "https://download.pytorch.org/whl/${CUDA_WHEELS}" "torch==2.13.0"

FROM torch-${VARIANT} AS app
WORKDIR /app
COPY pyproject.toml README.md LICENSE ./
COPY tivne tivne
COPY data_modules data_modules
COPY conf conf
COPY bench bench
COPY tests tests
# Editable: the commands find conf/ next to the package.
RUN pip install -e ".[test,eval,sweep]"
WORKDIR /runs
USER tivne
CMD ["python", "-m", "tivne.train"]
