"""Characters and motions: upload (multipart or raw body), list, get, download, delete. One factory, two routers."""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import APIRouter, HTTPException, Query, Request, Response, status
from fastapi.responses import FileResponse
from sqlalchemy import func, or_, select

from api import idempotency
from api.deps import CeleryDep, CurrentKey, SessionDep, SettingsDep, StorageDep
from api.models import Asset
from api.pages import MAX_QUERY_INT, page_bounds
from api.routing import SessionRoute
from api.schemas import AssetOut, ErrorOut, Page
from api.serialize import ASSET_CONTENT_TYPES, asset_out, collection
from api.services import assets as service
from api.services.assets import ALLOWED_FORMATS, AssetKind

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


def _upload_responses(kind: str, formats: str) -> dict[int | str, dict[str, Any]]:
    return {
        400: {"model": ErrorOut, "description": "Malformed request (no file part, empty body)"},
        408: {"model": ErrorOut, "description": "The body stalled or took too long"},
        413: {"model": ErrorOut, "description": "Over the upload size limit"},
        415: {"model": ErrorOut, "description": f"Not a {kind} file type ({formats})"},
        422: {"model": ErrorOut, "description": "The parser rejected the file; the message says why"},
        429: {"model": ErrorOut, "description": "Over the key's storage quota"},
        503: {"model": ErrorOut, "description": "No worker answered in time, or too many uploads at once"},
    }


def _add_upload(router: APIRouter, kind: AssetKind) -> None:
    formats = ", ".join(f.upper() for f in ALLOWED_FORMATS[kind])

    @router.post(
        "", status_code=201, response_model=AssetOut, summary=f"Upload a {kind}",
        description=f"Upload a {kind} file ({formats}). The file is streamed to disk under the size cap, its type "
        "is detected from its content, and a worker parses it before it is accepted. The answer says what was "
        "found (joints, mapping report, frames, fps, height, warnings). Identical files are stored once. With an "
        "Idempotency-Key header, a repeated upload answers with the asset the first one made. A file name is kept "
        "without its directory part and control characters; one that is left empty (such as '.' or '..') is "
        "dropped, and the asset is named after its kind.",
        responses=_upload_responses(kind, formats), openapi_extra=UPLOAD_BODY,
    )
    async def upload(
        request: Request, response: Response, key: CurrentKey, settings: SettingsDep, storage: StorageDep,
        celery: CeleryDep,
        name: Annotated[str | None, Query(max_length=300, description="Display name")] = None,
        filename: Annotated[str | None, Query(max_length=300, description="File name of a raw-body upload")] = None,
        idempotency_key: idempotency.IdempotencyKey = None,
    ) -> AssetOut:
        del filename  # read by receive_upload from the query string; declared here for the OpenAPI document
        out, replayed = await service.upload_asset(request, kind, key, settings, storage, celery, name,
                                                   idempotency_key)
        return service.answer_asset(response, out, replayed)


def _add_list(router: APIRouter, kind: AssetKind) -> None:
    @router.get("", response_model=Page[AssetOut], summary=f"List {collection(kind)}")
    def list_assets(
        session: SessionDep, key: CurrentKey, settings: SettingsDep,
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


def _add_get_download_delete(router: APIRouter, kind: AssetKind) -> None:
    @router.get("/{asset_id}", response_model=AssetOut, summary=f"Get a {kind}",
                responses={404: {"model": ErrorOut}})
    def get_asset(asset_id: str, session: SessionDep, key: CurrentKey) -> AssetOut:
        return asset_out(service.find_asset(session, key, kind, asset_id))

    @router.get(
        "/{asset_id}/file", summary=f"Download a {kind}'s file", response_class=FileResponse,
        responses={200: {"content": {"model/gltf-binary": {}, "application/octet-stream": {}}},
                   404: {"model": ErrorOut}},
    )
    def download(asset_id: str, session: SessionDep, key: CurrentKey, storage: StorageDep) -> FileResponse:
        asset = service.find_asset(session, key, kind, asset_id)
        if not asset.sha256 or not asset.format:
            raise HTTPException(404, f"{kind} {asset_id!r} has no file yet (a built-in body is generated on first "
                                     "use by a worker)")
        path = storage.blob_path(storage.blob_ref(asset.sha256, asset.format))
        if not path.is_file():
            raise HTTPException(404, f"the file of {kind} {asset_id!r} is missing from storage")
        return FileResponse(path, media_type=ASSET_CONTENT_TYPES.get(asset.format, "application/octet-stream"),
                            filename=service.download_name(asset))

    @router.delete("/{asset_id}", status_code=204, summary=f"Delete a {kind}",
                   responses={404: {"model": ErrorOut}, 409: {"model": ErrorOut}})
    def delete_asset(asset_id: str, session: SessionDep, key: CurrentKey, storage: StorageDep) -> Response:
        service.delete_asset(session, storage, service.find_asset(session, key, kind, asset_id))
        return Response(status_code=status.HTTP_204_NO_CONTENT)


def make_router(kind: AssetKind) -> APIRouter:
    """The router of ``/v1/characters`` or ``/v1/motions``."""
    router = APIRouter(prefix=f"/v1/{collection(kind)}", tags=[collection(kind)], route_class=SessionRoute)
    _add_upload(router, kind)
    _add_list(router, kind)
    _add_get_download_delete(router, kind)
    return router


character_router = make_router("character")
motion_router = make_router("motion")
