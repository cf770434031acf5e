"""The `pwm` command line."""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Optional

import typer

app = typer.Typer(help="Shape modeling of an asteroid with pixel-weighted maplets.", no_args_is_help=True,
                  add_completion=False, pretty_exceptions_enable=False)


def _logging(verbose: bool) -> None:
    logging.basicConfig(level=logging.DEBUG if verbose else logging.INFO, format="%(asctime)s %(levelname)s %(message)s", datefmt="%H:%M:%S")


def _knowledge_error(value: Optional[str]) -> tuple[float, float]:
    if value is None:
        return 0.0, 0.0
    try:
        pos_m, point_rad = (float(x) for x in value.split(","))
    except ValueError:
        raise typer.BadParameter("expected POS_M,POINT_RAD, e.g. 1.0,1e-4") from None
    if pos_m < 0 or point_rad < 0:
        raise typer.BadParameter("knowledge errors must be non-negative")
    return pos_m, point_rad


@app.command()
def simulate(
    out: Path = typer.Argument(..., help="output directory (downlink/ and truth/ are written in it)"),
    scenario: str = typer.Option("tiny", help="tiny | site | site-polar | global-coarse"),
    seed: int = typer.Option(0, help="random seed: the same seed gives the same products"),
    knowledge_error: Optional[str] = typer.Option(None, help="POS_M,POINT_RAD: 1-sigma position (m) and pointing (rad) errors in the kernels"),
    verbose: bool = typer.Option(False, "--verbose", "-v"),
) -> None:
    """Simulate a mission downlink (PDS4 images, SPICE kernels, start model) from a truth asteroid."""
    from pwm.simulate.campaign import simulate as run_simulation
    from pwm.simulate.scenarios import get_scenario

    _logging(verbose)
    try:
        sc = get_scenario(scenario)
    except ValueError as exc:
        raise typer.BadParameter(str(exc)) from None
    pos_m, point_rad = _knowledge_error(knowledge_error)
    manifest = run_simulation(out, scenario=sc, seed=seed, position_error_m=pos_m, pointing_error_rad=point_rad)
    typer.echo(f"{manifest['image_count']} images, GSD {manifest['gsd_m']:.3f} m -> {out}")


@app.command()
def evaluate(
    model: Path = typer.Argument(..., exists=True, dir_okay=False, help="model mesh (.obj or .ply, km, body-fixed)"),
    truth: Path = typer.Option(..., exists=True, file_okay=False, help="the simulation's truth/ directory"),
    json_out: Optional[Path] = typer.Option(None, "--json", help="write the figures as JSON here"),
    plots: Optional[Path] = typer.Option(None, help="write PNG plots (height error, profiles, views) here"),
    verbose: bool = typer.Option(False, "--verbose", "-v"),
) -> None:
    """Measure a model against the truth: ICP, RMS and median error, NCC/SSIM, boulder heights."""
    from pwm.evaluate.report import evaluate as run_evaluation, format_table

    _logging(verbose)
    result = run_evaluation(model, truth_dir=truth, plots_dir=plots)
    typer.echo(format_table(result))
    if json_out is not None:
        json_out.parent.mkdir(parents=True, exist_ok=True)
        json_out.write_text(json.dumps(result, indent=2))


@app.command()
def ingest(
    directory: Path = typer.Argument(..., exists=True, file_okay=False, help="a downlink directory (PDS4 labels, SPICE kernels)"),
    shape: Optional[Path] = typer.Option(None, exists=True, dir_okay=False, help="current shape model for boresight intercepts (.obj/.ply, km); default: the PCK ellipsoid"),
    name: Optional[str] = typer.Option(None, help="downlink name (default: the directory name)"),
    verbose: bool = typer.Option(False, "--verbose", "-v"),
) -> None:
    """Catalogue a downlink: kernels first, then every PDS4 product, accepted or rejected with a reason.

    Idempotent. The exit status is the number of files that failed (capped at 100); 0 means all went in.
    """
    from pwm.io.meshio import read_mesh
    from service.catalog import open_catalog
    from service.ingest import ingest_directory

    _logging(verbose)
    report = ingest_directory(open_catalog(), directory, downlink_name=name, shape=read_mesh(shape) if shape else None)
    typer.echo(report.summary())
    raise typer.Exit(min(report.failed, 100))


@app.command()
def images(
    status: Optional[str] = typer.Option(None, help="accepted | rejected | conflict"),
    limit: int = typer.Option(50, min=1, help="at most this many rows"),
) -> None:
    """List catalogued images: LIDVID, status, time, range and angles at the boresight intercept."""
    from sqlalchemy import select

    from service.catalog import open_catalog
    from service.models import Image

    with open_catalog()() as session:
        query = select(Image).order_by(Image.start_utc, Image.id).limit(limit)
        if status:
            query = query.where(Image.status == status)
        for image in session.scalars(query):
            g = image.geometry
            where = (f"range {g.range_km:.3f} km  inc {g.incidence_deg:.1f}  emi {g.emission_deg:.1f}  pha {g.phase_deg:.1f}"
                     if g is not None and g.incidence_deg is not None else (image.rejection_reason or image.geometry_unavailable_reason or ""))
            typer.echo(f"{image.lidvid}  {image.status}  {image.start_utc}  {where}")


if __name__ == "__main__":
    app()
