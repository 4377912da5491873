"""Small pieces of the service: storage, keys and signatures, settings, migrations, the keys CLI, the broker."""

from __future__ import annotations

import contextlib
import hashlib
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest
from alembic.autogenerate import compare_metadata
from alembic.migration import MigrationContext

from api.db import get_engine, session_scope
from api.models import Base
from api.security import create_key, find_key, hash_key, sign_payload, verify_signature
from api.settings import Settings, normalise_database_url
from api.storage import Storage, StorageError

REPO = Path(__file__).resolve().parents[2]


def test_storage_is_content_addressed(tmp_path: Path) -> None:
    st = Storage(tmp_path)
    st.ensure()
    data = b"HIERARCHY\nROOT a"
    sha = hashlib.sha256(data).hexdigest()
    ref = st.blob_ref(sha, "bvh")
    for _ in range(2):
        tmp = st.temp_path()
        tmp.write_bytes(data)
        path, _created = st.commit_blob(tmp, ref)
        assert not tmp.exists()
    assert path == tmp_path.resolve() / "blobs" / sha[:2] / f"{sha}.bvh" and path.read_bytes() == data
    assert [p for p in (tmp_path / "blobs").rglob("*") if p.is_file()] == [path]
    with pytest.raises(StorageError):
        st.blob_path("../../etc/passwd")
    with pytest.raises(StorageError):
        st.resolve("../outside")
    run = st.job_run_dir("job_abc", 2)
    (run / "x").write_text("1")
    assert st.relative(run / "x") == "jobs/job_abc/run-2/x" and st.resolve("jobs/job_abc/run-2/x").is_file()
    assert not any(st.job_run_dir("job_abc", 2).iterdir())  # a new run starts clean
    with pytest.raises(StorageError):
        st.job_run_dir("../x", 1)
    st.check_writable()


def test_storage_not_writable_is_reported(tmp_path: Path) -> None:
    (tmp_path / "file").write_text("")
    with pytest.raises(StorageError, match="not writable"):
        Storage(tmp_path / "file" / "sub").check_writable()


def test_webhook_signature_round_trip() -> None:
    body = b'{"event":"job.succeeded"}'
    header = sign_payload("s3cret", body, timestamp=1_700_000_000)
    assert header.startswith("t=1700000000,v1=")
    assert verify_signature("s3cret", body, header, tolerance_seconds=None)
    assert not verify_signature("other", body, header, tolerance_seconds=None)
    assert not verify_signature("s3cret", body + b" ", header, tolerance_seconds=None)
    assert not verify_signature("s3cret", body, header, tolerance_seconds=300)  # too old
    assert verify_signature("s3cret", body, sign_payload("s3cret", body))
    assert not verify_signature("s3cret", body, "garbage")


def test_keys_are_stored_hashed(tmp_path: Path) -> None:
    from api.migrate import upgrade

    url = f"sqlite:///{tmp_path / 'k.sqlite'}"
    upgrade(url)
    with session_scope(url) as s:
        row, plain = create_key(s, "studio")
        assert row.key_hash == hash_key(plain) and plain not in (row.key_hash, row.key_prefix + "x")
        assert find_key(s, plain).id == row.id and find_key(s, plain + "x") is None


def test_settings_urls(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    s = Settings(data_dir=tmp_path)
    assert s.resolved_database_url == f"sqlite:///{tmp_path.resolve() / 'service.sqlite'}"
    assert s.embedded_broker and s.resolved_broker_url.startswith("retarget-sqla+sqlite:///")
    monkeypatch.setenv("REDIS_URL", "redis://127.0.0.1:6379/3")
    monkeypatch.setenv("DATABASE_URL", "postgresql://u@h/db")
    s = Settings(data_dir=tmp_path)
    assert s.resolved_broker_url == "redis://127.0.0.1:6379/3" and not s.embedded_broker
    assert s.resolved_database_url.startswith("postgresql+psycopg")
    assert normalise_database_url("sqlite:///x") == "sqlite:///x"


def test_migrations_match_the_models(database_url: str) -> None:
    """Alembic's head schema equals api.models (a model change without a migration fails here)."""
    with get_engine(database_url).connect() as conn:
        diff = compare_metadata(MigrationContext.configure(conn), Base.metadata)
    assert diff == []


def test_keys_cli_create_list_revoke(tmp_path: Path) -> None:
    env = {**os.environ, "RETARGET_API_DATA_DIR": str(tmp_path)}
    env.pop("DATABASE_URL", None)
    out = subprocess.run([sys.executable, "-m", "api.keys", "create", "pipeline"], env=env, cwd=REPO,
                         capture_output=True, text=True, check=True).stdout
    key = next(line.split()[-1] for line in out.splitlines() if line.startswith("api key:"))
    key_id = next(line.split()[-1] for line in out.splitlines() if line.startswith("id:"))
    url = Settings(data_dir=tmp_path).resolved_database_url
    with session_scope(url) as s:
        assert find_key(s, key) is not None
    listed = subprocess.run([sys.executable, "-m", "api.keys", "list"], env=env, cwd=REPO, capture_output=True,
                            text=True, check=True).stdout
    assert key_id in listed and "'pipeline'" in listed and key not in listed
    subprocess.run([sys.executable, "-m", "api.keys", "revoke", key_id], env=env, cwd=REPO, check=True,
                   capture_output=True)
    with session_scope(url) as s:
        assert find_key(s, key) is None


def test_embedded_broker_delivers_and_deletes(tmp_path: Path) -> None:
    """The server-less transport: a message sent by one connection is received once by another, then gone."""
    from kombu import Connection, Exchange, Queue

    from api import sqla_transport

    sqla_transport.register()
    url = f"retarget-sqla+sqlite:///{tmp_path / 'b.sqlite'}"
    queue = Queue("cpu", Exchange("cpu", type="direct"), routing_key="cpu")
    with Connection(url, transport_options={"polling_interval": 0.05}) as conn:
        producer = conn.Producer()
        producer.publish({"n": 1}, exchange=queue.exchange, routing_key="cpu", declare=[queue])
    got: list[dict[str, int]] = []
    with Connection(url, transport_options={"polling_interval": 0.05}) as conn, \
            conn.Consumer(queue, callbacks=[lambda body, msg: (got.append(body), msg.ack())]):
        t = time.monotonic()
        while not got and time.monotonic() - t < 5:
            with contextlib.suppress(TimeoutError):
                conn.drain_events(timeout=0.5)
    assert got == [{"n": 1}]
    import sqlite3

    rows = sqlite3.connect(tmp_path / "b.sqlite").execute("select count(*) from kombu_message").fetchone()[0]
    assert rows == 0


def test_the_api_imports_neither_torch_nor_the_worker() -> None:
    code = ("import sys, api.main, api.serve, api.keys, api.migrate; api.main.create_app; "
            "bad = sorted(m for m in sys.modules if m.split('.')[0] in ('torch', 'worker', 'scipy', 'trimesh') "
            "or m in ('retarget_core.pipeline', 'retarget_core.loading', 'retarget_core.character')); "
            "print(bad); sys.exit(1 if bad else 0)")
    proc = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True)
    assert proc.returncode == 0, proc.stdout + proc.stderr


def test_celery_reliability_settings(tmp_path: Path) -> None:
    from api.queue import IO_QUEUE, TASK_INSPECT, TASK_RUN_JOB, make_celery

    s = Settings(data_dir=tmp_path, redis_url="redis://127.0.0.1:6379/9", job_soft_time_limit_seconds=100,
                 job_hard_time_limit_seconds=120)
    conf = make_celery(s).conf
    assert conf.task_acks_late and conf.task_reject_on_worker_lost and conf.worker_prefetch_multiplier == 1
    assert (conf.task_soft_time_limit, conf.task_time_limit) == (100, 120)
    assert {q.name for q in conf.task_queues} == {"cpu", "gpu", IO_QUEUE, "webhooks"}
    assert conf.task_routes["retarget.deliver_webhook"]["queue"] == "webhooks"
    assert conf.task_routes[TASK_INSPECT]["queue"] == IO_QUEUE and TASK_RUN_JOB not in conf.task_routes
    assert conf.broker_transport_options["visibility_timeout"] > 120  # never re-delivered while it may still run
    embedded = make_celery(Settings(data_dir=tmp_path)).conf
    assert embedded.broker_url.startswith("retarget-sqla+sqlite:") and not embedded.worker_enable_remote_control


def test_callback_urls_refuse_internal_addresses_in_every_spelling() -> None:
    import pytest

    from api.callbacks import CallbackRefused, check_url

    for url in ("http://169.254.169.254/latest", "http://2130706433/", "http://0x7f.0.0.1/", "http://127.1/",
                "http://[::1]/", "http://0.0.0.0/", "http://10.1.2.3/", "http://[::ffff:192.168.0.1]/",
                "http://metadata/", "http://svc.internal/", "http://localhost:8080/", "http://user:pw@example.com/",
                "ftp://example.com/"):
        with pytest.raises(CallbackRefused):
            check_url(url, [], 2000)
    assert check_url("https://hooks.example.com/x", [], 2000)
    assert check_url("http://metadata/x", ["metadata"], 2000)  # an operator's allow-list
