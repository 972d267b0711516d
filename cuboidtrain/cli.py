"""`cuboidtrain`: the trainer daemon's command line (training arrives with its issue)."""
from __future__ import annotations

import typer

app = typer.Typer(add_completion=False, no_args_is_help=True)


@app.callback()
def cuboidtrain() -> None:
    """Train the Refiner, Estimator and Tabulator from a spool (training is not implemented yet)."""


@app.command()
def version() -> None:
    """Print the package version."""
    from importlib.metadata import version as pkg_version

    typer.echo(pkg_version("cuboid-fit"))


def main() -> None:
    app()
