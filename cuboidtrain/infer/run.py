"""`cuboidtrain infer` as one library call: `infer(request, console)` checks, fits and writes what the command does.

The command line only parses its options into an `InferRequest` and turns the `InferResult`
into its messages and exit status; the Python API and the tests call `infer` the same way.
Every output and combination of options is checked before any input is read (one-line
UsageErrors), the workers' fork server starts before this process imports torch (`pool.warm_up`:
nothing here imports torch before it), and matplotlib is imported only for `explain`.
"""
from __future__ import annotations

import logging
import sys
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING

from cuboidtrain.fit.options import FitOptions
from cuboidtrain.infer.inputs import gather_inputs
from cuboidtrain.infer.mesh import MeshWriter, check_mesh_options
from cuboidtrain.infer.stopping import Stop, held_during_import
from shared.errors import UsageError, check_outputs, check_writable
from shared.files import json_text

log = logging.getLogger(__name__)

if TYPE_CHECKING:  # torch: imported by `infer` only after the warm-up
    from cuboidtrain.fit.fitter import Outcome
    from cuboidtrain.infer.reporting import Tally


@dataclass(frozen=True)
class InferRequest:
    """What `cuboidtrain infer` is asked, option by option (docs/inference.md; docs/contract.md)."""

    paths: tuple[str, ...] = ()  # mask files, folders or URLs
    from_list: str | None = None  # a text file of paths, one a line; - for stdin
    glob: str | None = None  # in folders, the files matching this (default: the image suffixes)
    checkpoints: tuple[Path, ...] = ()  # default: the shipped models of `options.shapes`
    options: FitOptions = field(default_factory=FitOptions)  # the command passes cuboid=True (its default)
    json_out: str | None = None  # the JSON list: a file (replaced atomically), - for stdout, None: not written
    jsonl: Path | None = None  # the JSONL record store, resumed when it exists
    workers: int = 1  # processes fitting at once
    cluster: str | None = None  # a Dask scheduler's address, or "local"
    explain: Path | None = None  # a folder for the explanation panels
    overlay: tuple[Path, ...] = ()  # with `explain`: the photo behind each mask, in input order
    photos: tuple[Path, ...] = ()  # the photo each mask was cut from, in input order: its EXIF focal length
    mesh: Path | None = None  # a folder for each fitted box's OBJ mesh


@dataclass(frozen=True)
class InferResult:
    """What a run did: its outcomes and its counts."""

    # In input order, kept when the JSON list is asked for or there is no record store (a city's
    # run keeps none); an input the store already held is there by its records, as read back.
    outcomes: list[Outcome | dict]
    tally: Tally  # inputs, failures, records by shape
    pictures: int | None = None  # explanation panels written, with `explain`
    meshes: int | None = None  # OBJ files in the `mesh` folder, with `mesh`
    records: int | None = None  # records in the JSON list, when one was written
    stopped: int | None = None  # the exit status of a run a signal stopped (130 Ctrl-C, 143 SIGTERM), else None


def infer(request: InferRequest, console) -> InferResult:
    """Fit the request's inputs as `cuboidtrain infer` does, write their records (`json_out`,
    `jsonl`) and pictures, and say what was done; `console` shows the progress and summary."""
    options = request.options.validate()
    check_request(request, options)
    inputs = gather_inputs(list(request.paths), request.from_list, request.glob)  # nothing to fit: before the models
    options.check_cameras_match(inputs)
    options = with_photos(options, list(request.photos), inputs)
    if request.cluster is None:
        from cuboidtrain.infer.pool import warm_up

        warm_up(request.workers)  # the workers' torch import, beside this process's below (no torch imported yet)
    with held_during_import():  # torch's: a Ctrl-C inside its native initialisation would abort the interpreter
        from cuboidtrain.fit.fitter import Fitter, Writers
    from cuboidtrain.infer.batch import Batch, run_batch
    from cuboidtrain.models.zoo import default_checkpoints

    checkpoints = default_checkpoints(list(request.checkpoints), options.shapes)
    options = pinned_classifier(options)
    fitter = Fitter.from_files(checkpoints, options)  # also checks the models before any worker starts
    batch = Batch(tuple(inputs), tuple(checkpoints), options, request.workers, request.jsonl,
                  keep=request.json_out is not None or request.jsonl is None, cluster=request.cluster)
    explainer = make_explainer(request.explain, list(request.overlay), len(inputs), batch.indexed())
    mesher = MeshWriter(request.mesh, batch.indexed()) if request.mesh is not None else None
    with Stop().installed() as stop:  # Ctrl-C, SIGTERM: what was fitted is written, as at the end
        outcomes, tally = run_batch(batch, fitter, console, Writers.of(explainer, mesher), stop)
        records = write_list(request.json_out, outcomes, options)
    meshes = None
    if mesher is not None:  # a pool's workers write their own: count the folder's then
        meshes = len(mesher.written) if request.workers == 1 else sum(1 for _ in mesher.folder.glob("*.obj"))
    return InferResult(outcomes, tally, None if explainer is None else len(explainer.written), meshes, records,
                       stop.exit_code if tally.stopped else None)


def with_photos(options: FitOptions, photos: list[Path], inputs: list[str]) -> FitOptions:
    """The options with each input's photo's EXIF camera (`--photo`, in input order); the photos
    that carry no EXIF focal length change nothing, and one line says so."""
    if not photos:
        return options
    if len(photos) != len(inputs):
        raise UsageError(f"--photo given {len(photos)} times for {len(inputs)} inputs: expected one photo per "
                         f"input, in the same order")
    from cuboidtrain.fit.exif import read_photo_camera

    cameras = [read_photo_camera(photo) for photo in photos]
    bare = [photo for photo, camera in zip(photos, cameras) if camera is None]
    if len(bare) == 1:
        log.warning("--photo %s: no EXIF focal length; its input's camera is fitted as without a photo", bare[0])
    elif bare:
        log.warning("--photo: %d of %d photos carry no EXIF focal length (the first: %s); their inputs' cameras "
                    "are fitted as without a photo", len(bare), len(photos), bare[0])
    return replace(options, photos=tuple((name, camera) for name, camera in zip(inputs, cameras) if camera))


def json_destination(json_out: str | None, jsonl: Path | None, terminal: bool) -> str | None:
    """Where `infer`'s JSON list goes: where --json says; without --json or --jsonl, to stdout when
    stdout is no terminal (a pipe or a file: scripts read it there, as they always did), and nowhere
    at a terminal, where each input's answer line and the total say what was fitted."""
    if json_out is not None or jsonl is not None:
        return json_out
    return None if terminal else "-"


def check_request(request: InferRequest, options: FitOptions) -> None:
    """The outputs and the combinations of options, before any input is read: one-line UsageErrors."""
    check_outputs(("--json", request.json_out), ("--jsonl", request.jsonl))
    if request.explain is not None:
        check_writable("--explain", request.explain, folder=True)
        if request.workers > 1 or request.cluster is not None:
            what = f"--workers {request.workers}" if request.cluster is None else f"--cluster {request.cluster}"
            raise UsageError(f"--explain with {what}: expected --workers 1 and no --cluster "
                             f"(pictures are drawn in one process)")
    if request.photos and (not options.cuboid or options.optimizer != "lm"):
        raise UsageError(f"--photo with {'--networks-only' if not options.cuboid else '--optimizer ' + options.optimizer}: "
                         f"expected the cuboid fit by --optimizer lm (only it holds a camera)")
    check_mesh_options(request.mesh, options.cuboid, request.cluster)
    if request.mesh is not None:
        check_writable("--mesh", request.mesh, folder=True)
    if request.cluster is not None:
        from cuboidtrain.infer.cluster import require_distributed

        require_distributed(request.cluster)  # before the models load: a missing extra is a one-line error


def make_explainer(folder: Path | None, photos: list[Path], inputs: int, names: list[str] | None = None):
    """The explanation writer for --explain/--overlay, or None; bad combinations are UsageErrors.
    `names`, the run's inputs in index order, fix the pictures' names."""
    if photos and folder is None:
        raise UsageError("--overlay needs --explain DIR: the folder its pictures go to")
    if photos and len(photos) != inputs:
        raise UsageError(f"--overlay given {len(photos)} times for {inputs} inputs: expected one photo per input, "
                         f"in the same order")
    if folder is None:
        return None  # a folder given was checked with the other outputs (`check_request`)
    from cuboidtrain.infer.explain import Explainer  # matplotlib: only when pictures are wanted

    return Explainer(folder, photos, names)


def write_list(json_out: str | None, outcomes: list[Outcome | dict], options: FitOptions) -> int | None:
    """The JSON list of the records, in input order: to a file (atomically), to stdout for -, or nowhere;
    how many records it holds."""
    if json_out is None:
        return None
    from cuboidtrain.infer.records import to_records, write_records

    records = to_records(outcomes, options)
    if json_out == "-":
        sys.stdout.write(json_text(records, indent=2) + "\n")
        sys.stdout.flush()
    else:
        write_records(Path(json_out), records)
    return len(records)


def pinned_classifier(options: FitOptions) -> FitOptions:
    """The options with the shape classifier's file named where it would be used (`FitOptions.classifier_file`):
    every worker, local or a cluster's, then loads this machine's file, or fails naming it."""
    from cuboidtrain.models.zoo import classifier_path

    if not (options.shape_classifier and options.cuboid) or options.classifier_file is not None:
        return options
    path = classifier_path()
    return replace(options, classifier_file=str(path.resolve())) if path.is_file() else options
