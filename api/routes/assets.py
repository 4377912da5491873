"""Characters and motions: upload (multipart or raw body), list, get, download, delete. One factory, two routers."""

from __future__ import annotations

import asyncio
from pathlib import Path
from typing import Annotated, Any, Literal

from fastapi import APIRouter, HTTPException, Query, Request, Response, status
from fastapi.responses import FileResponse
from sqlalchemy import func, or_, select
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session
from starlette.concurrency import run_in_threadpool

from api import idempotency
from api.db import session_scope
from api.deps import CeleryDep, CurrentKey, SessionDep, SettingsDep, StorageDep
from api.limits import check_storage
from api.models import ApiKey, Asset, Job, new_id
from api.pages import MAX_QUERY_INT, page_bounds
from api.queue import TASK_INSPECT
from api.routing import SessionRoute
from api.schemas import AssetOut, ErrorOut, Page
from api.serialize import ASSET_CONTENT_TYPES, asset_out, collection
from api.settings import Settings
from api.storage import Storage
from api.uploads import UploadError, receive_upload
from api.worker_calls import WorkerCallFailed, WorkerUnavailable, call_worker
from retarget_core.errors import UnsupportedFileError
from retarget_core.io.formats import detect_format_bytes

AssetKind = Literal["character", "motion"]
ALLOWED_FORMATS: dict[str, tuple[str, ...]] = {
    "character": ("glb", "gltf", "fbx"),
    "motion": ("bvh", "glb", "gltf", "fbx"),
}
ID_PREFIX = {"character": "chr", "motion": "mot"}

UPLOAD_BODY: dict[str, Any] = {
    "requestBody": {
        "required": True,
        "description": "The file, as multipart form data (part `file`, optional part `name`) or as the raw body "
        "(any Content-Type but multipart; name it with ?filename=). The type is detected from the content.",
        "content": {
            "multipart/form-data": {
                "schema": {
                    "type": "object",
                    "required": ["file"],
                    "properties": {
                        "file": {"type": "string", "format": "binary"},
                        "name": {"type": "string", "description": "Display name; default: the file name"},
                    },
                }
            },
            "application/octet-stream": {"schema": {"type": "string", "format": "binary"}},
        },
    }
}


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


def _insert_asset(url: str, idem: tuple[str, str, str] | None = None, **values: Any) -> tuple[AssetOut, bool]:
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
    response.headers["Location"] = out.links["self"]
    if replayed:
        response.headers[idempotency.REPLAYED_HEADER] = "true"
    return out


def make_router(kind: AssetKind) -> APIRouter:
    """The router of ``/v1/characters`` or ``/v1/motions``."""
    coll = collection(kind)
    router = APIRouter(prefix=f"/v1/{coll}", tags=[coll], route_class=SessionRoute)
    formats = ", ".join(f.upper() for f in ALLOWED_FORMATS[kind])

    @router.post(
        "",
        status_code=201,
        response_model=AssetOut,
        summary=f"Upload a {kind}",
        description=f"Upload a {kind} file ({formats}). The file is streamed to disk under the size cap, its type "
        "is detected from its content, and a worker parses it before it is accepted. The answer says what was "
        "found (joints, mapping report, frames, fps, height, warnings). Identical files are stored once. With an "
        "Idempotency-Key header, a repeated upload answers with the asset the first one made.",
        responses={
            400: {"model": ErrorOut, "description": "Malformed request (no file part, empty body)"},
            408: {"model": ErrorOut, "description": "The body stalled or took too long"},
            413: {"model": ErrorOut, "description": "Over the upload size limit"},
            415: {"model": ErrorOut, "description": f"Not a {kind} file type ({formats})"},
            422: {"model": ErrorOut, "description": "The parser rejected the file; the message says why"},
            429: {"model": ErrorOut, "description": "Over the key's storage quota"},
            503: {"model": ErrorOut, "description": "No worker answered in time, or too many uploads at once"},
        },
        openapi_extra=UPLOAD_BODY,
    )
    async def upload(
        request: Request,
        response: Response,
        key: CurrentKey,
        settings: SettingsDep,
        storage: StorageDep,
        celery: CeleryDep,
        name: Annotated[str | None, Query(max_length=300, description="Display name")] = None,
        filename: Annotated[str | None, Query(max_length=300, description="File name of a raw-body upload")] = None,
        idempotency_key: idempotency.IdempotencyKey = None,
    ) -> AssetOut:
        del filename  # read by receive_upload from the query string; declared here for the OpenAPI document
        url = settings.resolved_database_url
        slots: asyncio.Semaphore = request.app.state.upload_slots
        if slots.locked():
            raise HTTPException(503, f"{settings.max_concurrent_uploads} uploads are being received; try again in a "
                                "moment (setting RETARGET_API_MAX_CONCURRENT_UPLOADS)", headers={"Retry-After": "5"})
        tmp = storage.temp_path()
        try:
            async with slots:
                received = await receive_upload(request, tmp, settings.max_upload_bytes, settings.upload_chunk_bytes,
                                                settings.upload_idle_timeout_seconds, settings.upload_timeout_seconds)
        except UploadError as exc:
            raise HTTPException(exc.status, exc.detail) from exc
        try:
            await run_in_threadpool(_check_storage, url, key.id, received.size, settings)
        except HTTPException:
            tmp.unlink(missing_ok=True)
            raise
        scope = f"POST /v1/{coll}"
        fp = idempotency.fingerprint(received.sha256, received.filename or "", received.fields.get("name") or name or "")
        try:
            earlier = await run_in_threadpool(replayed_asset, url, key.id, idempotency_key, scope, fp)
        except HTTPException:
            tmp.unlink(missing_ok=True)
            raise
        if earlier is not None:
            tmp.unlink(missing_ok=True)
            return answer_asset(response, earlier, True)
        label = received.filename or "the upload"
        try:
            fmt = detect_format_bytes(received.head, label)
        except UnsupportedFileError as exc:
            tmp.unlink(missing_ok=True)
            raise HTTPException(415, str(exc)) from exc
        if fmt not in ALLOWED_FORMATS[kind]:
            tmp.unlink(missing_ok=True)
            raise HTTPException(415, f"{label}: a {fmt.upper()} file cannot be a {kind} (expected {formats})")
        ref = storage.blob_ref(received.sha256, fmt)
        _, created = await run_in_threadpool(storage.commit_blob, tmp, ref)

        info = await run_in_threadpool(_known_info, url, kind, received.sha256, key.id)
        if info is None:
            try:
                result = await call_worker(
                    celery, url, TASK_INSPECT,
                    {"ref": ref, "kind": kind, "label": received.filename},
                    settings.inspect_timeout_seconds,
                )
            except WorkerCallFailed as exc:
                if created:
                    await run_in_threadpool(_drop_blob_if_unused, url, storage, ref, received.sha256)
                raise HTTPException(422, str(exc)) from exc
            except WorkerUnavailable as exc:
                raise HTTPException(503, str(exc)) from exc
            info = result["info"]
        elif received.filename:
            info["name"] = Path(received.filename).stem
        display = received.fields.get("name") or name or Path(received.filename or f"{kind}.{fmt}").stem
        out, replayed = await run_in_threadpool(
            _insert_asset, url, (idempotency_key, scope, fp) if idempotency_key else None,
            id=new_id(ID_PREFIX[kind]), kind=kind, owner_id=key.id, origin="upload", name=display[:300],
            filename=received.filename, format=fmt, sha256=received.sha256, size_bytes=received.size, info=info,
        )
        return answer_asset(response, out, replayed)

    @router.get("", response_model=Page[AssetOut], summary=f"List {coll}")
    def list_assets(
        session: SessionDep,
        key: CurrentKey,
        settings: SettingsDep,
        limit: Annotated[int | None, Query(ge=1, le=MAX_QUERY_INT,
                                           description="Page size (default and maximum are settings)")] = None,
        offset: Annotated[int, Query(ge=0, le=MAX_QUERY_INT)] = 0,
        include_builtin: Annotated[bool, Query(description="List built-in bodies too (characters)")] = True,
    ) -> Page[AssetOut]:
        limit, offset = page_bounds(limit, offset, settings)
        cond = Asset.owner_id == key.id
        if include_builtin and kind == "character":
            cond = or_(cond, Asset.origin == "builtin")
        where = (Asset.kind == kind, cond)
        total = session.scalar(select(func.count()).select_from(Asset).where(*where)) or 0
        rows = session.scalars(
            select(Asset).where(*where)
            .order_by((Asset.origin == "builtin").desc(), Asset.created_at.desc(), Asset.id)
            .limit(limit).offset(offset)
        ).all()
        nxt = offset + limit if offset + limit < total else None
        return Page[AssetOut](items=[asset_out(a) for a in rows], total=total, limit=limit, offset=offset,
                              next_offset=nxt)

    @router.get("/{asset_id}", response_model=AssetOut, summary=f"Get a {kind}",
                responses={404: {"model": ErrorOut}})
    def get_asset(asset_id: str, session: SessionDep, key: CurrentKey) -> AssetOut:
        return asset_out(find_asset(session, key, kind, asset_id))

    @router.get(
        "/{asset_id}/file",
        summary=f"Download a {kind}'s file",
        response_class=FileResponse,
        responses={200: {"content": {"model/gltf-binary": {}, "application/octet-stream": {}}},
                   404: {"model": ErrorOut}},
    )
    def download(asset_id: str, session: SessionDep, key: CurrentKey, storage: StorageDep) -> FileResponse:
        asset = find_asset(session, key, kind, asset_id)
        if not asset.sha256 or not asset.format:
            raise HTTPException(404, f"{kind} {asset_id!r} has no file yet (a built-in body is generated on first "
                                     "use by a worker)")
        path = storage.blob_path(storage.blob_ref(asset.sha256, asset.format))
        if not path.is_file():
            raise HTTPException(404, f"the file of {kind} {asset_id!r} is missing from storage")
        name = asset.filename or f"{asset.name}.{asset.format}"
        return FileResponse(path, media_type=ASSET_CONTENT_TYPES.get(asset.format, "application/octet-stream"),
                            filename=name)

    @router.delete("/{asset_id}", status_code=204, summary=f"Delete a {kind}",
                   responses={404: {"model": ErrorOut}, 409: {"model": ErrorOut}})
    def delete_asset(asset_id: str, session: SessionDep, key: CurrentKey, storage: StorageDep) -> Response:
        asset = find_asset(session, key, kind, asset_id)
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
        return Response(status_code=status.HTTP_204_NO_CONTENT)

    return router
