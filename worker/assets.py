"""Worker side of uploads and bodies: parse a stored file, make a body from parameters, register built-in bodies.

Answers to the API go into the ``worker_calls`` row the API is polling.
"""

from __future__ import annotations

import hashlib
import logging
import math
from pathlib import Path
from typing import Any

from sqlalchemy import select
from sqlalchemy.exc import IntegrityError

from api.db import session_scope, utcnow
from api.models import Asset, WorkerCall
from api.redact import redact, redact_all
from api.settings import Settings
from api.storage import Storage
from worker.runner import json_safe

log = logging.getLogger(__name__)


def answer(settings: Settings, call_id: str, result: dict[str, Any] | None = None, error: str | None = None) -> None:
    """Write the outcome of a worker call."""
    with session_scope(settings.resolved_database_url) as s:
        call = s.get(WorkerCall, call_id)
        if call is None:
            return
        call.status = "error" if error is not None else "ok"
        call.message = error
        call.result = json_safe(result) if result is not None else None
        call.finished_at = utcnow()


def user_message(exc: BaseException, path: Path | None, label: str | None) -> str:
    """The parser's message with the storage path replaced by the name the user gave the file."""
    name = label or "the file"
    problem = getattr(exc, "problem", None)
    text = f"{name}: {problem}" if problem else str(exc)
    if path is not None:
        text = text.replace(str(path), name)
    return text


def inspect_blob(settings: Settings, ref: str, kind: str, label: str | None) -> dict[str, Any]:
    """What inspect_file finds in a stored blob. Raises RetargetError subclasses for bad files."""
    from retarget_core.inspect import inspect_file

    path = Storage(settings.data_dir).blob_path(ref)
    info = dict(inspect_file(path, kind))  # type: ignore[arg-type]
    info.setdefault("format", ref.rsplit(".", 1)[1])
    if str(info.get("name", "")).startswith(ref.split(".", 1)[0]):  # named after the blob file
        info["name"] = Path(label).stem if label else None
    return json_safe(info)


def range_problem(info: dict[str, Any], kind: str, settings: Settings) -> str | None:
    """What makes a parsed file unusable although it could be read (frame rate, duration, height), or None."""
    if kind == "motion":
        fps, duration = info.get("fps"), info.get("duration_s")
        if not isinstance(fps, (int, float)) or not settings.min_motion_fps <= fps <= settings.max_motion_fps:
            return (f"the frame rate is {fps!r} frames per second, outside {settings.min_motion_fps:g} to "
                    f"{settings.max_motion_fps:g} (settings RETARGET_API_MIN_MOTION_FPS / _MAX_MOTION_FPS)")
        if not isinstance(duration, (int, float)) or not math.isfinite(duration):
            return f"the duration ({duration!r} s) is not a finite number"
        return None
    height = info.get("height_m")
    if not isinstance(height, (int, float)) or not (
            settings.min_character_height_m <= height <= settings.max_character_height_m):
        shown = f"{height:.4g} m" if isinstance(height, (int, float)) else repr(height)
        return (f"the character is {shown} tall, outside {settings.min_character_height_m:g} to "
                f"{settings.max_character_height_m:g} m (settings RETARGET_API_MIN_CHARACTER_HEIGHT_M / "
                "_MAX_CHARACTER_HEIGHT_M); check the file's units")
    return None


def run_inspect(settings: Settings, call_id: str, ref: str, kind: str, label: str | None) -> None:
    """The inspect task: answer ok with the info, or error with a message naming the problem (and the file by
    the name the user gave it, never by its storage path or blob name)."""
    from retarget_core.errors import RetargetError

    path = Storage(settings.data_dir).blob_path(ref)
    name = label or "the file"
    names = {ref.split(".", 1)[0]: name}
    try:
        info = inspect_blob(settings, ref, kind, label)
    except RetargetError as exc:
        answer(settings, call_id, error=redact(user_message(exc, path, label), names, name))
    except MemoryError:
        answer(settings, call_id, error=f"{name}: reading it needs more memory than a parse may use")
    except Exception as exc:
        log.exception("inspect of %s failed", ref)
        answer(settings, call_id, error=redact(f"{name}: the file could not be read ({type(exc).__name__})",
                                               names, name))
    else:
        problem = range_problem(info, kind, settings)
        if problem:
            answer(settings, call_id, error=f"{name}: {problem}")
        else:
            answer(settings, call_id, {"info": redact_all(info, names, name)})


def store_file(storage: Storage, path: Path, fmt: str) -> tuple[str, str, int]:
    """Move a written file into the blob store; returns (sha256, ref, size)."""
    digest = hashlib.sha256()
    with open(path, "rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            digest.update(chunk)
    sha = digest.hexdigest()
    ref = storage.blob_ref(sha, fmt)
    size = path.stat().st_size
    storage.commit_blob(path, ref)
    return sha, ref, size


def run_make_body(settings: Settings, call_id: str, params: dict[str, Any]) -> None:
    """The make_body task: a MakeHuman body from shape parameters, stored as a GLB blob and inspected."""
    from pydantic import ValidationError

    from retarget_core.errors import RetargetError

    try:
        from retarget_core.bodies.makehuman import BodyParams, make_body
        from retarget_core.io.gltf_write import write_glb
    except ImportError as exc:
        answer(settings, call_id, error=f"this worker cannot make bodies: {exc}")
        return
    try:
        body_params = BodyParams.model_validate(params)
    except ValidationError as exc:
        problems = "; ".join(f"{'.'.join(str(p) for p in e['loc']) or 'params'}: {e['msg']}" for e in exc.errors())
        answer(settings, call_id, error=f"invalid body parameters: {problems}")
        return
    storage = Storage(settings.data_dir)
    tmp = storage.temp_path(".glb")
    try:
        character = make_body(body_params)
        write_glb(character, None, tmp)
        sha, ref, size = store_file(storage, tmp, "glb")
        info = inspect_blob(settings, ref, "character", None)
    except RetargetError as exc:
        answer(settings, call_id, error=f"the body could not be made: {exc}")
        return
    except Exception as exc:
        log.exception("make_body failed")
        answer(settings, call_id, error=f"the body could not be made (internal error {type(exc).__name__}: {exc})")
        return
    finally:
        tmp.unlink(missing_ok=True)
    answer(settings, call_id, {"sha256": sha, "size_bytes": size, "info": info,
                               "params": body_params.model_dump(mode="json"),
                               "name": getattr(character, "name", None)})


def _preset_names(presets: Any) -> list[str]:
    names = []
    for p in presets:
        if isinstance(p, str):
            names.append(p)
        elif isinstance(p, dict):
            names.append(str(p.get("name")))
        else:
            names.append(str(getattr(p, "name", p)))
    return names


def register_builtins(settings: Settings) -> list[str]:
    """List the library's preset bodies as built-in characters (``builtin:<name>``), each with a GLB."""
    from retarget_core.bodies.presets import list_presets, load_preset
    from retarget_core.io.gltf_write import write_glb

    storage = Storage(settings.data_dir)
    url = settings.resolved_database_url
    names = _preset_names(list_presets())
    with session_scope(url) as s:
        existing = {a.id: a for a in s.scalars(select(Asset).where(Asset.origin == "builtin"))}
        for asset_id, asset in existing.items():
            if asset_id.removeprefix("builtin:") not in names:
                s.delete(asset)
    for name in names:
        if f"builtin:{name}" in existing:
            continue
        try:
            with session_scope(url) as s:
                s.add(Asset(id=f"builtin:{name}", kind="character", owner_id=None, origin="builtin", name=name,
                            params={"preset": name}, info={"preset": name}))
        except IntegrityError:  # another io worker registered it at the same time
            pass
    for name in names:
        asset_id = f"builtin:{name}"
        with session_scope(url) as s:
            row = s.get(Asset, asset_id)
            if row is None:
                continue
            if row.sha256 and row.format and storage.blob_path(storage.blob_ref(row.sha256, row.format)).is_file():
                continue
        tmp = storage.temp_path(".glb")
        try:
            write_glb(load_preset(name), None, tmp)
            sha, ref, size = store_file(storage, tmp, "glb")
            info = inspect_blob(settings, ref, "character", f"{name}.glb")
        except Exception:
            log.exception("built-in body %s could not be made", name)
            continue
        finally:
            tmp.unlink(missing_ok=True)
        info["preset"] = name
        with session_scope(url) as s:
            row = s.get(Asset, asset_id)
            if row is not None:
                row.sha256, row.format, row.size_bytes = sha, "glb", size
                row.filename = f"{name}.glb"
                row.info = info
    return names
