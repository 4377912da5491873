"""Review links: make, list and revoke them (with the job owner's key); open a review with a link's token only
(read-only: the job's state and its result files, nothing else)."""

from __future__ import annotations

from datetime import datetime, timedelta
from typing import Any

from fastapi import APIRouter, HTTPException, Response
from fastapi.responses import FileResponse
from pydantic import BaseModel, Field
from sqlalchemy import select
from sqlalchemy.orm import Session

from api import reviewlinks
from api.db import utcnow
from api.deps import CurrentKey, SessionDep, SettingsDep, StorageDep
from api.models import Job, ReviewLink
from api.routing import SessionRoute
from api.schemas import NO_NUL, ErrorOut
from api.serialize import RESULT_FILES
from api.services.jobs import find_job
from api.settings import Settings

router = APIRouter(tags=["reviews"], route_class=SessionRoute)


class ReviewLinkCreate(BaseModel):
    expires_in_seconds: float | None = Field(default=None, gt=0, description="Life of the link; default and "
                                             "maximum are settings (7 and 30 days)")
    label: str | None = Field(default=None, max_length=200, pattern=NO_NUL,
                              description="Who it is for (shown in the list)")


class ReviewLinkOut(BaseModel):
    id: str
    job_id: str
    label: str | None
    created_at: datetime
    expires_at: datetime
    revoked: bool
    token: str | None = Field(default=None, description="Only in the answer that made it")
    url: str | None = Field(default=None, description="The review API of the link (only in the answer that made it)")


class ReviewOut(BaseModel):
    """One job as a reviewer sees it: its state and links to its result files (no key needed, read-only)."""

    job_id: str
    status: str
    stage: str | None
    progress: float
    message: str | None
    summary: dict[str, Any] | None
    warnings: list[str]
    created_at: datetime
    finished_at: datetime | None
    expires_at: datetime
    results: dict[str, str] | None


def _link_out(link: ReviewLink, token: str | None = None) -> ReviewLinkOut:
    return ReviewLinkOut(id=link.id, job_id=link.job_id, label=link.label, created_at=link.created_at,
                         expires_at=link.expires_at, revoked=link.revoked_at is not None, token=token,
                         url=f"/v1/review/{token}" if token else None)


@router.post("/v1/jobs/{job_id}/review-links", status_code=201, response_model=ReviewLinkOut,
             summary="Make a read-only review link for a job", responses={404: {"model": ErrorOut}})
def create_link(job_id: str, body: ReviewLinkCreate, session: SessionDep, key: CurrentKey,
                settings: SettingsDep) -> ReviewLinkOut:
    job = find_job(session, key, job_id)
    life = min(body.expires_in_seconds or settings.review_link_default_seconds, settings.review_link_max_seconds)
    now = utcnow().replace(microsecond=0)
    link = ReviewLink(job_id=job.id, owner_id=key.id, label=body.label, created_at=now,
                      expires_at=now + timedelta(seconds=int(max(1.0, life))))
    session.add(link)
    session.flush()
    return _link_out(link, reviewlinks.make_token(settings, link))


@router.get("/v1/jobs/{job_id}/review-links", response_model=list[ReviewLinkOut], summary="List a job's review links",
            responses={404: {"model": ErrorOut}})
def list_links(job_id: str, session: SessionDep, key: CurrentKey) -> list[ReviewLinkOut]:
    find_job(session, key, job_id)
    rows = session.scalars(select(ReviewLink).where(ReviewLink.job_id == job_id).order_by(ReviewLink.created_at))
    return [_link_out(r) for r in rows]


@router.delete("/v1/jobs/{job_id}/review-links/{link_id}", status_code=204, summary="Revoke a review link",
               responses={404: {"model": ErrorOut}})
def revoke_link(job_id: str, link_id: str, session: SessionDep, key: CurrentKey) -> Response:
    find_job(session, key, job_id)
    link = session.get(ReviewLink, link_id)
    if link is None or link.job_id != job_id:
        raise HTTPException(404, f"review link {link_id!r} not found")
    link.revoked_at = link.revoked_at or utcnow()
    # Committed before the 204 goes out: a revocation the client was told about must already hold for the next
    # request, whichever thread and connection serve it.
    session.commit()
    return Response(status_code=204)


def _open(session: Session, settings: Settings, token: str) -> tuple[ReviewLink, Job]:
    parsed = reviewlinks.parse_token(token)
    link = session.get(ReviewLink, parsed[0]) if parsed else None
    if link is None or not reviewlinks.valid(settings, link, token, utcnow()):
        raise HTTPException(404, "this review link is unknown, expired or revoked")
    job = session.get(Job, link.job_id)
    if job is None:
        raise HTTPException(404, "this review link is unknown, expired or revoked")
    return link, job


@router.get("/v1/review/{token}", response_model=ReviewOut, summary="Open a review (no key: the token is the access)",
            responses={404: {"model": ErrorOut}})
def open_review(token: str, session: SessionDep, settings: SettingsDep) -> ReviewOut:
    link, job = _open(session, settings, token)
    results = None
    if job.status == "succeeded" and job.outputs:
        results = {RESULT_FILES[n][0]: f"/v1/review/{token}/{n}" for n in RESULT_FILES if n in job.outputs}
    return ReviewOut(job_id=job.id, status=job.status, stage=job.stage, progress=min(1.0, max(0.0, job.progress)),
                     message=job.message, summary=job.summary, warnings=[str(w) for w in job.warnings or []],
                     created_at=job.created_at, finished_at=job.finished_at, expires_at=link.expires_at,
                     results=results)


@router.get("/v1/review/{token}/{name}", response_class=FileResponse, summary="A result file of a reviewed job",
            responses={200: {"content": {"model/gltf-binary": {}, "application/json": {}}},
                       404: {"model": ErrorOut}})
def review_file(token: str, name: str, session: SessionDep, settings: SettingsDep, storage: StorageDep
                ) -> FileResponse:
    _, job = _open(session, settings, token)
    rel = (job.outputs or {}).get(name) if job.status == "succeeded" and name in RESULT_FILES else None
    path = storage.resolve(rel) if rel else None
    if path is None or not path.is_file():
        raise HTTPException(404, f"this review has no {name[:40]!r}")
    return FileResponse(path, media_type=RESULT_FILES[name][1], filename=f"{job.id}-{name}")
