"""Characters and motions: find, store an upload (received, checked, parsed by a worker, recorded), delete."""

from __future__ import annotations

import asyncio
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Literal

from celery import Celery
from fastapi import HTTPException, Request, Response
from sqlalchemy import func, or_, select
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session
from starlette.concurrency import run_in_threadpool

from api import idempotency
from api.db import session_scope
from api.limits import check_storage
from api.models import ApiKey, Asset, Job, new_id
from api.queue import TASK_INSPECT
from api.schemas import AssetOut
from api.serialize import asset_out, collection
from api.settings import Settings
from api.storage import Storage
from api.uploads import ReceivedFile, UploadError, receive_upload, safe_filename, safe_text
from api.worker_calls import WorkerCallFailed, WorkerUnavailable, call_worker
from retarget_core.errors import UnsupportedFileError
from retarget_core.io.formats import detect_format_bytes

AssetKind = Literal["character", "motion"]
ALLOWED_FORMATS: dict[str, tuple[str, ...]] = {
    "character": ("glb", "gltf", "fbx"),
    "motion": ("bvh", "glb", "gltf", "fbx"),
}
ID_PREFIX = {"character": "chr", "motion": "mot"}


def find_asset(session: Session, key: ApiKey, kind: str, asset_id: str) -> Asset:
    """The asset ``asset_id`` of ``kind`` visible to ``key`` (own or built-in); 404 otherwise."""
    asset = session.get(Asset, asset_id)
    if asset is None or asset.kind != kind or (asset.owner_id != key.id and asset.origin != "builtin"):
        raise HTTPException(404, f"{kind} {asset_id!r} not found")
    return asset


def blob_in_use(session: Session, ref: str, sha256: str, except_asset: str | None = None) -> bool:
    """True when an asset or a job still refers to a blob."""
    q = select(func.count()).select_from(Asset).where(Asset.sha256 == sha256)
    if except_asset:
        q = q.where(Asset.id != except_asset)
    if session.scalar(q):
        return True
    jobs = select(func.count()).select_from(Job).where(
        or_(Job.motion_ref == ref, Job.target_ref == ref, Job.source_ref == ref)
    )
    return bool(session.scalar(jobs))


def delete_asset(session: Session, storage: Storage, asset: Asset) -> None:
    """Delete an asset, and its file when nothing else refers to it; 409 for a built-in body."""
    if asset.origin == "builtin":
        raise HTTPException(409, "built-in bodies cannot be deleted")
    sha, fmt = asset.sha256, asset.format
    session.delete(asset)
    session.flush()
    if sha and fmt:
        ref = storage.blob_ref(sha, fmt)
        if not blob_in_use(session, ref, sha):
            session.commit()
            storage.delete_blob(ref)


def download_name(asset: Asset) -> str:
    """The file name a download of the asset is offered under (always a usable file name)."""
    fmt = asset.format or "bin"
    return asset.filename or safe_filename(f"{asset.name}.{fmt}") or f"{asset.kind}.{fmt}"


def _drop_blob_if_unused(url: str, storage: Storage, ref: str, sha256: str) -> None:
    with session_scope(url) as s:
        if not blob_in_use(s, ref, sha256):
            storage.delete_blob(ref)


def _known_info(url: str, kind: str, sha256: str, owner_id: str) -> dict[str, Any] | None:
    """What an earlier parse of the same bytes as the same kind *by the same key* found. Another key's parse is
    never reused: its answer would carry that key's file name, and a faster answer would tell that someone else
    has the file."""
    with session_scope(url) as s:
        row = s.scalar(
            select(Asset).where(Asset.sha256 == sha256, Asset.kind == kind, Asset.owner_id == owner_id)
            .order_by(Asset.created_at).limit(1)
        )
        return dict(row.info) if row is not None and row.info else None


def _check_storage(url: str, owner_id: str, size: int, settings: Settings) -> None:
    with session_scope(url) as s:
        check_storage(s, owner_id, size, settings)


def replayed_asset(url: str, owner_id: str, idem: str | None, scope: str, fp: str) -> AssetOut | None:
    """The asset an earlier request with this Idempotency-Key made (None when there was none); 409 when it was
    deleted since, 422 when the key was used for a different request."""
    if not idem:
        return None
    with session_scope(url) as s:
        found = idempotency.find(s, owner_id, idem, scope, fp)
        if found is None:
            return None
        asset = s.get(Asset, found)
        if asset is None or asset.owner_id != owner_id:
            raise HTTPException(409, f"what the Idempotency-Key {idem[:80]!r} made was deleted since; use a new key")
        return asset_out(asset)


def insert_asset(url: str, idem: tuple[str, str, str] | None = None, **values: Any) -> tuple[AssetOut, bool]:
    """Insert the asset (and, with ``idem`` = (Idempotency-Key, scope, fingerprint), its record in the same
    transaction); returns it and whether it is the one a concurrent request with the same key made."""
    try:
        with session_scope(url) as s:
            asset = Asset(**values)
            s.add(asset)
            if idem:
                idempotency.remember(s, values["owner_id"], idem[0], idem[1], idem[2], asset.id)
            s.flush()
            return asset_out(asset), False
    except IntegrityError:
        earlier = replayed_asset(url, values["owner_id"], *idem) if idem else None
        if earlier is None:
            raise
        return earlier, True


def answer_asset(response: Response, out: AssetOut, replayed: bool) -> AssetOut:
    """The asset as the answer's body, with its Location (and the replay header when replayed)."""
    response.headers["Location"] = out.links["self"]
    if replayed:
        response.headers[idempotency.REPLAYED_HEADER] = "true"
    return out


@contextmanager
def _discarding(tmp: Path) -> Iterator[None]:
    """Remove the received file when the block refuses the upload."""
    try:
        yield
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


async def _receive(request: Request, storage: Storage, settings: Settings) -> ReceivedFile:
    """The request body in a temporary file; 503 when too many uploads are being received, else the
    upload's own status (400, 408, 413)."""
    slots: asyncio.Semaphore = request.app.state.upload_slots
    if slots.locked():
        raise HTTPException(503, f"{settings.max_concurrent_uploads} uploads are being received; try again in a "
                            "moment (setting RETARGET_API_MAX_CONCURRENT_UPLOADS)", headers={"Retry-After": "5"})
    try:
        async with slots:
            return await receive_upload(request, storage.temp_path(), settings.max_upload_bytes,
                                        settings.upload_chunk_bytes, settings.upload_idle_timeout_seconds,
                                        settings.upload_timeout_seconds)
    except UploadError as exc:
        raise HTTPException(exc.status, exc.detail) from exc


def _format(kind: str, received: ReceivedFile) -> str:
    """The detected format of the upload; 415 when it cannot be a ``kind``."""
    label = received.filename or "the upload"
    try:
        fmt = detect_format_bytes(received.head, label)
    except UnsupportedFileError as exc:
        raise HTTPException(415, str(exc)) from exc
    if fmt not in ALLOWED_FORMATS[kind]:
        allowed = ", ".join(f.upper() for f in ALLOWED_FORMATS[kind])
        raise HTTPException(415, f"{label}: a {fmt.upper()} file cannot be a {kind} (expected {allowed})")
    return fmt


async def _parsed_info(celery: Celery, settings: Settings, storage: Storage, kind: str, received: ReceivedFile,
                       ref: str, created: bool, owner_id: str) -> dict[str, Any]:
    """What a worker's parse of the stored file found (or an earlier parse of the same bytes by this key); 422
    with the parser's message (the new blob dropped), 503 when no worker answered."""
    url = settings.resolved_database_url
    info = await run_in_threadpool(_known_info, url, kind, received.sha256, owner_id)
    if info is not None:
        if received.filename:
            info["name"] = Path(received.filename).stem
        return info
    try:
        result = await call_worker(celery, url, TASK_INSPECT, {"ref": ref, "kind": kind, "label": received.filename},
                                   settings.inspect_timeout_seconds)
    except WorkerCallFailed as exc:
        if created:
            await run_in_threadpool(_drop_blob_if_unused, url, storage, ref, received.sha256)
        raise HTTPException(422, str(exc)) from exc
    except WorkerUnavailable as exc:
        raise HTTPException(503, str(exc)) from exc
    return dict(result["info"])


def display_name(kind: str, received: ReceivedFile, name: str | None) -> str:
    """The asset's display name: the form's or query's name, else the file name's stem, else the kind."""
    for candidate in (received.fields.get("name"), name, Path(received.filename or "").stem):
        text = safe_text(candidate or "")
        if text:
            return text[:300]
    return kind


async def upload_asset(request: Request, kind: AssetKind, key: ApiKey, settings: Settings, storage: Storage,
                       celery: Celery, name: str | None, idem: str | None) -> tuple[AssetOut, bool]:
    """Receive, check, store and parse an upload, then record it; the asset and whether it is a replay."""
    url = settings.resolved_database_url
    received = await _receive(request, storage, settings)
    scope = f"POST /v1/{collection(kind)}"
    fp = idempotency.fingerprint(received.sha256, received.filename or "", received.fields.get("name") or name or "")
    with _discarding(received.path):
        await run_in_threadpool(_check_storage, url, key.id, received.size, settings)
        earlier = await run_in_threadpool(replayed_asset, url, key.id, idem, scope, fp)
        fmt = _format(kind, received) if earlier is None else ""
    if earlier is not None:
        received.path.unlink(missing_ok=True)
        return earlier, True
    ref = storage.blob_ref(received.sha256, fmt)
    _, created = await run_in_threadpool(storage.commit_blob, received.path, ref)
    info = await _parsed_info(celery, settings, storage, kind, received, ref, created, key.id)
    return await run_in_threadpool(
        insert_asset, url, (idem, scope, fp) if idem else None,
        id=new_id(ID_PREFIX[kind]), kind=kind, owner_id=key.id, origin="upload",
        name=display_name(kind, received, name), filename=received.filename, format=fmt,
        sha256=received.sha256, size_bytes=received.size, info=info,
    )
