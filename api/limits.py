"""Checks made when work is submitted: the size of a job (output frames x target vertices) and per-key quotas.

Each raises HTTPException with a message that names the limit and its setting: 422 for a job that can never
run, 429 for a quota (try again when earlier work has finished or files were deleted).
"""

from __future__ import annotations

import math
from typing import Any

from fastapi import HTTPException
from sqlalchemy import Row, Select, func, select
from sqlalchemy.orm import Session

from api.models import Asset, Job
from api.settings import Settings
from retarget_core.options import RetargetOptions


def output_frames(motion_info: dict[str, Any], options: RetargetOptions) -> int | None:
    """Frames a job will produce from a motion (as its upload was parsed) and the options; None when unknown."""
    frames, fps = motion_info.get("frames"), motion_info.get("fps")
    if not isinstance(frames, int) or not isinstance(fps, (int, float)) or not fps > 0:
        return None
    end = min(options.frame_end or frames, frames)
    span = max(1, end - options.frame_start)
    out_fps = options.fps or float(fps)
    return int(math.floor((span - 1) / float(fps) * out_fps + 1e-9)) + 1


def check_job_size(motion: Asset | Row[Any], target: Asset | Row[Any], options: RetargetOptions, settings: Settings) -> None:
    """422 when output frames x target vertices is over ``max_job_frame_vertices``."""
    frames = output_frames(motion.info or {}, options)
    vertices = (target.info or {}).get("vertices")
    if frames is None or not isinstance(vertices, int):
        return
    if options.frame_start >= int((motion.info or {}).get("frames", 0)):
        raise HTTPException(422, f"options.frame_start: the motion has {motion.info['frames']} frames; "
                                 f"frame_start {options.frame_start} is past its end")
    size = frames * vertices
    if size > settings.max_job_frame_vertices:
        raise HTTPException(
            422, f"the job would make {frames} frames on a target of {vertices} vertices ({size} frame-vertices), "
            f"over the limit of {settings.max_job_frame_vertices} (setting RETARGET_API_MAX_JOB_FRAME_VERTICES); "
            "choose a shorter frame range (frame_start/frame_end) or a lower fps")


def active_jobs_query(owner_id: Any, quota: int) -> Select[Any]:
    """The count of a key's queued and running jobs, at most quota + 1 of them (``owner_id``: a value or a bind
    parameter), so it costs the same however many jobs a key has queued."""
    capped = select(Job.id).where(Job.owner_id == owner_id, Job.status.in_(("queued", "running"))).limit(quota + 1)
    return select(func.count()).select_from(capped.subquery())


def check_active_jobs(session: Session, owner_id: str, adding: int, settings: Settings) -> None:
    """429 when the key would have more than ``max_active_jobs_per_key`` queued or running jobs."""
    active = session.scalar(active_jobs_query(owner_id, settings.max_active_jobs_per_key)) or 0
    refuse_over_quota(active, adding, settings)


def refuse_over_quota(active: int, adding: int, settings: Settings) -> None:
    """429 when ``active`` jobs (counted by :func:`active_jobs_query`) plus ``adding`` pass the quota."""
    quota = settings.max_active_jobs_per_key
    if active + adding > quota:
        shown = f"{active}" if active <= quota else f"more than {quota}"
        raise HTTPException(
            429, f"this key has {shown} queued or running jobs; adding {adding} would pass the quota of "
            f"{settings.max_active_jobs_per_key} (setting RETARGET_API_MAX_ACTIVE_JOBS_PER_KEY); wait for some "
            "to finish", headers={"Retry-After": "30"})


def stored_bytes(session: Session, owner_id: str) -> int:
    """Bytes of the files of a key's uploaded and generated assets."""
    return int(session.scalar(select(func.coalesce(func.sum(Asset.size_bytes), 0)).where(
        Asset.owner_id == owner_id)) or 0)


def check_storage(session: Session, owner_id: str, adding: int, settings: Settings) -> None:
    """429 when a new file of ``adding`` bytes would pass ``max_stored_bytes_per_key``."""
    used = stored_bytes(session, owner_id)
    if used + adding > settings.max_stored_bytes_per_key:
        raise HTTPException(
            429, f"this key stores {used} bytes; {adding} more would pass the quota of "
            f"{settings.max_stored_bytes_per_key} (setting RETARGET_API_MAX_STORED_BYTES_PER_KEY); delete "
            "characters or motions you no longer need", headers={"Retry-After": "3600"})
