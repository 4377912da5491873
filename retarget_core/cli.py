"""Command line: ``retarget run``, ``retarget inspect``, ``retarget bodies``, ``retarget eval``, ``retarget train``."""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any

import typer
from rich.console import Console
from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn
from rich.table import Table

from retarget_core.errors import RetargetError
from retarget_core.stages import STAGE_NAMES, STAGES

if TYPE_CHECKING:
    from retarget_core.retargeted import Retargeted

app = typer.Typer(add_completion=False, no_args_is_help=True, help="Put a human motion onto any skinned character.")
console = Console(stderr=True)


def _load_override(path: Path | None) -> dict[str, str] | None:
    if path is None:
        return None
    from retarget_core.mapping import load_override

    return load_override(path)


@app.command()
def run(
    motion: Annotated[Path, typer.Argument(help="Motion file: BVH, glTF/GLB or FBX", exists=True, dir_okay=False)],
    target: Annotated[str, typer.Argument(help="Target character file (GLB/glTF/FBX) or builtin:<preset>")],
    output: Annotated[
        Path, typer.Option("-o", "--output", help="Result file: .glb (animated character) or .bvh")
    ] = Path("out.glb"),
    before: Annotated[Path | None, typer.Option(help="Also write the copy baseline ('before') GLB here")] = None,
    metrics: Annotated[Path | None, typer.Option(help="Also write the metrics JSON here")] = None,
    source_character: Annotated[str | None, typer.Option(help="Source body file or builtin:<preset>")] = None,
    clip: Annotated[str | None, typer.Option(help="Animation name or index in a multi-clip file")] = None,
    fps: Annotated[float | None, typer.Option(help="Output frame rate (default: the source's)")] = None,
    start: Annotated[int, typer.Option(help="First source frame")] = 0,
    end: Annotated[int | None, typer.Option(help="End source frame (exclusive)")] = None,
    in_place: Annotated[bool, typer.Option(help="Remove horizontal root motion")] = False,
    map_override: Annotated[Path | None, typer.Option(help="JSON {canonical: joint} for the motion's skeleton")] = None,
    target_map_override: Annotated[Path | None, typer.Option(help="JSON {canonical: joint} for the target")] = None,
    off: Annotated[
        list[str] | None, typer.Option("--off", help=f"Switch a stage off (repeatable): {', '.join(STAGE_NAMES)}")
    ] = None,
    on: Annotated[
        list[str] | None, typer.Option("--on", help="Switch on a stage that is off by default (repeatable)")
    ] = None,
    device: Annotated[str, typer.Option(help="Torch device: cpu, cuda, cuda:N or auto")] = "cpu",
) -> None:
    """Retarget MOTION onto TARGET and write an animated GLB (or BVH)."""
    from retarget_core.jobs import JobInputs
    from retarget_core.options import RetargetOptions
    from retarget_core.pipeline import StageClock, retarget

    if output.suffix.lower() not in (".glb", ".bvh"):
        _fail(f"output must end in .glb or .bvh, not {output.suffix!r}")
    unknown = [s for s in (off or []) + (on or []) if s not in STAGE_NAMES]
    if unknown:
        _fail(f"unknown stage(s) {', '.join(unknown)}; stages: {', '.join(STAGE_NAMES)}")
    options = RetargetOptions(
        fps=fps, frame_start=start, frame_end=end, clip=clip, in_place=in_place, device=device,
        stages={s.name: (s.default or s.name in (on or [])) and s.name not in (off or []) for s in STAGES},
        joint_map_override=_load_override(map_override), target_joint_map_override=_load_override(target_map_override),
    )  # fmt: skip
    inputs = JobInputs(motion, target if target.startswith("builtin:") else Path(target), source_character, options)
    with _progress() as bar:
        task = bar.add_task("starting", total=1.0)
        clock = StageClock(progress=lambda stage, frac: bar.update(task, completed=frac, description=stage))
        try:
            result = retarget(inputs, clock)
            report = None
            if metrics is not None:
                with clock.stage("metrics"):
                    report = _metrics_report(result)
            with clock.stage("write"):
                _write_outputs(result, output, before, metrics, report, clock.seconds)
        except RetargetError as exc:
            bar.stop()
            _fail(str(exc))
    for w in result.warnings:
        console.print(f"[yellow]note:[/] {w}")
    m = result.after
    console.print(
        f"wrote {output}: {m.num_frames} frames at {m.fps:g} fps ({m.duration:.2f} s) on "
        f"{result.target.character.name} ({result.target.character.height:.2f} m)"
    )


def _metrics_report(result: Retargeted) -> dict[str, Any]:
    from retarget_core.measure import torch_threads
    from retarget_core.metrics_summary import build_metrics
    from retarget_core.pipeline import PIPELINE_THREADS

    with torch_threads(PIPELINE_THREADS):
        return build_metrics(result)


def _write_outputs(
    result: Retargeted, output: Path, before: Path | None, metrics: Path | None, report: dict[str, Any] | None,
    seconds: dict[str, float],
) -> None:
    from retarget_core.io.bvh import write_bvh
    from retarget_core.io.gltf_write import write_glb

    character = result.target.character
    if output.suffix.lower() == ".bvh":
        write_bvh(result.after, output)
    else:
        write_glb(character, result.after, output, clip_name=result.source.motion.name)
    if before is not None:
        write_glb(character, result.before, before, clip_name=result.source.motion.name)
    if metrics is not None and report is not None:
        report["context"]["stage_seconds"] = seconds
        metrics.write_text(json.dumps(report, separators=(",", ":")))


@app.command()
def inspect(
    file: Annotated[Path, typer.Argument(help="A motion or character file", exists=True, dir_okay=False)],
    kind: Annotated[str | None, typer.Option(help="'motion' or 'character' (default: guessed)")] = None,
    as_json: Annotated[bool, typer.Option("--json", help="Print JSON instead of tables")] = False,
) -> None:
    """Print joints, the mapping report, frames, fps and height of FILE."""
    from retarget_core.inspect import inspect_file
    from retarget_core.io.formats import detect_format

    try:
        chosen = kind or ("motion" if detect_format(file) == "bvh" else _guess_kind(file))
        info = inspect_file(file, chosen)  # type: ignore[arg-type]
    except RetargetError as exc:
        _fail(str(exc))
    if as_json:
        print(json.dumps(info, indent=1))
        return
    _print_info(info)


def _guess_kind(file: Path) -> str:
    from retarget_core.io.fbx import read_fbx
    from retarget_core.io.formats import detect_format
    from retarget_core.io.gltf_read import read_gltf

    contents = read_fbx(file) if detect_format(file) == "fbx" else read_gltf(file)
    return "character" if contents.character is not None and not contents.motions else "motion"


def _print_info(info: dict[str, Any]) -> None:
    out = Console()
    out.print(f"[bold]{info['name']}[/] ({info['kind']}, {info['format']}), {info['joint_count']} joints")
    if info["kind"] == "motion":
        out.print(
            f"frames {info['frames']}, fps {info['fps']:g}, duration {info['duration_s']:.2f} s, clips {info['clips']}"
        )
    else:
        out.print(f"vertices {info['vertices']}, triangles {info['triangles']}, height {info['height_m']:.3f} m")
    for m in info.get("meshes", []):  # the role decided per mesh (docs/meshes.md), a motion file's own mesh too
        out.print(f"mesh {m['name']}: {m['role']} ({m['reason']}), {m['vertices']} vertices")
    norm = info["normalization"]
    out.print(f"units {norm['unit']} (x{norm['scale']:g}), up axis {norm['up_axis']}, rest pose: {norm['rest_pose']}")
    table = Table(title="joint mapping")
    for col in ("canonical", "joint", "confidence", "method"):
        table.add_column(col)
    for canonical, row in info["mapping"]["joints"].items():
        table.add_row(canonical, row["joint"] or "[red]-[/]", f"{row['confidence']:.2f}", row["method"] or "")
    out.print(table)
    if extras := info["mapping"].get("extras"):  # fingers, toes, twist bones (docs/mapping.md)
        table = Table(title="extra joints")
        for col in ("extra", "joint", "confidence", "method"):
            table.add_column(col)
        for name, row in extras.items():
            share = f", share {row['share']:g}" if "share" in row else ""
            table.add_row(name, row["joint"], f"{row['confidence']:.2f}", f"{row['method']}{share}")
        out.print(table)
    for w in info["warnings"]:
        out.print(f"[yellow]note:[/] {w}")


@app.command()
def bodies() -> None:
    """List the built-in bodies (use them as builtin:<name>)."""
    from retarget_core.bodies.presets import PRESETS

    for name, params in PRESETS.items():
        print(f"builtin:{name}\t{params.model_dump_json()}")


def _expand(paths: list[Path], suffixes: tuple[str, ...]) -> list[Path]:
    """Files as given, and the files with one of ``suffixes`` inside the folders given (recursively, sorted)."""
    out: list[Path] = []
    for p in paths:
        out += sorted(f for f in p.rglob("*") if f.suffix.lower() in suffixes) if p.is_dir() else [p]
    return out


@app.command(name="eval")
def evaluate(
    motions: Annotated[
        list[Path] | None, typer.Argument(help="Motion files or folders of them (BVH/GLB/FBX); with --heldout: none")
    ] = None,
    body: Annotated[
        list[str] | None,
        typer.Option("--body", "-b", help="Target body file, folder of them, or builtin:<preset>; repeat for several"),
    ] = None,
    heldout: Annotated[
        Path | None,
        typer.Option(help="Run the fixed held-out split (retarget_core/data/heldout.json): its clips from this "
                     "folder (the shared motions/cmu) on its generated bodies, sources as GLBs on male_average"),
    ] = None,
    split_name: Annotated[
        str | None,
        typer.Option("--split", help="Run a fixed case list instead: 'hard' (retarget_core/data/heldout_hard.json: whole clips "
                     "of the hard kinds on the held-out, extreme and real bodies, sources as GLBs on male_average)"),
    ] = None,
    shared_data: Annotated[
        Path, typer.Option(help="The shared data folder the --split files are read from")
    ] = Path("../shared/data"),
    out: Annotated[Path, typer.Option("-o", "--out", help="Folder for eval.json and eval.md")] = Path("out/eval"),
    method: Annotated[
        list[str] | None,
        typer.Option(help="Methods to compare, repeatable (evaluation.METHODS): copy, collisions, foot_lock, "
                     "collisions+foot_lock, recurrent, recurrent[skeleton|foot|interpenetration] (networks trained "
                     "on part of the energy), recurrent[pointnet] (PointNet geometry code), recurrent+eso, "
                     "recurrent+eso+collisions+foot_lock, full (the default chain), full[eso12] (the default chain "
                     "with 12 ESO steps)"),
    ] = None,
    ablation: Annotated[
        bool, typer.Option(help="Add paper 1 table 3's rows (evaluation.ABLATION) to the methods")
    ] = False,
    max_frames: Annotated[int | None, typer.Option(help="First frames of each clip (after resampling)")] = 300,
    fps: Annotated[float, typer.Option(help="Resample every clip to this rate first")] = 30.0,
    source_body: Annotated[
        str | None, typer.Option(help="Body performing the motions (file or builtin:<preset>); default: their own")
    ] = None,
    source_glb_body: Annotated[
        str | None, typer.Option(help="Write each clip as a GLB on this body first and use that (as a studio sends it)")
    ] = None,
    jobs: Annotated[int, typer.Option(help="Clips evaluated in parallel processes (one torch thread each)")] = 1,
    only: Annotated[
        list[str] | None,
        typer.Option(help="With --split: run only the cases whose clip or body name contains this; repeatable"),
    ] = None,
) -> None:
    """Run methods over motions x bodies; print and write the acceptance figures by body and clip group."""
    from retarget_core.evaluation import ABLATION, run_evaluation

    if ablation:
        method = list(dict.fromkeys([*ABLATION, *(method or [])]))

    groups: dict[str, str] | None = None
    cases: list[tuple[Path, str | Path]] | None = None
    files: list[Path] = []
    bodies: list[str | Path] = []
    if split_name is not None:
        cases, groups = _split_cases(split_name, shared_data, only or [])
        source_glb_body = source_glb_body or _heldout_source_body()
    elif heldout is not None:
        from retarget_core import heldout as split

        files = split.clip_paths(heldout)
        paths = split.body_paths()
        bodies = list(paths)
        groups = {p.stem: p.stem.split("-")[0].removeprefix("heldout_") for p in paths}  # heavy, bulky, ...
        source_glb_body = source_glb_body or split.SOURCE_BODY
    else:
        files = _expand(motions or [], (".bvh", ".glb", ".gltf", ".fbx"))
        bodies = [b for b in body or [] if b.startswith("builtin:")]
        bodies += _expand([Path(b) for b in body or [] if not b.startswith("builtin:")], (".glb", ".gltf", ".fbx"))
    if cases is None and (not files or not bodies):
        _fail("no motion files or no bodies given (or use --heldout MOTIONS_DIR or --split hard)")
    try:
        table = run_evaluation(
            files, bodies, method or None, out, max_frames, fps=fps, log=console.print, source_character=source_body,
            source_glb_body=source_glb_body, body_groups=groups, jobs=jobs, cases=cases,
        )  # fmt: skip
    except (RetargetError, ValueError, FileNotFoundError) as exc:
        _fail(str(exc))
    print(table.to_markdown())
    console.print(f"wrote {out / 'eval.json'} and {out / 'eval.md'}")


def _split_cases(
    split: str, shared_data: Path, only: list[str]
) -> tuple[list[tuple[Path, str | Path]], dict[str, str]]:
    """The named split's fixed cases (clip file, body file; those naming one of ``only`` when given) and its body
    groups; exits on a missing file or when no case matches."""
    if split != "hard":
        _fail(f"unknown split {split!r}; available: hard")
    from retarget_core import heldout_hard

    try:
        cases: list[tuple[Path, str | Path]] = list(heldout_hard.split_cases(shared_data, only=only))
        return cases, heldout_hard.body_groups(shared_data)
    except FileNotFoundError as exc:
        _fail(f"{exc} (give the shared data folder with --shared-data)")
        raise
    except ValueError as exc:
        _fail(str(exc))
        raise


def _heldout_source_body() -> str:
    from retarget_core.heldout import SOURCE_BODY

    return SOURCE_BODY


train_app = typer.Typer(add_completion=False, no_args_is_help=True, help="Train the learned stages.")
app.add_typer(train_app, name="train")

# Options both training commands take (their defaults differ per command).
ClipsOption = Annotated[Path, typer.Option(help="Folder of CMU BVH clips (held-out clips are skipped)")]
WeightsOption = Annotated[Path, typer.Option("-o", "--out", help="Weights file")]
LogOption = Annotated[Path, typer.Option(help="Losses, one JSON line per step")]
CacheOption = Annotated[Path, typer.Option(help="Where the built training set is cached")]
ThreadsOption = Annotated[int, typer.Option(help="Torch threads (1 makes runs reproducible)")]
SHARED_CLIPS = Path("../shared/data/motions/cmu")


def _start_training(clips: Path, threads: int, log: Path) -> None:
    """Logging, torch threads and the clip folder's check before a training run."""
    import logging

    import torch

    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    logging.getLogger("retarget_core.mapping").setLevel(logging.WARNING)
    torch.set_num_threads(threads)
    if not clips.is_dir():
        _fail(f"no clip folder {clips}")
    log.parent.mkdir(parents=True, exist_ok=True)


def _trained(out: Path, summary: dict[str, Any], digits: int) -> None:
    console.print(f"wrote {out}: {summary['steps']} steps in {summary['train_seconds']:.0f} s "
                  f"(data {summary['data_seconds']:.0f} s), final loss {summary['final'].get('loss', float('nan')):.{digits}f}")  # fmt: skip


@train_app.command(name="recurrent")
def train_recurrent(
    clips: ClipsOption = SHARED_CLIPS,
    out: WeightsOption = Path("retarget_core/data/models/recurrent.pt"),
    log: LogOption = Path("var/train-recurrent.jsonl"),
    cache_dir: CacheOption = Path("~/.cache/retarget/recurrent"),
    steps: Annotated[int, typer.Option(help="Optimiser steps")] = 1500,
    minutes: Annotated[float, typer.Option(help="Stop after this many minutes of training")] = 30.0,
    seed: Annotated[int, typer.Option(help="Seed of bodies, windows and weights")] = 0,
    batch: Annotated[int, typer.Option(help="Windows per step")] = 8,
    bodies: Annotated[int, typer.Option(help="Generated training bodies")] = 6,
    ik_windows: Annotated[int, typer.Option(help="IK contact windows added to the clips")] = 80,
    threads: ThreadsOption = 1,
    contact_weight: Annotated[float, typer.Option(help="Weight of the vertex-contact term")] = 1000.0,
    ik_share: Annotated[float, typer.Option(help="Share of windows drawn from the IK contact windows")] = 0.3,
    energy: Annotated[str, typer.Option(help="Energy trained on (paper 1 table 3's ablation): skeleton, foot "
                                            "(+ foot), interpenetration (+ interpenetration) or full")] = "full",
    geometry: Annotated[str, typer.Option(help="Body shape code: girths (per-segment girths, the shipped weights) "
                                              "or pointnet (a PointNet over rest vertices and skin weights)")] = "girths",
) -> None:
    """Train the geometry-conditioned recurrent retargeter on the energy and write its weights."""
    from retarget_core.model.network import GEOMETRIES, NetworkConfig
    from retarget_core.model.train_recurrent import ENERGY_TERMS, TrainConfig, train, with_energy

    _start_training(clips, threads, log)
    if energy not in ENERGY_TERMS:
        _fail(f"unknown energy {energy!r}; one of {', '.join(ENERGY_TERMS)}")
    if geometry not in GEOMETRIES:
        _fail(f"unknown geometry {geometry!r}; one of {', '.join(GEOMETRIES)}")
    cfg = TrainConfig(seed=seed, steps=steps, max_minutes=minutes, batch=batch, bodies=bodies, ik_windows=ik_windows,
                      w_contact=contact_weight, ik_share=ik_share, network=NetworkConfig(geometry=geometry))  # fmt: skip
    _trained(out, train(clips, out, with_energy(cfg, energy), cache_dir.expanduser(), log), 4)


@train_app.command(name="collisions")
def train_collisions_cmd(
    clips: ClipsOption = SHARED_CLIPS,
    out: WeightsOption = Path("retarget_core/data/models/collisions.pt"),
    log: LogOption = Path("var/train-collisions.jsonl"),
    cache_dir: CacheOption = Path("~/.cache/retarget/collisions"),
    steps: Annotated[int, typer.Option(help="Optimiser steps")] = 8000,
    minutes: Annotated[float, typer.Option(help="Stop after this many minutes of training (data building apart)")] = 18.0,
    seed: Annotated[int, typer.Option(help="Seed of bodies, frames, augmentation and weights")] = 0,
    batch: Annotated[int, typer.Option(help="Frames per step")] = 32,
    bodies: Annotated[int, typer.Option(help="Generated training bodies")] = 12,
    stride: Annotated[int, typer.Option(help="Every n-th frame of the 30 fps clips")] = 2,
    threads: ThreadsOption = 1,
    penetration_weight: Annotated[float, typer.Option(help="Weight of the penetration loss (paper 2: 0.5)")] = 2.0,
) -> None:
    """Train paper 2's per-limb learned collision resolver on copy poses of generated bodies."""
    from retarget_core.model.train_collisions import CollisionTrainConfig, train_collisions

    _start_training(clips, threads, log)
    cfg = CollisionTrainConfig(seed=seed, steps=steps, max_minutes=minutes, batch=batch, bodies=bodies, stride=stride,
                               w_penetration=penetration_weight)  # fmt: skip
    _trained(out, train_collisions(clips, out, cfg, cache_dir.expanduser(), log), 5)


def _progress() -> Progress:
    return Progress(
        TextColumn("{task.description:>10}"), BarColumn(), TimeElapsedColumn(), console=console, transient=True
    )


def _fail(message: str) -> None:
    console.print(f"[red]error:[/] {message}")
    raise typer.Exit(code=2)


def main() -> None:
    """Entry point of the ``retarget`` command."""
    try:
        app()
    except KeyboardInterrupt:
        sys.exit(130)


if __name__ == "__main__":
    main()
