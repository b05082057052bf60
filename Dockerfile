# CPU image: python -m tivne.train runs the built-in moving-cube sequence without any download.
FROM python:3.11-slim
ENV PIP_NO_CACHE_DIR=1 OMP_WAIT_POLICY=PASSIVE TIVNE_CACHE_DIR=/app/.cache
WORKDIR /app
# torch first and pinned, so pip takes the CPU build rather than a CUDA one.
RUN pip install --index-url https://download.pytorch.org/whl/cpu "torch==2.13.0"
COPY pyproject.toml README.md LICENSE ./
COPY tivne tivne
COPY data_modules data_modules
COPY conf conf
COPY bench bench
COPY tests tests
RUN pip install -e ".[test]"
CMD ["python", "-m", "tivne.train"]
