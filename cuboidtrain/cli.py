"""`cuboidtrain`: parse options, build a TrainConfig, call the library. Nothing else lives here."""
from __future__ import annotations

import copy
import sys
from pathlib import Path
from typing import Optional

import typer

from cuboidtrain.train.config import LR_SCHEDULES, PHASES, TrainConfig
from cuboidtrain.infer.inputs import DEFAULT_GLOB_HELP, read_cameras
from cuboidtrain.fit.options import FIT_SHAPES, OPTIMIZERS, FitOptions
from cuboidtrain.models.settings import EXTRACTORS, MAX_REFINE_STEPS
from shared.console import CLI, choices, console, fail, say, setup_logging
from shared.errors import UsageError, check_outputs, check_writable
from shared.files import json_text
from shared.shapes import SHAPES

app = CLI(add_completion=False, no_args_is_help=True,
                  help="Train the Refiner, Estimator and Tabulator from a spool; evaluate; watch a run; infer.")


PhaseChoice = choices("PhaseChoice", PHASES)
ShapeChoice = choices("ShapeChoice", SHAPES)
FitShape = choices("FitShape", FIT_SHAPES)
ExtractorChoice = choices("ExtractorChoice", EXTRACTORS)
OptimizerChoice = choices("OptimizerChoice", OPTIMIZERS)
ScheduleChoice = choices("ScheduleChoice", LR_SCHEDULES)
FIT = FitOptions()  # the fitting commands' defaults are the library's: stated once, in FitOptions
# `infer` answers with the fitted cuboid unless told otherwise: on the same 300 masks a set it is
# better on 4 of 6 sets' mean corner error and on every median, shape selection, yaw, width/height
# and 3D IoU, within the 50 ms a mask (BENCHMARKS.md, "infer --cuboid, second version"). The
# library's default (FitOptions.cuboid) stays off: eval, training's validation and the paper's
# report measure the networks' chain.
INFER_CUBOID = True
TRAIN = TrainConfig()  # `run`'s too, in TrainConfig (but --out's, which follows --phase)


@app.command()
def run(
    phase: PhaseChoice = typer.Option(PhaseChoice[TRAIN.phase], envvar="CUBOIDTRAIN_PHASE", help="1: each network alone; 2: chained with all losses; e2e / finetune: the paper's ablations (final loss only)."),
    spool: Path = typer.Option(Path(TRAIN.spool), envvar="CUBOIDTRAIN_SPOOL", help="Spool folder, enumerated afresh every epoch."),
    shape: ShapeChoice = typer.Option(ShapeChoice[TRAIN.shape], envvar="CUBOIDTRAIN_SHAPE", help="Shape class of the model."),
    size: int = typer.Option(TRAIN.size, envvar="CUBOIDTRAIN_SIZE", help="Model input size in px (a multiple of 32)."),
    arch: str = typer.Option(TRAIN.arch, envvar="CUBOIDTRAIN_ARCH", help="Architecture of R, S and T: compact (the shipped models'), slim (narrower, for 128 px inputs), paper (three ResNet-18s, Table 3), tiny (tests)."),
    reframe: bool = typer.Option(TRAIN.reframe, "--reframe/--no-reframe", envvar="CUBOIDTRAIN_REFRAME", help="Frame each sample as infer frames a mask (its visible pieces), from a spool of any size; --no-reframe: train on the spool's own framing, whose size must be --size."),
    grey_input: bool = typer.Option(TRAIN.grey_input, "--grey-input/--binary-input", envvar="CUBOIDTRAIN_GREY_INPUT", help="Show R each model pixel's covered share of the mask (grey: where an edge lies inside a pixel) instead of a binary mask; needs --reframe. The model file keeps which, and infer frames masks alike."),
    steps: Optional[int] = typer.Option(TRAIN.steps, envvar="CUBOIDTRAIN_STEPS", help="Train until this step (neither --steps nor --epochs: until stopped)."),
    stop_at: Optional[int] = typer.Option(TRAIN.stop_at, envvar="CUBOIDTRAIN_STOP_AT", help="Stop, with a checkpoint, after this step, the schedule still running to --steps (one share of a longer run: a campaign's lease)."),
    epochs: Optional[int] = typer.Option(TRAIN.epochs, envvar="CUBOIDTRAIN_EPOCHS", help="Or this many epochs over the spool."),
    batch_size: int = typer.Option(TRAIN.batch_size, envvar="CUBOIDTRAIN_BATCH_SIZE", help="Samples per step."),
    lr: float = typer.Option(TRAIN.lr, envvar="CUBOIDTRAIN_LR", help="Adam learning rate."),
    lr_schedule: ScheduleChoice = typer.Option(ScheduleChoice[TRAIN.lr_schedule], envvar="CUBOIDTRAIN_LR_SCHEDULE", help="constant, or cosine (decays to lr/100 at --steps, or without it at --max-minutes)."),
    max_minutes: Optional[float] = typer.Option(TRAIN.max_minutes, envvar="CUBOIDTRAIN_MAX_MINUTES", help="Stop, with a checkpoint, after this many minutes."),
    max_wait: Optional[float] = typer.Option(TRAIN.max_wait, metavar="SECONDS", envvar="CUBOIDTRAIN_MAX_WAIT", help="Give up (exit 1) after waiting this long for a usable sample: an empty spool, or none of its samples fit (default: wait on)."),
    weight_decay: float = typer.Option(TRAIN.weight_decay, envvar="CUBOIDTRAIN_WEIGHT_DECAY", help="Adam's L2 penalty."),
    sigma: Optional[float] = typer.Option(TRAIN.sigma, envvar="CUBOIDTRAIN_SIGMA", help="Heat-map Gaussian std in px (default size/128, at least 1)."),
    alpha_r: float = typer.Option(TRAIN.alpha_r, envvar="CUBOIDTRAIN_ALPHA_R", help="Phase 2 weight of D_R."),
    alpha_s: float = typer.Option(TRAIN.alpha_s, envvar="CUBOIDTRAIN_ALPHA_S", help="Phase 2 weight of D_S."),
    alpha_t: float = typer.Option(TRAIN.alpha_t, envvar="CUBOIDTRAIN_ALPHA_T", help="Phase 2 weight of D_T."),
    ratio_weight: float = typer.Option(TRAIN.ratio_weight, envvar="CUBOIDTRAIN_RATIO_WEIGHT", help="Weight of the ratio term in D_T."),
    init: Optional[Path] = typer.Option(TRAIN.init, envvar="CUBOIDTRAIN_INIT", help="Start from this checkpoint's weights (phase 2, finetune)."),
    out: Optional[Path] = typer.Option(None, envvar="CUBOIDTRAIN_OUT", help="Run folder (default runs/p1, runs/p2, runs/e2e, runs/finetune)."),
    resume: bool = typer.Option(TRAIN.resume, envvar="CUBOIDTRAIN_RESUME", help="Continue OUT/last.pt exactly: weights, optimizer, step, data order, RNG."),
    overwrite: bool = typer.Option(TRAIN.overwrite, envvar="CUBOIDTRAIN_OVERWRITE", help="Start over in an --out that holds a run, replacing its last.pt and metrics.jsonl (without it, or --resume, such a run is refused)."),
    checkpoint_every: int = typer.Option(TRAIN.checkpoint_every, envvar="CUBOIDTRAIN_CHECKPOINT_EVERY", help="Steps between checkpoints (OUT/last.pt, replaced atomically)."),
    log_every: int = typer.Option(TRAIN.log_every, envvar="CUBOIDTRAIN_LOG_EVERY", help="Steps between records in OUT/metrics.jsonl."),
    ledger: bool = typer.Option(TRAIN.ledger, "--ledger", envvar="CUBOIDTRAIN_LEDGER", help="Write OUT/ledger.jsonl: every step's samples, by name and payload checksum (which bytes each step trained on)."),
    loader_workers: Optional[int] = typer.Option(TRAIN.loader_workers, envvar="CUBOIDTRAIN_LOADER_WORKERS", help="DataLoader worker processes reading the spool (default: 2; on CUDA a quarter of the cores, 2 to 6)."),
    seed: int = typer.Option(TRAIN.seed, envvar="CUBOIDTRAIN_SEED", help="Seed of the initial weights and the epoch order."),
    device: str = typer.Option(TRAIN.device, envvar="CUBOIDTRAIN_DEVICE", help="auto (CUDA when present), cpu, cuda or cuda:N."),
    threads: Optional[int] = typer.Option(TRAIN.threads, envvar="CUBOIDTRAIN_THREADS", help="CPU threads for torch (default: all cores)."),
    amp: bool = typer.Option(TRAIN.amp, "--amp/--no-amp", envvar="CUBOIDTRAIN_AMP", help="bfloat16 autocast on CUDA (ignored on the CPU)."),
    dashboard: bool = typer.Option(TRAIN.dashboard, "--dashboard/--no-dashboard", envvar="CUBOIDTRAIN_DASHBOARD", help="Live dashboard (else log lines)."),
    val_spool: Optional[Path] = typer.Option(TRAIN.val_spool, envvar="CUBOIDTRAIN_VAL_SPOOL", help="Validation spool, evaluated every --val-every steps."),
    val_every: int = typer.Option(TRAIN.val_every, envvar="CUBOIDTRAIN_VAL_EVERY", help="Steps between validations."),
    val_samples: int = typer.Option(TRAIN.val_samples, envvar="CUBOIDTRAIN_VAL_SAMPLES", help="Validation samples per evaluation."),
) -> None:
    """Train from the spool until --steps/--epochs are done, or Ctrl-C/SIGTERM (which checkpoint first)."""
    setup_logging()
    config = TrainConfig(
        phase=phase.value, spool=str(spool), shape=shape.value, size=size, arch=arch, reframe=reframe, grey_input=grey_input, steps=steps,
        stop_at=stop_at, epochs=epochs, batch_size=batch_size, lr=lr, lr_schedule=lr_schedule.value, max_minutes=max_minutes, max_wait=max_wait, weight_decay=weight_decay, sigma=sigma, alpha_r=alpha_r, alpha_s=alpha_s,
        alpha_t=alpha_t, ratio_weight=ratio_weight, init=str(init) if init else None,
        out=str(out or Path("runs") / (f"p{phase.value}" if phase.value in ("1", "2") else phase.value)),
        resume=resume, overwrite=overwrite, checkpoint_every=checkpoint_every, log_every=log_every, ledger=ledger, loader_workers=loader_workers,
        seed=seed, device=device, threads=threads, amp=amp, dashboard=dashboard, val_spool=str(val_spool) if val_spool else None,
        val_every=val_every, val_samples=val_samples,
    ).validate()
    _train(config)


def _train(config: TrainConfig) -> None:
    """`run` once its options are a TrainConfig: the paths checked before the dashboard starts, the
    training, and one line on how it ended (rank 0's under torchrun)."""
    from cuboidtrain.train.monitor.dashboard import Dashboard
    from cuboidtrain.train.loop import run as run_training
    from cuboidtrain.train.preflight import check_paths
    from cuboidtrain.train.monitor.status import TrainingFailed

    check_paths(config)  # every path option, before the dashboard starts (run() checks them again)
    try:
        with Dashboard(live=config.dashboard and console.is_terminal) as board:  # the panel is on stderr, with the log
            status = run_training(config, dashboard=board)
    except TrainingFailed as exc:  # not a bad value (a full disk, a spool that never fills): exit 1
        fail(str(exc), code=1)
    if status.rank == 0:  # under torchrun rank 0 speaks for the run
        ckpt = status.last_checkpoint
        say(f"{status.state} at step {status.step}; "
            + (f"checkpoint {ckpt.path}" if ckpt else "no checkpoint written (no step was trained)"))


EXTRACTOR_HELP = ("How keypoints are read off the heat maps: tabulator (the paper's T), argmax, centre-of-mass, "
                  "dark (sub-pixel Taylor step), pdm (argmax made valid by a PCA shape model). Ratios are always T's.")
PDM_HELP = "PDM active components: a count (e.g. 6) or the fraction of shape variance to keep (e.g. 0.999)."
DEVICE_HELP = "auto (CUDA when present), cpu, cuda or cuda:N."
# Options that more than one command takes, declared once (the same name, default and help in each).
DEVICE = typer.Option(FIT.device, metavar="DEVICE", help=DEVICE_HELP)
EXTRACTOR = typer.Option(ExtractorChoice[FIT.extractor], metavar="NAME", help=EXTRACTOR_HELP)
PDM_COMPONENTS = typer.Option(str(FIT.pdm_components), metavar="N|FRACTION", help=PDM_HELP)
SHIPPED_SHAPE = typer.Option(ShapeChoice["box"], help="Without --checkpoint: which shipped model.")
THREADS = typer.Option(None, help="CPU threads for torch (default: all cores).")


def refine_steps_option(help: str):
    """--refine-steps, whose help says what the passes are in its command."""
    return typer.Option(str(FIT.refine_steps), metavar="K|auto", help=help)


@app.command("eval")
def evaluate(
    checkpoint: Optional[Path] = typer.Option(None, help="Checkpoint or model file to evaluate (default: the shipped model of --shape)."),
    spool: Path = typer.Option(..., help="Validation spool (e.g. `cuboidgen run --scene paper-clean --limit 0 --max-samples 1000`); any size: samples are framed as infer frames a mask."),
    shape: ShapeChoice = SHIPPED_SHAPE,
    batch_size: int = typer.Option(32, help="Samples per forward pass."),
    max_samples: Optional[int] = typer.Option(None, help="Evaluate only the first N samples."),
    device: str = DEVICE,
    extractor: ExtractorChoice = EXTRACTOR,
    pdm_components: str = PDM_COMPONENTS,
    refine_steps: str = refine_steps_option("Refiner passes before S (as in infer)."),
    cuboid: bool = typer.Option(False, "--cuboid", help="Also fit each sample's cuboid (as infer --cuboid) and score both paths side by side: networks only and cuboid."),
    as_json: bool = typer.Option(False, "--json", help="Print JSON instead of a table."),
) -> None:
    """Keypoint error (px), PCK, ratio error and Refiner IoU, beside a randomly initialised model's; then
    where the error is, per path, in the samples' own px: hull and interior corners, NME, ratio, yaw and 3D IoU."""
    from cuboidtrain.train.evaluate import evaluate_checkpoint, format_report
    from cuboidtrain.models.zoo import default_checkpoints

    setup_logging()
    options = FitOptions(refine_steps=refine_steps, extractor=extractor.value, pdm_components=pdm_components,
                         device=device, cuboid=cuboid).validate()
    checkpoint = default_checkpoints([checkpoint] if checkpoint else None, (shape.value,))[0]
    result = evaluate_checkpoint(checkpoint, spool, options, batch_size=batch_size, max_samples=max_samples)
    typer.echo(json_text(result.to_dict(), indent=2) if as_json else format_report(result))


@app.command()
def watch(
    out: Path = typer.Argument(..., help="A run folder (holding status.json)."),
    interval: float = typer.Option(1.0, help="Seconds between refreshes."),
    once: bool = typer.Option(False, help="Print the dashboard once and exit."),
) -> None:
    """Show a running (or finished) training run's dashboard from another terminal."""
    from cuboidtrain.train.monitor.dashboard import watch as watch_run

    try:
        code = watch_run(out, interval=interval, once=once)
    except KeyboardInterrupt:
        code = 0
    raise typer.Exit(code)


# infer's options in groups (`--help` shows a panel each), in the order a user meets them
INPUTS, CAMERA, OUTPUT = "Inputs: what to fit", "Camera: where it is known", "Output: records, pictures, meshes"
MODELS, SPEED = "Models and the fit", "Speed: processes, a cluster, the device"


def in_panel(option, panel: str):
    """A shared option (`DEVICE`, `EXTRACTOR`, ...) in one command's help panel, the others' left as they are."""
    option = copy.copy(option)
    option.rich_help_panel = panel
    return option


@app.command()
def infer(
    paths: Optional[list[str]] = typer.Argument(None, metavar="PATH", help="Mask images (PNG/JPG, any size): two-valued, the object its light side (--invert: dark; --threshold T for a greyscale image), or by --label-id; a folder: its images, recursively. Or a URL fsspec reads (s3://bucket/masks/, gs://..., file://...; a glob in it is expanded)."),
    from_list: Optional[str] = typer.Option(None, "--from-list", metavar="FILE", help="A text file of mask paths (or folders, or URLs), one a line; - for stdin.", rich_help_panel=INPUTS),
    glob: Optional[str] = typer.Option(None, metavar="PATTERN", help=f"In folders, the files matching this (e.g. '*_mask.png'); default {DEFAULT_GLOB_HELP}.", rich_help_panel=INPUTS),
    all_components: bool = typer.Option(False, "--all-components", help="One record per 8-connected component (>= 16 px), largest first; else one building: its pieces (>= 1% of the largest one's area) fitted together.", rich_help_panel=INPUTS),
    label_id: Optional[int] = typer.Option(None, metavar="K", help="Read a grey label map: pixels equal to this id are the object.", rich_help_panel=INPUTS),
    threshold: Optional[float] = typer.Option(None, metavar="T", help="Not a two-valued mask (a greyscale image, a photo): the object is the pixels whose level is above T, in the image's own units (0-255 for 8 bits; colour: its grey). Without it an image must be two-valued, or it is refused.", rich_help_panel=INPUTS),
    invert: bool = typer.Option(False, "--invert", help="The object is the dark side: a dark building on a light background (an object that covers the whole border is refused, naming this option).", rich_help_panel=INPUTS),
    checkpoint: list[Path] = typer.Option([], metavar="CKPT", help="A trained model; give it twice (one box, one twobox) to choose per input. Default: the shipped box and twobox models.", rich_help_panel=MODELS),
    shape: FitShape = typer.Option(FitShape[FIT.shape], metavar="SHAPE", help="auto, box or twobox; auto: every given model, the best-explained fit wins.", rich_help_panel=MODELS),
    refine_steps: str = in_panel(refine_steps_option(f"Refiner passes, each on the last one's binary output; auto: until nothing changes (at most {MAX_REFINE_STEPS})."), MODELS),
    margin: float = typer.Option(FIT.margin, metavar="FRACTION", help="Empty border around the framed object, as a fraction of the model size per side.", rich_help_panel=MODELS),
    extractor: ExtractorChoice = in_panel(EXTRACTOR, MODELS),
    pdm_components: str = in_panel(PDM_COMPONENTS, MODELS),
    cuboid: bool = typer.Option(INFER_CUBOID, "--cuboid/--networks-only", help="--cuboid (the default): fit a perspective box to each mask at its own resolution, from the networks' corners: keypoints are its projection, ratios its own, and the record gains a `cuboid` object (rotation, focal length, IoU, per-corner scores). --networks-only: the networks' corners alone (free points, the Tabulator's ratios), about 2.5x faster (BENCHMARKS.md).", rich_help_panel=MODELS),
    no_classifier: bool = typer.Option(not FIT.shape_classifier, "--no-classifier", help="Box or twobox by the fitted silhouettes alone, not the shape classifier's sure call on a rough mask (shape_call).", rich_help_panel=MODELS),
    optimizer: OptimizerChoice = typer.Option(OptimizerChoice[FIT.optimizer], metavar="NAME", help="The cuboid fit's solver: lm (Levenberg-Marquardt on the outline, ~45 ms a mask) or soft (a soft-rasterised silhouette by L-BFGS: more accurate on every measured set, ~35x slower; BENCHMARKS.md, \"Choosing the mask-fit optimiser\").", rich_help_panel=MODELS),
    focal_px: Optional[float] = typer.Option(None, metavar="F", help="The camera's focal length in the inputs' pixels, where known: held by the cuboid fit (the record says so). With the camera given, depth/height is several times more accurate (BENCHMARKS.md).", rich_help_panel=CAMERA),
    principal_px: Optional[tuple[float, float]] = typer.Option(None, metavar="X Y", help="The camera's principal point in the inputs' pixels, where known (a full frame with --label-id or --all-components: its centre unless given).", rich_help_panel=CAMERA),
    camera: Optional[Path] = typer.Option(None, metavar="FILE", help='Each input\'s camera: a JSON object mapping its path as given (or its file name) to {"focal_px": F, "principal_px": [X, Y]}; over --focal-px and --principal-px.', rich_help_panel=CAMERA),
    photo: list[Path] = typer.Option([], metavar="PHOTO", help="The photo each mask was cut from, in the same order (repeat it): its EXIF focal length sets the camera, loosely (the record says exif); --focal-px, --principal-px, --camera override it.", rich_help_panel=CAMERA),
    json_out: Optional[str] = typer.Option(None, "--json", metavar="OUT", help="Where the JSON list goes: a file (written atomically) or - for stdout (the default without --jsonl when stdout is a pipe or a file; at a terminal, without --json, each input's answer is a line on stderr and no JSON is written).", rich_help_panel=OUTPUT),
    jsonl: Optional[Path] = typer.Option(None, metavar="OUT", help="Stream one record a line to OUT as fits complete; rerun with the same OUT to resume a killed run.", rich_help_panel=OUTPUT),
    explain: Optional[Path] = typer.Option(None, metavar="DIR", help="Write a Figure 4-style PNG panel per input (and per component) here.", rich_help_panel=OUTPUT),
    overlay: list[Path] = typer.Option([], metavar="PHOTO", help="The photo behind each mask, in the same order (repeat it): the fit is drawn over it, into --explain DIR.", rich_help_panel=OUTPUT),
    mesh: Optional[Path] = typer.Option(None, metavar="DIR", help="Write each fitted box as a Wavefront OBJ mesh here, DIR/<input>.obj, in the camera's frame (x right, y down, z forward; units: box heights); its vertices are the keypoints, in order. Not with --networks-only.", rich_help_panel=OUTPUT),
    workers: int = typer.Option(1, min=1, metavar="N", help="Processes fitting at once, each with its own models and one torch thread.", rich_help_panel=SPEED),
    cluster: Optional[str] = typer.Option(None, metavar="ADDRESS", help="Fit on a Dask cluster (pip install 'cuboid-fit\\[cluster]'): tcp://HOST:8786 joins a running scheduler; local starts one here with --workers processes. Workers read the inputs' paths themselves.", rich_help_panel=SPEED),
    device: str = in_panel(DEVICE, SPEED),
) -> None:
    """Fit cuboids to mask images: keypoints in the input's own pixels, ratios, confidence (JSON), and one
    line per input on stderr (file, shape, trust, ratios, yaw, camera, warnings) and a total.

    Exits 1 when any input failed (its record says why); the others are still written.
    """
    from cuboidtrain.infer.run import InferRequest, infer as run_infer, json_destination  # no torch: it comes after the workers' warm-up

    setup_logging()
    options = FitOptions(shape=shape.value, refine_steps=refine_steps, margin=margin, extractor=extractor.value,
                         pdm_components=pdm_components, all_components=all_components, label_id=label_id,
                         threshold=threshold, invert=invert, device=device, cuboid=cuboid, shape_classifier=not no_classifier, optimizer=optimizer.value, focal_px=focal_px,
                         principal_px=principal_px, cameras=read_cameras(camera) if camera is not None else ())
    request = InferRequest(paths=tuple(paths or []), from_list=from_list, glob=glob, checkpoints=tuple(checkpoint),
                           options=options, json_out=json_destination(json_out, jsonl, sys.stdout.isatty()),
                           jsonl=jsonl, workers=workers, cluster=cluster, explain=explain, overlay=tuple(overlay),
                           photos=tuple(photo), mesh=mesh)
    result = run_infer(request, console)
    if result.pictures is not None:
        say(f"{result.pictures} picture{'' if result.pictures == 1 else 's'} in {explain}")
    if result.meshes is not None:
        say(f"{result.meshes} mesh{'' if result.meshes == 1 else 'es'} in {mesh}")
    if result.stopped is not None:
        say(stopped_line(result.tally, result.records, request))
        raise typer.Exit(result.stopped)
    if result.tally.failed:
        console.print(f"{result.tally.failed} of {result.tally.total} inputs have an error (see their records' "
                      f"\"error\" field)", highlight=False)
        raise typer.Exit(1)


def stopped_line(tally, records: int | None, request) -> str:
    """What a stopped `infer` kept: the inputs fitted of all, and where their records are."""
    kept = [f"{records} record{'' if records == 1 else 's'} in {request.json_out}"] if records is not None and request.json_out != "-" else []
    if request.jsonl is not None:
        kept.append(f"the store {request.jsonl} (the same command resumes it)")
    where = f"; {' and '.join(kept)}" if kept else ""
    return f"stopped by {tally.stopped}: {tally.resumed + tally.done} of {tally.total} inputs fitted{where}"


@app.command()
def serve(
    host: str = typer.Option("127.0.0.1", metavar="ADDRESS", help="The address to listen on: 127.0.0.1 is this machine only; 0.0.0.0 every interface (anyone who can reach it may fit masks)."),
    port: int = typer.Option(8765, min=1, max=65535, help="The port to listen on."),
    workers: int = typer.Option(2, min=1, help="Fitting processes, each with the shipped models and one torch thread: answers at once."),
    max_upload_mb: float = typer.Option(32.0, metavar="MB", help="The largest upload taken, in MB (10^6 bytes); a larger one is refused in one line."),
) -> None:
    """A local page to try the shipped models: drop a mask, see the fit and its explanation, turn the box in 3D.

    Fits as `infer` does (the same Fitter and options, the cuboid fit on). Needs the web extra:
    pip install 'cuboid-fit\\[web]'. Ctrl-C stops it.
    """
    from cuboidtrain.web.server import ServeConfig, serve as run_server  # the web extra: only here

    setup_logging()
    run_server(ServeConfig(host=host, port=port, workers=workers, max_upload_mb=max_upload_mb), announce=typer.echo)
    console.print("stopped", highlight=False)


@app.command()
def export(
    checkpoint: Optional[Path] = typer.Option(None, metavar="CKPT", help="A trained model (cuboidtrain run's last.pt, or a model file); default: the shipped model of --shape."),
    shape: ShapeChoice = SHIPPED_SHAPE,
    onnx: Path = typer.Option(..., metavar="OUT.onnx", help="Where the ONNX model goes (replaced atomically)."),
    refine_steps: int = typer.Option(1, metavar="K", help="Refiner passes in the graph, each on the last one's binary output."),
    opset: int = typer.Option(17, help="ONNX opset (11 to 20)."),
) -> None:
    """Export R (K passes), S and T as one ONNX graph: +-1 mask in; refined, heatmaps, keypoints, ratios out."""
    from cuboidtrain.infer.export import export_checkpoint
    from cuboidtrain.models.zoo import default_checkpoints

    setup_logging()
    check_outputs(("--onnx", onnx))
    checkpoint = default_checkpoints([checkpoint] if checkpoint else None, (shape.value,))[0]
    meta = export_checkpoint(checkpoint, onnx, refine_steps=refine_steps, opset=opset)
    say(f"{onnx}: {meta['shape']} model, {meta['size']} px, {meta['refine_steps']} Refiner pass(es), "
        f"step {meta['checkpoint_step'] or '?'}, opset {opset}")


STREET_HELP = "A street's known buildings (docs/inference.md: Localization); locate the MASKs in it."
TEMPERATURE_HELP = "Probabilities are softmax(-distance / temperature)."
BOX_CHECKPOINT_HELP = "A trained box model (street buildings are single boxes); default: the shipped one."
BOX_CHECKPOINTS = typer.Option(None, metavar="CKPT", help=BOX_CHECKPOINT_HELP)
TEMPERATURE = typer.Option(1.0, help=TEMPERATURE_HELP)
REFINE_STEPS_AS_INFER = refine_steps_option("Refiner passes, as infer.")
MARGIN_AS_INFER = typer.Option(FIT.margin, help="Framing margin, as infer.")
RESULT_JSON = typer.Option(None, "--json", metavar="OUT", help="The result as JSON: a file or - for stdout.")
BARS = typer.Option(None, metavar="OUT.png", help="Figure 12: probability of each start position.")


@app.command()
def localize(
    mask_args: Optional[list[str]] = typer.Argument(None, metavar="MASK", help="Masks of consecutive buildings, in street order."),
    street: Path = typer.Option(..., metavar="STREET.json", help=STREET_HELP),
    masks: Optional[list[str]] = typer.Option(None, "--masks", metavar="MASK", help="Masks in street order: --masks A B C, or one per --masks."),
    checkpoint: Optional[list[Path]] = BOX_CHECKPOINTS,
    temperature: float = TEMPERATURE,
    refine_steps: str = REFINE_STEPS_AS_INFER,
    margin: float = MARGIN_AS_INFER,
    json_out: Optional[str] = RESULT_JSON,
    bars: Optional[Path] = BARS,
    device: str = DEVICE,
    threads: Optional[int] = THREADS,
) -> None:
    """Localization (paper section 5): where in a known street the MASKs were taken, start positions ranked."""
    from cuboidtrain import localize as loc
    from cuboidtrain.experiments import localize_figures as figures
    from cuboidtrain.models.checkpoint import load_models

    out = localize_setup(json_out, threads)
    options = FitOptions(shape="box", refine_steps=refine_steps, margin=margin, device=device).validate()
    check_outputs(("--json", json_out), ("--bars", bars))
    paths = loc.mask_sequence(masks, mask_args)
    if not paths:
        raise UsageError("--street: expected masks (--masks A B C) to locate in it")
    result = loc.localize_masks(loc.read_street(street), paths, load_models(box_checkpoints(checkpoint)), options,
                                temperature=temperature)
    out.print(figures.ranking_table(result))
    if bars:
        figures.plot_ranking(bars, result)
    figures.write_json(json_out, result)


@app.command("localize-experiment")
def localize_experiment(
    checkpoint: Optional[list[Path]] = BOX_CHECKPOINTS,
    buildings: int = typer.Option(100, help="N, buildings per random street."),
    max_m: int = typer.Option(30, help="M, the longest sub-sequence (at most N)."),
    top_l: int = typer.Option(5, help="L, the widest top-l."),
    seed: int = typer.Option(0, help="Seed of the streets, views, occluders and noise."),
    streets: int = typer.Option(1, help="Independent streets; acc is their mean."),
    scene: str = typer.Option("paper", help="The generator's scene (extent ranges, views, occlusion, noise)."),
    mask_size: Optional[int] = typer.Option(None, metavar="PX", help="Size of the drawn masks (default the model's)."),
    oracle: bool = typer.Option(False, "--oracle", help="True ratios with --oracle-noise instead of the networks."),
    oracle_noise: float = typer.Option(0.0, metavar="SIGMA", help="The oracle's relative Gaussian noise (0: exact ratios)."),
    example_m: int = typer.Option(4, help="Figure 12's sub-sequence length."),
    example_start: Optional[int] = typer.Option(None, help="Figure 12's true start, 1-based (default the middle)."),
    temperature: float = TEMPERATURE,
    refine_steps: str = REFINE_STEPS_AS_INFER,
    margin: float = MARGIN_AS_INFER,
    cuboid: bool = typer.Option(FIT.cuboid, "--cuboid", help="The ratios of the perspective box fitted to each mask (infer --cuboid), not the Tabulator's."),
    json_out: Optional[str] = RESULT_JSON,
    csv_out: Optional[Path] = typer.Option(None, "--csv", metavar="OUT.csv", help="acc(m, l), one row per m."),
    heatmap: Optional[Path] = typer.Option(None, metavar="OUT.png", help="Figures 10-11's heat map of acc(m, l)."),
    bars: Optional[Path] = BARS,
    device: str = DEVICE,
    threads: Optional[int] = THREADS,
) -> None:
    """The localization experiment (paper section 5.1, eq. 2): acc(m, l) on random streets drawn by the generator."""
    from cuboidtrain.experiments import localize_experiment as experiment
    from cuboidtrain.experiments import localize_figures as figures
    from cuboidtrain.models.checkpoint import load_models

    out = localize_setup(json_out, threads)
    options = FitOptions(shape="box", refine_steps=refine_steps, margin=margin, device=device, cuboid=cuboid).validate()
    config = experiment.ExperimentConfig(
        buildings=buildings, max_m=max_m, top_l=top_l, seed=seed, streets=streets, scene=scene,
        mask_size=mask_size, oracle=oracle, oracle_noise=oracle_noise,
        example_m=example_m, example_start=example_start, temperature=temperature).validate()
    check_outputs(("--json", json_out), ("--csv", csv_out), ("--heatmap", heatmap), ("--bars", bars))
    checkpoint = [] if oracle else box_checkpoints(checkpoint)
    result = experiment.run_experiment(config, models=load_models(checkpoint),
                                       checkpoints=[str(c) for c in checkpoint], options=options)
    out.print(figures.accuracy_table(result))
    if csv_out:
        figures.write_csv(csv_out, result)
    if heatmap:
        figures.plot_accuracy(heatmap, result)
    if bars:
        figures.plot_example(bars, result)
    figures.write_json(json_out, result)


def localize_setup(json_out: Optional[str], threads: Optional[int]):
    """Set up logging and torch threads; returns where tables go: stdout, or stderr when --json - takes stdout."""
    import torch
    from rich.console import Console

    setup_logging()
    if threads is not None:
        torch.set_num_threads(max(threads, 1))
    return console if json_out == "-" else Console()


def box_checkpoints(given: Optional[list[Path]]) -> list[Path]:
    from cuboidtrain.models.zoo import default_checkpoints

    return default_checkpoints(given, ("box",))


@app.command()
def report(
    checkpoint: list[Path] = typer.Option([], metavar="CKPT", help="The trained model of a shape class (phase 1 + 2); repeat per class. Default: the shipped models."),
    clean_spool: list[Path] = typer.Option(..., metavar="DIR", help="Clean validation spool(s) (--scene paper-clean): Table 3, extractors."),
    noisy_spool: list[Path] = typer.Option([], metavar="DIR", help="Noisy, occluded validation spool(s) (--scene paper): extractors, refinement."),
    finetune: list[Path] = typer.Option([], metavar="CKPT", help="Table 3: the phase 1 model trained on with the final loss only (--phase finetune)."),
    e2e: list[Path] = typer.Option([], metavar="CKPT", help="Table 3: trained from random weights with the final loss only (--phase e2e)."),
    out: Path = typer.Option(Path("reports"), help="Folder for REPORT.md, report.json and the plots."),
    samples: int = typer.Option(500, help="Validation samples per spool and model."),
    sweep_samples: int = typer.Option(200, help="Generated samples per noise level, per shape for shape selection (twice this for occlusion)."),
    seed: int = typer.Option(0, help="Seed of the generated sweeps."),
    threads: Optional[int] = THREADS,
    device: str = typer.Option("cpu", help="cpu, cuda or cuda:N."),
) -> None:
    """Measure Table 3, Figure 14, occlusion, refinement, extractors and shape selection; write REPORT.md."""
    import shlex

    import torch

    from cuboidtrain.experiments.report import ReportConfig, run_report
    from cuboidtrain.experiments.report_figures import write_report
    from cuboidtrain.models.zoo import default_checkpoints

    setup_logging()
    if threads:
        torch.set_num_threads(threads)
    check_writable("--out", out, folder=True)
    checkpoint = default_checkpoints(checkpoint)
    config = ReportConfig(
        checkpoints=tuple(map(str, checkpoint)), clean_spools=tuple(map(str, clean_spool)),
        noisy_spools=tuple(map(str, noisy_spool)), finetune=tuple(map(str, finetune)), e2e=tuple(map(str, e2e)),
        out=str(out), samples=samples, sweep_samples=sweep_samples, seed=seed, device=device,
    )
    results = run_report(config)
    localization = out / "localization.md"
    command = "cuboidtrain report " + shlex.join(sys.argv[2:])
    written = write_report(results, out, command, localization if localization.is_file() else None)
    say(f"wrote {', '.join(str(p) for p in written)}")


models_app = CLI(add_completion=False, help="The shipped models: their cards, and packing a checkpoint into a model file.")
app.add_typer(models_app, name="models")


@models_app.callback(invoke_without_command=True)
def models(
    ctx: typer.Context,
    folder: Optional[Path] = typer.Option(None, metavar="DIR", help="Model files to list (default: the shipped ones, or $CUBOID_MODELS)."),
    as_json: bool = typer.Option(False, "--json", help="Print the cards as JSON."),
) -> None:
    """Print the model cards: arch, size, scenes, steps, samples seen, wall time, commit, validation figures."""
    if ctx.invoked_subcommand is not None:
        return
    from cuboidtrain.models.zoo import cards

    found = cards(folder)
    if as_json:
        typer.echo(json_text(found, indent=2))
    else:
        print_table(_cards_table(found))


def _cards_table(found: list[dict]):
    from rich.table import Table

    table = Table(title="Model files (cuboidtrain models --json: the whole cards)" if found else "No model files")
    for column in ("shape", "arch", "px", "input", "scenes", "steps", "samples", "hours", "clean/paper/street", "MiB"):
        table.add_column(column, no_wrap=column != "scenes", overflow="fold")  # a number is never split
    for card in found:
        sets = card.get("validation", {}).get("sets", {})
        figures = "/".join(f"{sets[s]['infer_mean_256']:.2f}" if s in sets else "-"
                           for s in ("paper-clean", "paper", "street"))
        table.add_row(card["shape"], card["arch"], str(card["size"]), "grey" if card.get("grey_input") else "binary",
                      "+".join(card.get("scenes", [])) or "-",
                      f"{card.get('steps', 0):,}", f"{card.get('samples_seen', 0):,}",
                      f"{(card.get('wall_time_s') or 0) / 3600:.2f}", figures, f"{card['bytes'] / 2**20:.1f}")
    if found:
        table.caption = "errors: mean corner px at 256 px, through infer"
    return table


def print_table(table) -> None:
    """A table on the console: in a terminal at its width; elsewhere (a log, `make demo`'s 80
    columns without a terminal) at the table's own, so that no row is wrapped."""
    from rich.console import Console
    from rich.measure import Measurement

    natural = Measurement.get(console, console.options.update(max_width=10_000), table).maximum
    out = console if console.is_terminal or natural <= console.width else Console(stderr=True, width=natural)
    out.print(table)


@models_app.command("pack")
def models_pack(
    checkpoint: Path = typer.Option(..., metavar="CKPT", help="A training checkpoint (cuboidtrain run's last.pt), or a model file with --pdm-spool."),
    out: Path = typer.Option(..., metavar="OUT.pt", help="The model file to write (replaced atomically)."),
    scene: list[str] = typer.Option([], metavar="NAME", help="A scene the training spool was drawn from, for the card (repeat)."),
    validation: Optional[Path] = typer.Option(None, metavar="JSON", help="Validation figures for the card (benchmarks/accuracy/bench_accuracy.py --json output)."),
    recipe: Optional[str] = typer.Option(None, help="The command that trained it, for the card."),
    half: bool = typer.Option(True, "--half/--float32", help="Store the weights as float16 (half the size)."),
    pdm_spool: Optional[Path] = typer.Option(None, metavar="DIR", help="Fit --extractor pdm's shape model on this spool's keypoints (the one it trained on) and save it in the file; with a model file as CKPT, only that is redone."),
) -> None:
    """Write a model file (weights, config, card; no optimizer state) from a training checkpoint."""
    from cuboidtrain.models.zoo import pack, validation_for

    check_outputs(("--out", out))
    figures = validation_for(validation, checkpoint) if validation else None
    card = pack(checkpoint, out, scene, figures, recipe, half, pdm_spool)
    say(f"{out}: {card['shape']} {card['arch']} {card['size']} px, {card['steps']} steps, "
        f"{out.stat().st_size / 2**20:.1f} MiB")


campaign_app = CLI(add_completion=False, help="The GPU campaign (docs/training.md, \"A GPU lease\"): one standing run that each lease continues.")
app.add_typer(campaign_app, name="campaign")


@campaign_app.command("lease")
def campaign_lease(
    out: Path = typer.Option(..., envvar="OUT", metavar="DIR", help="The folder the lent machine sends back ($OUT): the state's parts, lease.json, eval.json."),
    campaign: Path = typer.Option(Path("campaign"), metavar="DIR", help="The campaign folder: plan.json, the standing state, log.jsonl."),
    minutes: float = typer.Option(9.5, help="The whole command's minutes, smoke check to the last file; training ends the plan's eval_minutes before (15 s with --no-evaluate)."),
    device: str = typer.Option("cuda", help="cuda (the smoke check fails in seconds without it), cuda:N or cpu."),
    work: Path = typer.Option(Path("/tmp/campaign-work"), metavar="DIR", help="Spools, run folders and logs (emptied first; not sent back)."),
    lease_steps: Optional[int] = typer.Option(None, help="Train at most this many steps a shape (a deterministic stop, for tests)."),
    spool: Optional[Path] = typer.Option(None, metavar="DIR", help="Train every shape on this frozen spool instead of starting generators (tests)."),
    evaluate: bool = typer.Option(True, "--evaluate/--no-evaluate", help="Score the result and the shipped models on bench_accuracy's sets."),
    commit: Optional[str] = typer.Option(None, envvar="COMMIT", help="The commit the tree is (the lent machine has no .git)."),
    threads: Optional[int] = typer.Option(None, help="Each trainer's CPU threads for torch."),
    eval_threads: Optional[int] = typer.Option(None, help="bench_accuracy's threads (default: 4)."),
) -> None:
    """Run one lease: smoke check, generators, the standing run resumed until the deadline, state and log row into OUT, evaluation."""
    from cuboidtrain.campaign.lease import LeaseOptions, run_lease

    setup_logging()
    row = run_lease(LeaseOptions(out=out, campaign=campaign, work=work, minutes=minutes, device=device, lease_steps=lease_steps,
                                 spool=spool, evaluate=evaluate, commit=commit, threads=threads, eval_threads=eval_threads))
    typer.echo(json_text(row))  # the log row, one line on stdout


@campaign_app.command("apply")
def campaign_apply(
    returned: Path = typer.Argument(..., metavar="DIR", help="What the lease sent back (the device's files_at, or a folder below it holding lease.json)."),
    campaign: Path = typer.Option(Path("campaign"), metavar="DIR", help="The campaign folder to update."),
) -> None:
    """Take a lease's state, log row and evaluation into the campaign folder (once per lease)."""
    from cuboidtrain.campaign.apply import apply_lease

    row = apply_lease(returned, campaign)
    say(f"{campaign}: lease {row['lease']} applied ({row['steps']} steps, {row['minutes_trained']} min trained "
        f"on {row['device']}); commit campaign/ now")


@campaign_app.command("evaluate")
def campaign_evaluate(
    campaign: Path = typer.Option(Path("campaign"), metavar="DIR", help="The campaign folder whose standing state to score."),
    work: Path = typer.Option(Path("/tmp/campaign-eval"), metavar="DIR", help="Checkpoints, model files and spools (emptied first)."),
    threads: int = typer.Option(1, help="bench_accuracy's torch threads."),
) -> None:
    """Score the standing state and the shipped models on the lease's masks, here: CAMPAIGN/eval.json (for a lease whose own evaluation did not finish)."""
    from cuboidtrain.campaign.lease import EVAL, evaluate_state

    setup_logging()
    record = evaluate_state(campaign, work, threads)
    for name, figures in record["compare"]["sets"].items():
        say(f"{name}: campaign {figures.get('campaign', '-')} px, shipped {figures.get('shipped', '-')} px (mean corner error, 256 px units)")
    say(f"{campaign / EVAL}: lease {record['lease']}, the campaign wins {record['compare']['campaign_wins']} of "
        f"{record['compare']['compared']} sets; commit campaign/ now")


classifier_app = CLI(add_completion=False, help="The shape classifier: the fourth network, which calls a rough silhouette box or twobox (cuboidtrain.models.classifier).")
app.add_typer(classifier_app, name="classifier")


@classifier_app.command("train")
def classifier_train(
    box: Path = typer.Option(..., metavar="DIR", help="A spool of box samples (cuboidgen run --shape box): their noisy masks are the box class."),
    twobox: Path = typer.Option(..., metavar="DIR", help="A spool of twobox samples: the twobox class."),
    out: Path = typer.Option(..., metavar="OUT.pt", help="The classifier file to write (replaced atomically); the shipped one is cuboidtrain/models/shipped/classifier.pt."),
    minutes: Optional[float] = typer.Option(None, min=0.01, help="Train this long (the learning rate a cosine over it)."),
    steps: Optional[int] = typer.Option(None, min=1, help="Or this many steps of --batch-size masks (whichever ends first)."),
    batch_size: int = typer.Option(128, min=2, help="Masks a step."),
    seed: int = typer.Option(0, help="The weights' and the batches' seed."),
    threads: int = typer.Option(1, min=1, help="Torch threads (one: it trains beside the daemons)."),
    device: str = typer.Option("cpu", help="cpu, cuda or cuda:N (the masks are then held on the GPU: 2 GB for 120,000)."),
    scene: list[str] = typer.Option([], metavar="NAME", help="A scene the spools were drawn from, for the card (repeat)."),
    recipe: Optional[str] = typer.Option(None, help="The command that drew the spools and trained it, for the card."),
    init: Optional[Path] = typer.Option(None, metavar="FILE.pt", help="Start from this classifier's weights (train on), not random ones; its card is kept in the new one's."),
    lr: Optional[float] = typer.Option(None, help="The cosine's peak learning rate (default 2e-3; lower to train on from --init)."),
) -> None:
    """Train the shape classifier on a box spool and a twobox spool and write its file (weights and card)."""
    import torch

    from cuboidtrain.models.classifier import save_classifier
    from cuboidtrain.models.zoo import git_commit
    from cuboidtrain.train.classifier_training import train_classifier

    setup_logging()
    check_outputs(("--out", out))
    torch.set_num_threads(threads)
    spools = {"box": box, "twobox": twobox}
    trained = train_classifier(spools, minutes, steps, batch_size, seed, device, init, lr)
    save_classifier(out, trained.net, trained.card(spools, scene, git_commit(), recipe))
    say(f"{out}: shape classifier, {trained.steps:,} steps of {batch_size} on {sum(trained.masks.values()):,} masks "
        f"in {trained.wall_time_s / 60:.1f} min, {out.stat().st_size / 2**10:.0f} KiB")


@app.command()
def version() -> None:
    """Print the package version."""
    from importlib.metadata import version as pkg_version

    typer.echo(pkg_version("cuboid-fit"))


def main() -> None:
    app()
