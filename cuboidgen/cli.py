"""`cuboidgen`: parse options, build a GenConfig, call the library. Nothing else lives here."""
from __future__ import annotations

import os
import sys
from dataclasses import asdict
from pathlib import Path
from typing import Optional

import typer
from rich.console import Console
from rich.table import Table

from cuboidgen.config import GEN_SHAPES, SCENES, GenConfig
from shared.console import CLI, choices, say, setup_logging
from shared.errors import UsageError, check_outputs, check_writable
from shared.files import atomic_path, json_text

app = CLI(add_completion=False, no_args_is_help=True,
                  help="Synthetic cuboid samples into a capped spool.")
occluders_app = CLI(no_args_is_help=True, help="Occluder libraries: extract cutouts, preview them.")
app.add_typer(occluders_app, name="occluders")


GenShape = choices("GenShape", GEN_SHAPES)
GEN = GenConfig()  # `run`'s defaults are the config's: stated once


@app.command()
def run(
    spool: Path = typer.Option(GEN.spool, envvar="CUBOIDGEN_SPOOL", help="Spool folder (created if missing)."),
    limit: int = typer.Option(GEN.limit, envvar="CUBOIDGEN_LIMIT",
                              help="Samples kept; the oldest are evicted. 0 retains the spool (no eviction)."),
    max_samples: Optional[int] = typer.Option(None, envvar="CUBOIDGEN_MAX_SAMPLES", help="Stop after publishing this many samples."),
    workers: int = typer.Option(os.cpu_count() or 1, envvar="CUBOIDGEN_WORKERS", help="Worker processes (default: all cores; at most 4 per core)."),
    size: int = typer.Option(GEN.size, envvar="CUBOIDGEN_SIZE", help="Mask size in px (square)."),
    shape: GenShape = typer.Option(GenShape[GEN.shape], envvar="CUBOIDGEN_SHAPE", help="Shape class; mix picks one per sample."),
    seed: Optional[int] = typer.Option(None, envvar="CUBOIDGEN_SEED", help="Run seed: the same seed and options give the same samples."),
    scene: str = typer.Option(GEN.scene.name, envvar="CUBOIDGEN_SCENE",
                              help=f"Scene preset ({', '.join(SCENES)}) or a .json/.toml scene file."),
    occluders: Optional[Path] = typer.Option(None, envvar="CUBOIDGEN_OCCLUDERS",
                                             help="Folder of RGBA or binary PNG occluders (default: built-in)."),
    dashboard: bool = typer.Option(True, "--dashboard/--no-dashboard", envvar="CUBOIDGEN_DASHBOARD",
                                   help="Live dashboard (else log lines)."),
    fsync: bool = typer.Option(False, envvar="CUBOIDGEN_FSYNC",
                               help="Sync every sample to disk before publishing it (survives power loss)."),
    evict_every: int = typer.Option(GEN.evict_every, envvar="CUBOIDGEN_EVICT_EVERY",
                                    help="Publishes between spool listings; bounds overshoot per worker."),
    max_rate: Optional[float] = typer.Option(None, envvar="CUBOIDGEN_MAX_RATE",
                                             help="At most this many samples a second, all workers together "
                                                  "(default: as fast as they go)."),
) -> None:
    """Generate samples into the spool until Ctrl-C/SIGTERM (or --max-samples)."""
    from cuboidgen.config import load_scene
    from cuboidgen.daemon import run as run_daemon
    from cuboidgen.scene import check_drawable
    from shared.shapes import SHAPES, get_shape

    setup_logging()
    config = GenConfig(
        spool=spool, limit=limit, max_samples=max_samples, workers=workers, size=size, shape=shape.value,
        seed=seed, scene=load_scene(scene), occluders=occluders, dashboard=dashboard, fsync=fsync,
        evict_every=evict_every, max_rate=max_rate,
    ).validate()
    check_drawable(config.scene, [get_shape(s) for s in SHAPES if config.shape in (s, "mix")], config.size)
    if occluders is not None:
        from cuboidgen.occluders import OccluderLibrary

        OccluderLibrary.from_dir(occluders)  # fail now, in one line, not in every worker
    run_daemon(config)


@app.command()
def preview(
    spool: Path = typer.Argument(..., help="Spool folder."),
    out: Path = typer.Option(Path("preview.png"), help="PNG to write."),
    count: int = typer.Option(12, help="How many of the newest samples."),
    columns: int = typer.Option(4, help="Samples per row."),
) -> None:
    """Draw the newest samples: noisy input | clean mask with keypoints, indices and wireframe."""
    from cuboidgen.preview import newest_samples, render_grid

    check_outputs(("--out", out))
    path = render_grid(newest_samples(spool, count), out, columns)
    say(f"wrote {path}")


@app.command()
def inspect(
    spool: Path = typer.Argument(..., help="Spool folder."),
    as_json: bool = typer.Option(False, "--json", help="Print JSON instead of a table."),
) -> None:
    """Count samples, corrupt files, shapes, sizes, bytes and ages in a spool."""
    from shared.inspect import inspect_spool

    report = inspect_spool(spool)
    if as_json:
        typer.echo(json_text(report, indent=2))
        return
    table = Table("key", "value", title=f"spool {spool}")
    for key, value in report.items():
        table.add_row(key, str(value))
    Console().print(table)


@app.command()
def masks(
    spool: Path = typer.Argument(..., metavar="SPOOL", help="Spool folder."),
    out: Path = typer.Argument(..., metavar="OUT_DIR", help="Folder to write into (created if missing)."),
    count: Optional[int] = typer.Option(None, metavar="N", help="Only the first N samples, in the spool's order (default: all)."),
    clean: bool = typer.Option(False, "--clean", help="The clean silhouette instead of the noisy, occluded input mask."),
) -> None:
    """Write each sample's input mask as OUT_DIR/NNNNN.png and its truth as NNNNN.json (shape, keypoints,
    ratios, camera focal length and principal point in px): for `cuboidtrain infer OUT_DIR`."""
    from cuboidgen.export_masks import write_masks

    check_writable("OUT_DIR", out, folder=True)
    written = write_masks(spool, out, count, clean)
    say(f"wrote {written} mask{'' if written == 1 else 's'} and their truth to {out} "
        f"(try: cuboidtrain infer {out} --json -)")


@app.command()
def health(
    spool: Path = typer.Argument(..., help="Spool folder."),
    max_age: float = typer.Option(60.0, help="Healthy while the newest sample is at most this many seconds old."),
    mine: bool = typer.Option(False, "--mine", help="Only samples published from this host (a container's own)."),
) -> None:
    """Exit 0 when the spool's newest sample is fresh and decodes, else 1 (a container healthcheck)."""
    from shared.inspect import freshness
    from shared.spool import host_tag

    try:
        if max_age <= 0:
            raise UsageError(f"--max-age {max_age}: expected a positive number of seconds")
        report = freshness(spool, host_tag() if mine else None)
    except (ValueError, OSError) as exc:  # unhealthy, not the one-line error: a healthcheck's answer is 0 or 1
        unhealthy(str(exc))
    whose = f" from host {report['host']}" if report["host"] else ""
    if report["newest"] is None:
        unhealthy(f"spool {spool}: no samples{whose}")
    if report["corrupt"]:
        unhealthy(f"spool {spool}: newest sample{whose} {report['newest']} is corrupt ({report['corrupt']})")
    if report["age_s"] > max_age:
        unhealthy(f"spool {spool}: newest sample{whose} is {report['age_s']:.0f} s old, expected at most {max_age:g} s")
    typer.echo(f"healthy: newest sample{whose} {report['age_s']:.1f} s old, {report['samples']} samples")


def unhealthy(message: str) -> None:
    # Exit 1, not fail()'s 2: Docker reads a healthcheck's 1 as unhealthy and reserves 2.
    say(f"[red]unhealthy:[/red] {message}")
    raise typer.Exit(1)


@app.command()
def scenes(name: Optional[str] = typer.Argument(None, help="Show one preset's ranges.")) -> None:
    """List the scene presets, or print one as JSON (a starting point for your own file)."""
    from cuboidgen.config import SCENES
    from cuboidgen.irregular import irregular

    if name is None:
        for preset in SCENES.values():
            kind = "ground-standing, tilted camera" if preset.eye_height else "paper Table 4"
            if preset.occluders == (0, 0) and preset.contour_noise == (0.0, 0.0):
                kind += ", no occlusion or contour noise (Table 3's validation)"
            if irregular(preset):
                kind += ", irregular outlines (roof lines, chimneys, parapets, neighbours, blobby edges, low resolution)"
            typer.echo(f"{preset.name}: {kind}")
        return
    if name not in SCENES:
        raise UsageError(f"scene {name!r}: expected one of {', '.join(SCENES)}")
    typer.echo(json_text(asdict(SCENES[name]), indent=2))


@app.command()
def bench(
    size: int = typer.Option(256, help="Mask size in px."),
    samples: int = typer.Option(400, help="Samples per repeat."),
    repeats: int = typer.Option(5, help="Repeats; medians are reported."),
    json_out: Optional[Path] = typer.Option(None, "--json", help="Also write the results as JSON here."),
    where: Path = typer.Option(Path("."), "--dir", help="Make the benchmark spools here (the spool's filesystem)."),
) -> None:
    """Generation and spool read throughput on this machine (table and JSON)."""
    from cuboidgen.bench import run_benchmarks

    setup_logging()
    check_outputs(("--json", json_out))
    results = run_benchmarks(size=size, samples=samples, repeats=repeats, where=str(where))
    text = json_text(results, indent=2)
    if json_out:
        with atomic_path(json_out) as tmp:
            tmp.write_text(text)
    typer.echo(text)


@occluders_app.command("extract")
def occluders_extract(
    cityscapes: Path = typer.Option(..., help="Cityscapes root (holding gtFine/)."),
    out: Path = typer.Option(..., help="Folder to write PNG cutouts into."),
    classes: Optional[list[str]] = typer.Option(None, "--class", help="Restrict to these classes (repeatable)."),
    min_pixels: int = typer.Option(400, help="Skip cutouts smaller than this."),
) -> None:
    """Cut occluder instances (car, person, pole, vegetation, ...) out of Cityscapes gtFine labels."""
    from cuboidgen.occluders import extract_cityscapes

    setup_logging()
    check_writable("--out", out, folder=True)
    counts = extract_cityscapes(cityscapes, out, classes=classes or None, min_pixels=min_pixels)
    for name, n in sorted(counts.items()):
        typer.echo(f"{name}: {n}")
    typer.echo(f"total: {sum(counts.values())} cutouts in {out}")


@occluders_app.command("preview")
def occluders_preview(
    occluders: Optional[Path] = typer.Option(None, help="Folder of PNG cutouts (default: built-in library)."),
    out: Path = typer.Option(Path("occluders.png"), help="PNG to write."),
) -> None:
    """Tile an occluder library into one picture."""
    from cuboidgen.occluders import OccluderLibrary
    from cuboidgen.preview import render_occluders

    check_outputs(("--out", out))
    path = render_occluders(OccluderLibrary.load(occluders), out)
    say(f"wrote {path}")


def main() -> None:
    app()


if __name__ == "__main__":
    sys.exit(main())
