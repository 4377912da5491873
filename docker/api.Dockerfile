# The API image: FastAPI + SQLAlchemy + Celery client only (no torch). Build from the repository root:
#   docker build -f docker/api.Dockerfile -t retarget-api .
# UNTESTED: no Docker engine was available where this was written (see docs/service.md).

# The front end, when frontend/ has a build script (served by the API at /).
FROM node:20-slim AS frontend
WORKDIR /src/frontend
COPY frontend/package*.json ./
RUN npm ci --no-audit --no-fund || npm install --no-audit --no-fund
COPY frontend/ ./
RUN npm run build --if-present && mkdir -p dist

FROM python:3.11-slim AS api
ENV PYTHONDONTWRITEBYTECODE=1 PYTHONUNBUFFERED=1 PIP_NO_CACHE_DIR=1 \
    RETARGET_API_DATA_DIR=/data RETARGET_API_FRONTEND_DIR=/app/frontend/dist
WORKDIR /app
COPY pyproject.toml README.md ./
COPY retarget_core/ retarget_core/
COPY api/ api/
COPY worker/ worker/
RUN pip install ".[api]" && useradd --uid 10001 --create-home retarget && mkdir -p /data && chown retarget /data
COPY --from=frontend /src/frontend/dist /app/frontend/dist
USER retarget
VOLUME ["/data"]
EXPOSE 8000
HEALTHCHECK --interval=15s --timeout=5s --retries=3 \
  CMD python -c "import urllib.request; urllib.request.urlopen('http://127.0.0.1:8000/healthz', timeout=4)"
CMD ["uvicorn", "api.main:create_app", "--factory", "--host", "0.0.0.0", "--port", "8000", "--proxy-headers"]
