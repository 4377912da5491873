"""Request and response bodies of the HTTP API (pydantic). Light: the worker imports these for webhook payloads."""

from __future__ import annotations

from datetime import datetime
from typing import Annotated, Any, Generic, Literal, TypeVar

from pydantic import AnyHttpUrl, BaseModel, ConfigDict, Field

from retarget_core.bodies.params import BodyParams
from retarget_core.options import RetargetOptions

JobStatus = Literal["queued", "running", "succeeded", "failed", "canceled"]
FINISHED: tuple[str, ...] = ("succeeded", "failed", "canceled")
T = TypeVar("T")

_INSPECT_EXAMPLE: dict[str, Any] = {
    "format": "bvh",
    "joints": ["CC_Base_BoneRoot", "CC_Base_Hip", "CC_Base_Pelvis", "..."],
    "mapping": {"Hips": {"joint": "CC_Base_Hip", "confidence": 1.0}},
    "frames": 412,
    "fps": 60.0,
    "duration": 6.87,
    "height": 1.71,
    "warnings": [],
}


# An asset id as the API makes them (``mot_...``, ``chr_...``, ``builtin:<preset>``): a request naming anything
# else is a 422 at once, not a database lookup of arbitrary text.
ResourceId = Annotated[str, Field(min_length=1, max_length=100, pattern=r"^[A-Za-z0-9_:.-]+$")]

NO_NUL = r"^[^\x00]*$"
"""Texts the database stores: a NUL character cannot be stored (PostgreSQL), so the schema refuses it."""


class BodyShape(BodyParams):
    """BodyParams as a request gives them (its name is stored, so no NUL character)."""

    name: str = Field(default="makehuman", max_length=300, pattern=NO_NUL)


class ErrorOut(BaseModel):
    """Every error: a sentence a person can act on."""

    detail: str = Field(examples=["not a recognised file type (expected BVH, glTF 2.0 / GLB or FBX)"])
    errors: list[dict[str, Any]] | None = Field(
        default=None, description="For an invalid request (422): each problem with its location (loc), message "
        "(msg) and type")


class Page(BaseModel, Generic[T]):
    """One page of a list; ask for the next with ``offset=next_offset``."""

    items: list[T]
    total: int = Field(description="Items matching the filters, over all pages")
    limit: int
    offset: int
    next_offset: int | None = Field(description="Offset of the next page, or null on the last page")


class AssetOut(BaseModel):
    """A character or a motion, with what the parser found in it."""

    model_config = ConfigDict(
        json_schema_extra={
            "examples": [
                {
                    "id": "mot_5b1e0c3a9d2f4e6a7b8c9d0e",
                    "kind": "motion",
                    "name": "007_03",
                    "builtin": False,
                    "origin": "upload",
                    "filename": "007_03.bvh",
                    "format": "bvh",
                    "size_bytes": 734212,
                    "sha256": "9f2c...",
                    "created_at": "2026-11-22T10:00:00Z",
                    "info": _INSPECT_EXAMPLE,
                    "params": None,
                    "links": {"self": "/v1/motions/mot_5b1e...", "file": "/v1/motions/mot_5b1e.../file"},
                }
            ]
        }
    )

    id: str
    kind: Literal["character", "motion"]
    name: str
    builtin: bool = Field(description="A built-in body shared by every key (characters only)")
    origin: Literal["upload", "generated", "builtin"]
    filename: str | None
    format: str | None = Field(description="bvh, glb, gltf or fbx, detected from the content")
    size_bytes: int | None
    sha256: str | None
    created_at: datetime
    info: dict[str, Any] = Field(
        description="What the parser found: format, joints, mapping report, frames, fps, duration, height, warnings"
    )
    params: dict[str, Any] | None = Field(default=None, description="Shape parameters of a generated body")
    links: dict[str, str]


class BodyCreate(BaseModel):
    """A body made from shape parameters (the MakeHuman generator of retarget_core.bodies)."""

    model_config = ConfigDict(
        json_schema_extra={"examples": [{"name": "tall heavy", "params": {"height": 1.9, "weight": 0.8}}]}
    )

    name: str | None = Field(default=None, max_length=300, pattern=NO_NUL,
                             description="Display name; default: made from params")
    params: BodyShape = Field(
        default_factory=BodyShape,
        description="The body's shape (retarget_core.bodies.params.BodyParams); fields left out keep their defaults",
    )


class JobCreate(BaseModel):
    """One motion on one target character."""

    model_config = ConfigDict(
        json_schema_extra={
            "examples": [
                {
                    "motion_id": "mot_5b1e0c3a9d2f4e6a7b8c9d0e",
                    "target_character_id": "chr_0a1b2c3d4e5f60718293a4b5",
                    "options": {"frame_end": 120, "in_place": False},
                    "callback_url": "https://pipeline.example/hooks/retarget",
                }
            ]
        }
    )

    motion_id: ResourceId = Field(description="A motion id (POST /v1/motions)")
    target_character_id: ResourceId = Field(description="A character id, uploaded or built-in (builtin:<preset>)")
    source_character_id: ResourceId | None = Field(
        default=None, description="The body the motion was performed by; default: the motion's own mesh, or a "
        "built-in body fitted to its bone lengths"
    )
    options: RetargetOptions = Field(default_factory=RetargetOptions)
    callback_url: AnyHttpUrl | None = Field(default=None, description="POSTed a signed JSON when the job ends")
    queue: Literal["cpu", "gpu"] | None = Field(default=None, description="Device kind; default: the server's")


class BatchCreate(BaseModel):
    """Every motion on every character: len(motion_ids) x len(target_character_ids) jobs."""

    model_config = ConfigDict(
        json_schema_extra={
            "examples": [
                {
                    "name": "walks on all bodies",
                    "motion_ids": ["mot_a...", "mot_b..."],
                    "target_character_ids": ["builtin:male_average", "chr_c..."],
                    "options": {"frame_end": 240},
                }
            ]
        }
    )

    name: str | None = Field(default=None, max_length=300, pattern=NO_NUL)
    motion_ids: list[ResourceId] = Field(min_length=1)
    target_character_ids: list[ResourceId] = Field(min_length=1)
    source_character_id: ResourceId | None = None
    options: RetargetOptions = Field(default_factory=RetargetOptions)
    callback_url: AnyHttpUrl | None = None
    queue: Literal["cpu", "gpu"] | None = None


class Timings(BaseModel):
    queued_seconds: float | None = Field(description="From submission (or retry) to the start of the last run")
    run_seconds: float | None = Field(description="Duration of the last run")
    stages: dict[str, float] = Field(default_factory=dict, description="Seconds per pipeline stage")


class WebhookState(BaseModel):
    event: str
    status: Literal["pending", "delivered", "failed"]
    attempts: int
    last_status_code: int | None
    last_error: str | None


class JobOut(BaseModel):
    """A job's state. Poll it, or pass a callback_url."""

    model_config = ConfigDict(
        json_schema_extra={
            "examples": [
                {
                    "id": "job_1c2d3e4f5a6b7c8d9e0f1a2b",
                    "status": "running",
                    "stage": "copy",
                    "progress": 0.4,
                    "message": None,
                    "attempt": 1,
                    "results": None,
                }
            ]
        }
    )

    id: str
    status: JobStatus
    stage: str | None = Field(description="The pipeline stage running now (or last)")
    progress: float = Field(ge=0, le=1, description="Fraction of the job done")
    message: str | None = Field(description="Why it failed or was canceled, in words")
    note: str | None = Field(default=None, description="Why it runs again (its earlier attempt's worker stopped), "
                             "or why it waits (no worker serves its queue)")
    error_kind: Literal["input", "internal", "timeout", "worker_lost"] | None = Field(
        description="input: fix the files or options; internal: a bug, retrying may help; timeout; worker_lost"
    )
    cancel_requested: bool
    attempt: int = Field(description="Runs so far (a vanished worker's job is run again)")
    batch_id: str | None
    motion_id: str
    target_character_id: str
    source_character_id: str | None
    options: dict[str, Any]
    queue: str
    callback_url: str | None
    worker: str | None
    created_at: datetime
    started_at: datetime | None
    finished_at: datetime | None
    updated_at: datetime
    timings: Timings
    summary: dict[str, Any] | None = Field(description="Headline metrics (before and after) when succeeded")
    warnings: list[str]
    results: dict[str, str] | None = Field(
        description="Download links when succeeded: result_glb, before_glb, metrics_json (and source_glb when "
        "the pipeline wrote one)"
    )
    webhook: WebhookState | None
    links: dict[str, str]


class BatchOut(BaseModel):
    """A batch with the aggregate state of its jobs."""

    id: str
    name: str | None
    created_at: datetime
    status: Literal["queued", "running", "succeeded", "failed", "canceled"] = Field(
        description="queued: none started; running: some not finished; succeeded: all succeeded; failed: all "
        "finished and at least one failed; canceled: all finished, none failed, some canceled"
    )
    total: int
    counts: dict[str, int] = Field(description="Jobs per status")
    progress: float = Field(description="Mean progress of the jobs")
    jobs: list[JobOut]
    links: dict[str, str]


class StageOut(BaseModel):
    """One switchable pipeline stage, in pipeline order (the key of ``options.stages``)."""

    name: str
    label: str
    description: str
    default: bool
    available: bool = Field(description="implemented in this version; unavailable stages are skipped with a note")


class ServiceInfo(BaseModel):
    """Limits and facts a client needs before uploading."""

    version: str
    max_upload_bytes: int
    inspect_timeout_seconds: float
    max_batch_jobs: int
    page_size_max: int
    queues: list[str]
    character_formats: list[str]
    motion_formats: list[str]
    result_files: list[str]
    stages: list[StageOut] = Field(default_factory=list, description="The pipeline's switchable stages, in order")


class KeyInfo(BaseModel):
    """The calling key: how to check the signature of its webhooks."""

    id: str
    name: str
    key_prefix: str
    created_at: datetime
    webhook_secret: str = Field(description="HMAC-SHA256 secret of this key's callbacks (unless the server sets one)")
    signature_header: str
