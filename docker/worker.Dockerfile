# Worker images: the library (torch) + Celery. Build from the repository root:
#   docker build -f docker/worker.Dockerfile --target cpu -t retarget-worker .
#   docker build -f docker/worker.Dockerfile --target gpu -t retarget-worker-gpu .
# UNTESTED: no Docker engine was available where this was written (see docs/service.md).

FROM python:3.11-slim AS base
ENV PYTHONDONTWRITEBYTECODE=1 PYTHONUNBUFFERED=1 PIP_NO_CACHE_DIR=1 RETARGET_API_DATA_DIR=/data \
    NUMBA_CACHE_DIR=/home/retarget/.cache/numba
# NUMBA_CACHE_DIR: the compiled tree walks (retarget_core/geometry/bvh_kernels.py) cached where the user may write
# assimp-utils: FBX input (retarget_core reads FBX through the assimp command line)
RUN apt-get update && apt-get install -y --no-install-recommends assimp-utils && rm -rf /var/lib/apt/lists/* \
    && useradd --uid 10001 --create-home retarget && mkdir -p /data && chown retarget /data
WORKDIR /app

FROM base AS cpu
RUN pip install torch==2.13.0 --index-url https://download.pytorch.org/whl/cpu
COPY pyproject.toml README.md ./
COPY retarget_core/ retarget_core/
COPY api/ api/
COPY worker/ worker/
RUN pip install ".[worker]"
USER retarget
VOLUME ["/data"]
CMD ["python", "-m", "worker", "--queues", "cpu", "--concurrency", "2"]

FROM base AS gpu
# The default PyPI wheel of torch carries the CUDA runtime; the host needs the NVIDIA container toolkit.
RUN pip install torch==2.13.0
COPY pyproject.toml README.md ./
COPY retarget_core/ retarget_core/
COPY api/ api/
COPY worker/ worker/
RUN pip install ".[worker]"
USER retarget
VOLUME ["/data"]
CMD ["python", "-m", "worker", "--queues", "gpu", "--concurrency", "1"]
