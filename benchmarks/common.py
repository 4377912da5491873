"""What the benchmark, diagnostic and evaluation scripts share: where things are (the repository, the shared data,
each purpose's results), the common options, writing a result JSON, timing, a whole job timed as the worker runs
it, a clip loaded at the judge's rate, one held-out case as ``retarget eval`` prepares it, and the service
benchmarks' ports, Redis databases and process groups.

The standard library only at import: the service benchmarks run with the API's install (no torch); what needs
``retarget_core`` imports it inside the function. A script under ``benchmarks/<purpose>/`` puts the repository on
``sys.path`` and imports this module as ``benchmarks.common``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import secrets
import signal
import socket
import statistics
import subprocess
import tempfile
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from retarget_core.canonical import JointMapping
    from retarget_core.character import Character
    from retarget_core.loading import LoadedMotion
    from retarget_core.metrics.acceptance import ClipAcceptance
    from retarget_core.motion import Motion
    from retarget_core.retargeted import Prepared

REPO = Path(__file__).resolve().parents[1]
SAMPLES = REPO / "retarget_core" / "data" / "samples"
BULKY_SAMPLE = SAMPLES / "characters" / "mh_male_bulky.glb"
"""The 13,380-vertex sample body the job benchmark times."""
SHARED_DATA = Path(os.environ.get("RETARGET_SHARED_DATA", REPO.parent / "shared" / "data"))
"""The shared data set: ``$RETARGET_SHARED_DATA``, or ``../shared/data`` beside the repository."""
PURPOSES = ("bench", "diag", "eval", "train")
JUDGE_FPS = 30.0
"""What ``retarget eval`` (and the judge) resamples every clip to."""
REFERENCE_HEIGHT_M = 1.80
"""Lengths are reported at a character of this height (ACCEPTANCE.md)."""


# --- where things are ---------------------------------------------------------------------------------------


def results_dir(purpose: str) -> Path:
    """``benchmarks/<purpose>/results``, where the scripts of ``purpose`` (bench, diag, eval, train) write."""
    if purpose not in PURPOSES:
        raise ValueError(f"unknown purpose {purpose!r}: one of {', '.join(PURPOSES)}")
    return REPO / "benchmarks" / purpose / "results"


def clip_path(name: str, collection: str = "cmu") -> Path:
    """A shared clip by name (``002_08`` -> ``<shared data>/motions/cmu/002_08.bvh``)."""
    return SHARED_DATA / "motions" / collection / f"{name}.bvh"


def character_path(name: str) -> Path:
    """A shared character by name (``mh_male_bulky`` -> ``<shared data>/characters/mh_male_bulky.glb``)."""
    return SHARED_DATA / "characters" / f"{name}.glb"


def shared_data() -> Path:
    """The shared data folder; a clear exit when it is not there."""
    if not (SHARED_DATA / "characters").is_dir():
        raise SystemExit(f"the shared data set is needed: {SHARED_DATA} has no characters/ "
                         "(put it at ../shared/data beside the repository, or set RETARGET_SHARED_DATA)")  # fmt: skip
    return SHARED_DATA


# --- options and output -----------------------------------------------------------------------------------


def parser(doc: str | None) -> argparse.ArgumentParser:
    """An argument parser whose ``--help`` prints the script's docstring as written."""
    return argparse.ArgumentParser(description=doc, formatter_class=argparse.RawDescriptionHelpFormatter)


def add_output(ap: argparse.ArgumentParser, default: Path, what: str = "the result JSON") -> None:
    """``-o`` / ``--output`` / ``--out`` (one option, ``args.output``)."""
    shown = default.relative_to(REPO) if default.is_relative_to(REPO) else default
    ap.add_argument("-o", "--output", "--out", dest="output", type=Path, default=default, help=f"{what} ({shown})")


def add_clip_options(ap: argparse.ArgumentParser, frames: int = 300, fps: float = JUDGE_FPS,
                     motion: Path | None = None) -> None:  # fmt: skip
    """``--motion`` (a clip file; default CMU 002_08, two-hand grips), ``--frames`` and ``--fps``."""
    ap.add_argument("--motion", type=Path, default=motion or clip_path("002_08"), help="the clip (BVH, GLB, FBX)")
    ap.add_argument("--frames", type=int, default=frames, help="frames at --fps")
    ap.add_argument("--fps", type=float, default=fps)


def commit() -> str | None:
    """The checked-out commit (``+dirty`` when tracked files have changes), or None outside git."""
    def git(*args: str) -> str:
        return subprocess.run(["git", *args], cwd=REPO, capture_output=True, text=True, check=True).stdout.strip()

    try:
        return git("rev-parse", "--short", "HEAD") + ("+dirty" if git("status", "--porcelain", "--untracked-files=no") else "")
    except (OSError, subprocess.CalledProcessError):
        return None


def machine() -> dict[str, Any]:
    """Where and when a figure was taken: CPUs, platform, Python, the 1-minute load, the time, the commit."""
    return {"cpus": os.cpu_count(), "platform": platform.platform(), "python": platform.python_version(),
            "load_average_1min": round(os.getloadavg()[0], 2), "when": time.strftime("%Y-%m-%d %H:%M:%S"),
            "commit": commit()}  # fmt: skip


def write_json(path: Path, data: Any, quiet: bool = False) -> Path:
    """``data`` as indented JSON at ``path`` (folders made); prints where unless ``quiet``."""
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(data, indent=1) + "\n")
    if not quiet:
        print(f"wrote {path}", flush=True)
    return path


def mean(values: list[float | None], digits: int = 4) -> float | None:
    """The mean of the values that are not None, rounded; None when there are none."""
    kept = [v for v in values if v is not None]
    return round(statistics.fmean(kept), digits) if kept else None


# --- timing -----------------------------------------------------------------------------------------------


@dataclass
class Timing:
    """Wall-clock and process CPU seconds of a block (CPU is the figure to read on a shared machine)."""

    wall_s: float = 0.0
    cpu_s: float = 0.0

    def ms_per_frame(self, frames: int) -> float:
        return round(1000.0 * self.wall_s / max(frames, 1), 3)

    def cpu_ms_per_frame(self, frames: int) -> float:
        return round(1000.0 * self.cpu_s / max(frames, 1), 3)


@contextmanager
def timer() -> Iterator[Timing]:
    """``with timer() as t: ...``; ``t.wall_s`` and ``t.cpu_s`` are set when the block ends."""
    t = Timing()
    wall, cpu = time.perf_counter(), time.process_time()
    try:
        yield t
    finally:
        t.wall_s, t.cpu_s = time.perf_counter() - wall, time.process_time() - cpu


def profile_to(out: Path, fn: Callable[[], object]) -> Path:
    """Run ``fn`` under pyinstrument and write its call tree (calls under 1 % of the time hidden) to ``out``."""
    from pyinstrument import Profiler

    profiler = Profiler(interval=0.005)
    with profiler:
        fn()
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(profiler.output_text(unicode=False, color=False, show_all=False, time="seconds"))
    print(f"wrote {out}", flush=True)
    return out


def jerk(motion: Motion, height: float) -> float:
    """Mean third difference of joint positions (m per frame^3) at a 1.80 m character (ACCEPTANCE.md)."""
    _, p = motion.global_transforms()
    p = p * (REFERENCE_HEIGHT_M / height)
    return float((p[3:] - 3 * p[2:-1] + 3 * p[1:-2] - p[:-3]).norm(dim=-1).mean())


# --- a whole job, as the worker runs it -------------------------------------------------------------------


def source_frames(motion: Path, frames: int, fps: float) -> int:
    """The source frames of ``motion`` that make ``frames`` frames at ``fps``."""
    from retarget_core.loading import load_motion

    src_fps = load_motion(motion).motion.fps
    return max(2, int(round((frames - 1) * src_fps / fps)) + 1)


def run_job_once(motion: Path, target: str, frames: int, fps: float, stages_on: bool | None,
                 switched: dict[str, bool] | None = None) -> dict[str, Any]:  # fmt: skip
    """One job (``pipeline.run_job``) in a scratch folder: wall and CPU seconds, the pipeline's seconds per stage,
    the stages' reports and whether the per-body cache was warm. ``stages_on``: every refinement stage on (True)
    or off (False); None: the default chain; ``switched``: stages then switched on or off by name."""
    from retarget_core.jobs import JobInputs
    from retarget_core.options import RetargetOptions
    from retarget_core.pipeline import run_job
    from retarget_core.stages import REFINEMENT_STAGE_NAMES

    stages = {} if stages_on is None else {n: stages_on for n in REFINEMENT_STAGE_NAMES}
    extra: dict[str, Any] = {"stages": {**stages, **(switched or {})}}
    opts = RetargetOptions(fps=fps, frame_end=source_frames(motion, frames, fps), **extra)
    with tempfile.TemporaryDirectory() as tmp, timer() as t:
        out = run_job(JobInputs(motion, target, options=opts), Path(tmp))
        report = json.loads(out.metrics_json.read_text())
    return {"frames": report["before"]["summary"]["frames"], "wall_s": round(t.wall_s, 3), "cpu_s": round(t.cpu_s, 3),
            "stage_s": out.stage_seconds, "stage_reports": report["context"].get("stage_reports", {}),
            "body_cache": report["context"]["body_cache"]}  # fmt: skip


def per_frame_ms(run: dict[str, Any]) -> dict[str, float]:
    """A :func:`run_job_once` result in ms per frame: each stage, the whole job (wall) and its CPU."""
    n = run["frames"]
    out = {k: round(1000 * v / n, 2) for k, v in run["stage_s"].items()}
    out["whole job"] = round(1000 * run["wall_s"] / n, 2)
    out["whole job (cpu)"] = round(1000 * run["cpu_s"] / n, 2)
    return out


# --- a clip as the judge reads it ---------------------------------------------------------------------------


def load_clip(path: Path, fps: float | None = JUDGE_FPS, frames: int | None = None) -> LoadedMotion:
    """``path`` read, resampled to ``fps`` (None or <= 0: the file's rate) and cut to its first ``frames``."""
    from retarget_core.loading import load_motion
    from retarget_core.resample import resample, select_frames

    loaded = load_motion(path)
    motion = loaded.motion if not fps or fps <= 0 else resample(loaded.motion, fps)
    loaded.motion = select_frames(motion, 0, frames) if frames else motion
    return loaded


def source_view(loaded: LoadedMotion) -> tuple[Character, JointMapping, Motion]:
    """The clip performed by its source body: a GLB's own mesh, or the built-in body fitted to a bare
    skeleton's bones (``source_body.py``), as the pipeline does; ``(body, its mapping, the copied motion)``."""
    from retarget_core.copy_retarget import copy_retarget
    from retarget_core.source_body import source_body_for

    if loaded.source_character is not None:
        body, body_map = loaded.source_character.character, loaded.source_character.mapping
    else:
        body, body_map = source_body_for(loaded.motion.skeleton, loaded.mapping)
    return body, body_map, copy_retarget(loaded.motion, loaded.mapping, body.skeleton, body_map)


# --- one held-out case, as `retarget eval` prepares it ------------------------------------------------------


def case_parser(description: str | None, frames: int = 100) -> argparse.ArgumentParser:
    """The diagnostics' common arguments: clip, body, ``--frames``, ``--source-body``, ``--json``."""
    ap = parser(description)
    ap.add_argument("clip", type=Path, help="the clip (BVH)")
    ap.add_argument("body", help="the target body (GLB, or builtin:<preset>)")
    ap.add_argument("--frames", type=int, default=frames, help="first frames at 30 fps")
    ap.add_argument("--source-body", default="builtin:male_average", help="the body the clip is sent on")
    ap.add_argument("--json", type=Path, default=None, help="also write the figures here")
    return ap


def setting_overrides(defaults: object, pairs: list[str]) -> dict[str, Any]:
    """``KEY=VALUE`` numeric settings of a settings dataclass ``defaults``; ``FIELD.NAME=VALUE`` sets one entry of a
    dict field (e.g. ``end_effectors.LeftHand=2``)."""
    out: dict[str, Any] = {}
    for key, value in (kv.split("=", 1) for kv in pairs):
        name, _, entry = key.partition(".")
        if entry:
            table = dict(out.get(name, getattr(defaults, name)))
            table[entry] = float(value)
            out[name] = table
        else:
            out[name] = type(getattr(defaults, name))(float(value))
    return out


@dataclass
class HeldoutCase:
    """prepared: the job on the target; source: the judge's measures of the source file, performed by
    ``source_character`` (with ``source_mapping``)."""

    prepared: Prepared
    source: ClipAcceptance
    source_character: Character
    source_mapping: JointMapping


def prepare_case(clip: Path, body: str, frames: int, source_body: str, method: str = "full") -> HeldoutCase:
    """``clip`` (its first ``frames`` frames at 30 fps) sent as a GLB on ``source_body`` and prepared on ``body``
    with ``method``'s options (see :func:`retarget_core.evaluation.method_options`)."""
    from retarget_core.evaluation import judged_source, method_options, source_as_glb
    from retarget_core.jobs import JobInputs
    from retarget_core.metrics.acceptance import measure_acceptance
    from retarget_core.pipeline import prepare

    with tempfile.TemporaryDirectory(prefix="heldout-case-") as tmp:
        glb = source_as_glb(clip, source_body, Path(tmp) / f"{clip.stem}.glb", frames, JUDGE_FPS)
        prepared = prepare(JobInputs(glb, body, None, method_options(method, JUDGE_FPS)), max_frames=frames)
        judged = judged_source(glb, prepared)
    if judged is None:
        raise ValueError(f"{clip}: the source GLB could not be read back with its body")
    character, mapping, motion = judged
    return HeldoutCase(prepared, measure_acceptance(character, mapping, motion), character, mapping)


# --- drawing (the renders) -------------------------------------------------------------------------------


def frame_3d(ax: Any, verts: Any, faces: Any, view: tuple[float, float], focus: Any = None,
             radius: float | None = None, zoom: float = 1.0) -> Any:  # fmt: skip
    """Frame a matplotlib 3D axis on a Y-up mesh: ``verts (V, 3)`` already in matplotlib's z-up order, the
    whole mesh, or the cube of half-size ``radius`` around ``focus (3,)`` (Y-up); ``view``: (elevation,
    azimuth) degrees. Returns which faces ``(T,)`` (bool) lie inside the frame."""
    if focus is not None and radius is not None:
        c, r = focus[[0, 2, 1]], radius
        keep = (abs(verts[faces] - c).max(-1) < r).all(1)
    else:
        lo, hi = verts.min(0), verts.max(0)
        c, r = (lo + hi) / 2, (hi - lo).max() / 2
        keep = faces[:, 0] >= 0
    ax.set_xlim(c[0] - r, c[0] + r)
    ax.set_ylim(c[1] - r, c[1] + r)
    ax.set_zlim(c[2] - r, c[2] + r)
    ax.set_box_aspect((1, 1, 1), zoom=zoom)
    ax.view_init(elev=view[0], azim=view[1])
    ax.set_axis_off()
    return keep


# --- the service benchmarks ---------------------------------------------------------------------------------


def free_port() -> int:
    """A TCP port free on 127.0.0.1 now."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def claim_redis_db(host: str = "127.0.0.1", port: int = 6379) -> tuple[Any, int]:
    """An empty Redis database (15 down to 1) on the local server, locked for an hour and flushed; its client
    and number. Exits when every one is in use."""
    import redis

    token = secrets.token_hex(8)
    for db in range(15, 0, -1):
        r = redis.Redis(host, port, db=db, socket_timeout=2)
        if r.dbsize() == 0 and r.set("retarget-benchmark:lock", token, nx=True, ex=3600):
            r.flushdb()
            return r, db
    raise SystemExit(f"no empty Redis database (1-15) at {host}:{port}")


def service_env(root: Path, database_url: str, **extra: str) -> dict[str, str]:
    """The environment of an API or worker process on ``root``'s data and ``database_url``: this one without
    the service's own settings, plus ``extra`` (e.g. ``REDIS_URL``); one thread per process."""
    env = {k: v for k, v in os.environ.items()
           if not k.startswith("RETARGET_API_") and k not in ("DATABASE_URL", "REDIS_URL")}  # fmt: skip
    env.update({"PYTHONPATH": str(REPO), "RETARGET_API_DATA_DIR": str(root / "data"),
                "RETARGET_API_DATABASE_URL": database_url, "OMP_NUM_THREADS": "1", **extra})  # fmt: skip
    return env


def stop_group(proc: subprocess.Popen[bytes], wait_s: float = 30.0) -> None:
    """SIGTERM to ``proc``'s process group (started with ``start_new_session``), SIGKILL after ``wait_s``."""
    if proc.poll() is None:
        os.killpg(proc.pid, signal.SIGTERM)
    try:
        proc.wait(wait_s)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait(wait_s)


def percentiles(seconds: list[float], digits: int = 1) -> dict[str, float | int | None]:
    """Latencies (s) as ``n``, ``p50_ms``, ``p95_ms``, ``p99_ms``, ``mean_ms`` and ``max_ms``."""
    ms = sorted(s * 1000 for s in seconds)
    if not ms:
        return {"n": 0, "p50_ms": None, "p95_ms": None, "p99_ms": None, "mean_ms": None, "max_ms": None}
    q = statistics.quantiles(ms, n=100, method="inclusive") if len(ms) > 1 else ms * 99
    return {"n": len(ms), "p50_ms": round(q[49], digits), "p95_ms": round(q[94], digits),
            "p99_ms": round(q[98], digits), "mean_ms": round(statistics.fmean(ms), digits),
            "max_ms": round(ms[-1], digits)}  # fmt: skip
