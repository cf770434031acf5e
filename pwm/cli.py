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


if __name__ == "__main__":
    app()
