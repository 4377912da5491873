"""Settings of the service (API and worker), read from the environment. Every limit is named here.

Variables use the prefix ``RETARGET_API_`` (for example ``RETARGET_API_MAX_UPLOAD_BYTES``); the two connection
strings are also read from the conventional ``DATABASE_URL`` and ``REDIS_URL``.
"""

from __future__ import annotations

import importlib.util
from functools import lru_cache
from pathlib import Path
from typing import Literal

from pydantic import AliasChoices, Field
from pydantic_settings import BaseSettings, SettingsConfigDict

REPO_ROOT = Path(__file__).resolve().parents[1]

QueueName = Literal["cpu", "gpu"]


class Settings(BaseSettings):
    """One place for every setting of the service. Both the API and the worker read it."""

    model_config = SettingsConfigDict(env_prefix="RETARGET_API_", extra="ignore")

    # Where things live
    data_dir: Path = Field(
        default=Path("var/service"),
        description="Root of local storage: blobs/, jobs/, tmp/ and (by default) the SQLite files",
    )
    database_url: str | None = Field(
        default=None,
        validation_alias=AliasChoices("RETARGET_API_DATABASE_URL", "DATABASE_URL"),
        description="SQLAlchemy URL; default: SQLite file <data_dir>/service.sqlite",
    )
    redis_url: str | None = Field(
        default=None,
        validation_alias=AliasChoices("RETARGET_API_REDIS_URL", "REDIS_URL"),
        description="Redis URL for the Celery broker; default: no Redis, Celery's SQLAlchemy transport on SQLite",
    )
    broker_url: str | None = Field(default=None, description="Explicit Celery broker URL (overrides redis_url)")
    broker_polling_interval_seconds: float = Field(
        default=0.2, gt=0, description="How often a worker polls the SQLite broker (embedded mode only)"
    )
    db_pool_size: int = Field(
        default=24, ge=1, description="Database connections each process keeps open (at least api_threads: a "
        "connection opened past the pool size is closed again when returned, and under load one would be opened "
        "and closed for nearly every request)"
    )
    db_max_overflow: int = Field(
        default=16, ge=0, description="Extra connections a process may open under load (pool size + overflow "
        "must be at least api_threads)"
    )
    db_pool_timeout_seconds: float = Field(default=10.0, gt=0, description="Longest wait for a free connection")
    api_threads: int = Field(default=24, ge=1, description="Threads of an API process that run blocking work")
    gil_switch_interval_seconds: float = Field(
        default=0.001, ge=0, description="Python's thread switch interval in an API process (sys.setswitchinterval; "
        "0: leave Python's 0.005). A busy event loop hands the interpreter lock to a waiting thread only this "
        "often, and a thread (the sent marker's broker sends, sync endpoints) needs it after each round trip"
    )

    loop_write_wait_seconds: float = Field(
        default=0.02, gt=0, description="Longest wait of a submission's write on an API process's event loop for "
        "another writer (SQLite's write lock, a PostgreSQL row lock); the whole process waits with it. Past it the "
        "write is made in a thread"
    )

    # Uploads
    max_upload_bytes: int = Field(default=200 * 1024 * 1024, gt=0, description="Largest accepted upload")
    upload_chunk_bytes: int = Field(default=1024 * 1024, gt=0, description="Bytes buffered before each disk write")
    inspect_timeout_seconds: float = Field(
        default=60.0, gt=0, description="How long an upload waits for a worker to parse it before answering 503"
    )
    inspect_time_limit_seconds: int = Field(default=120, gt=0, description="Hard time limit of a parse task")
    upload_timeout_seconds: float = Field(default=600.0, gt=0, description="Longest time to receive one upload body")
    upload_idle_timeout_seconds: float = Field(
        default=30.0, gt=0, description="An upload that sends nothing for this long is cut off (408)"
    )
    max_concurrent_uploads: int = Field(
        default=32, ge=1, description="Uploads one API process receives at once; more answer 503 with Retry-After"
    )
    parse_budget_bytes: int = Field(
        default=300 * 1024 * 1024, gt=0,
        description="Memory one parse may allocate above the worker's resting size (passed to the readers as "
        "RETARGET_PARSE_BUDGET_BYTES)",
    )
    min_motion_fps: float = Field(default=1.0, gt=0, description="Lowest frame rate of an accepted motion")
    max_motion_fps: float = Field(default=1000.0, gt=0, description="Highest frame rate of an accepted motion")
    min_character_height_m: float = Field(default=0.2, gt=0, description="Shortest accepted character (metres)")
    max_character_height_m: float = Field(default=10.0, gt=0, description="Tallest accepted character (metres)")

    # Jobs
    default_queue: QueueName = "cpu"
    job_soft_time_limit_seconds: int = Field(default=1800, gt=0, description="A job is stopped with a message")
    job_hard_time_limit_seconds: int = Field(default=1860, gt=0, description="A job's process is killed")
    max_job_attempts: int = Field(default=3, ge=1, description="Runs of a job whose worker vanished before it fails")
    heartbeat_interval_seconds: float = Field(default=5.0, gt=0, description="How often a running job says alive")
    worker_device: str | None = Field(
        default=None, pattern=r"^(cpu|cuda(:\d+)?|auto)$",
        description="Torch device of this worker's jobs when a job does not choose one (default: cuda on the gpu "
        "queue, cpu elsewhere)",
    )
    heartbeat_timeout_seconds: float = Field(
        default=60.0, gt=0, description="Silence after which a running job's worker is taken for dead"
    )
    reaper_interval_seconds: float = Field(default=5.0, gt=0, description="How often each worker runs the reaper")
    requeue_queued_after_seconds: float = Field(
        default=900.0, gt=0, description="A queued job whose message was sent this long ago is sent again"
    )
    progress_min_interval_seconds: float = Field(
        default=0.5, ge=0, description="Least time between two progress writes of one job"
    )
    max_batch_jobs: int = Field(default=500, gt=0, description="Most jobs one batch may create")
    max_job_frame_vertices: int = Field(
        default=40_000_000, gt=0,
        description="Output frames x target vertices one job may have (memory grows with it), checked at submission",
    )
    resend_unsent_after_seconds: float = Field(
        default=5.0, gt=0, description="A queued job whose message was not confirmed sent this long is sent (again)"
    )
    redelivery_takeover_seconds: float = Field(
        default=15.0, gt=0,
        description="A redelivered job whose running attempt has been silent this long is run again at once",
    )
    sent_mark_interval_seconds: float = Field(
        default=0.05, ge=0, description="An API process records sent_at of the jobs it sent in batches this often "
        "(one write for many submissions); 0: at once, in the request"
    )
    idempotency_ttl_seconds: float = Field(default=86400.0, gt=0, description="How long an Idempotency-Key is kept")
    max_idempotency_key_length: int = Field(default=200, ge=8, description="Longest Idempotency-Key header")

    # Per-key quotas (429 when exceeded)
    max_active_jobs_per_key: int = Field(default=2000, ge=1, description="Queued plus running jobs of one key")
    max_stored_bytes_per_key: int = Field(
        default=20 * 1024**3, ge=1, description="Bytes of uploaded files one key may keep"
    )

    # Listing
    page_size_default: int = Field(default=50, gt=0)
    page_size_max: int = Field(default=500, gt=0)
    max_list_offset: int = Field(default=1_000_000_000, gt=0, description="Largest offset of a list request")

    # Webhooks
    webhook_secret: str | None = Field(
        default=None, description="One signing secret for every key; default: each API key's own secret"
    )
    webhook_timeout_seconds: float = Field(default=5.0, gt=0, description="Whole time of one delivery attempt")
    webhook_connect_timeout_seconds: float = Field(default=3.0, gt=0, description="Connecting to the receiver")
    callback_allowed_hosts: list[str] = Field(
        default_factory=list,
        description="Host names (exact, lower case) callbacks may reach although they resolve to private, loopback "
        "or link-local addresses (on-premises receivers); JSON list",
    )
    max_callback_url_length: int = Field(default=2000, ge=20, description="Longest callback_url")
    webhook_max_attempts: int = Field(default=8, ge=1)
    webhook_backoff_base_seconds: float = Field(default=2.0, gt=0, description="Delay before the 2nd attempt")
    webhook_backoff_max_seconds: float = Field(default=600.0, gt=0)
    public_base_url: str | None = Field(
        default=None, description="Base URL put in front of links in webhook payloads, e.g. https://retarget.example"
    )

    # Access
    dev_api_key: str | None = Field(
        default=None, description="A key created at start-up (embedded mode prints it); never set it in production"
    )
    key_cache_seconds: float = Field(
        default=5.0, ge=0, description="How long an API process trusts a key it looked up (a revoked key works "
        "this much longer); 0: look up every request"
    )
    review_link_secret: str | None = Field(
        default=None, description="Key that signs review links; default: a random one kept in <data_dir>/secrets"
    )
    review_link_max_seconds: float = Field(default=30 * 86400.0, gt=0, description="Longest life of a review link")
    review_link_default_seconds: float = Field(default=7 * 86400.0, gt=0, description="Life of a review link")
    worker_queue_cache_seconds: float = Field(
        default=2.0, ge=0, description="How long an API process reuses its list of the queues live workers serve"
    )
    cors_origins: list[str] = Field(default_factory=list, description="Allowed browser origins; empty: CORS off")
    frontend_dir: Path = Field(default=REPO_ROOT / "frontend" / "dist", description="Static front end served at /")

    # Embedded server
    host: str = "127.0.0.1"
    port: int = 8000
    worker_concurrency: int = Field(default=1, ge=1, description="Job processes of the embedded cpu worker")

    @property
    def resolved_database_url(self) -> str:
        """The SQLAlchemy URL in use, with a driver that is installed."""
        url = self.database_url or f"sqlite:///{(self.data_dir / 'service.sqlite').resolve()}"
        return normalise_database_url(url)

    @property
    def resolved_broker_url(self) -> str:
        """The Celery broker URL in use."""
        if self.broker_url:
            return self.broker_url
        if self.redis_url:
            return self.redis_url
        return f"retarget-sqla+sqlite:///{(self.data_dir / 'broker.sqlite').resolve()}"

    @property
    def embedded_broker(self) -> bool:
        """True when the broker is the server-less SQLite transport."""
        return self.resolved_broker_url.startswith(("retarget-sqla+", "sqla+", "sqlalchemy+"))

    @property
    def blobs_dir(self) -> Path:
        return self.data_dir / "blobs"

    @property
    def jobs_dir(self) -> Path:
        return self.data_dir / "jobs"

    @property
    def tmp_dir(self) -> Path:
        return self.data_dir / "tmp"


@lru_cache(maxsize=64)
def normalise_database_url(url: str) -> str:
    """``postgresql://`` and ``postgres://`` use psycopg 3 when psycopg2 is absent (psycopg 3 is what we install).
    Cached: looking for the driver costs file system calls, and every submission asks several times."""
    for prefix in ("postgres://", "postgresql://"):
        if url.startswith(prefix):
            rest = url[len(prefix):]
            driver = "psycopg2" if importlib.util.find_spec("psycopg2") else "psycopg"
            return f"postgresql+{driver}://{rest}"
    return url


@lru_cache(maxsize=1)
def get_settings() -> Settings:
    """The process-wide settings (read once from the environment)."""
    return Settings()
