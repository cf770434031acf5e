"""`pwm spg`: stereo photogrammetry on a downlink directory, without the catalog."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import typer

from service.cli.app import app, setup_logging


@app.command()
def spg(
    downlink: Path = typer.Argument(..., exists=True, file_okay=False, help="a downlink directory (PDS4 images, kernels with one meta-kernel)"),
    start: Path = typer.Option(..., exists=True, dir_okay=False, help="previous shape model (.obj/.ply, km, body-fixed): fills where points are missing"),
    out: Path = typer.Option(..., help="output directory: spg.ply, spg.obj, corrections.json, spg.json"),
    sigma_position: float = typer.Option(1.0, min=0.0, help="navigation position knowledge, 1 sigma per axis, m"),
    sigma_pointing: float = typer.Option(1e-4, min=0.0, help="navigation pointing knowledge, 1 sigma per axis, rad"),
    max_features: int = typer.Option(8192, min=64, help="SIFT features per image at most"),
    first_octave: int = typer.Option(0, min=-1, max=1, help="SIFT first octave: -1 doubles the images (more features, ~3x slower)"),
    per_image: int = typer.Option(6, min=1, help="stereo partners matched per image"),
    threads: int = typer.Option(2, min=1, help="threads for extraction and matching"),
    instrument: int = typer.Option(-64361, help="NAIF id of the camera"),
    target: str = typer.Option("BENNU"),
    body_frame: str = typer.Option("IAU_BENNU"),
    verbose: bool = typer.Option(False, "--verbose", "-v"),
) -> None:
    """Photogrammetric model and per-image pose corrections from a downlink's images."""
    from pwm.io.downlink import read_views
    from pwm.io.meshio import read_mesh, write_obj, write_ply
    from pwm.spg import stereo_photogrammetry

    setup_logging(verbose)
    views = read_views(downlink, instrument_id=instrument, target=target, body_frame=body_frame)
    result = stereo_photogrammetry(views, read_mesh(start), sigma_position_km=sigma_position * 1e-3, sigma_pointing_rad=sigma_pointing,
                                   max_features=max_features, first_octave=first_octave, per_image=per_image, threads=threads)
    out.mkdir(parents=True, exist_ok=True)
    write_ply(out / "spg.ply", result.mesh)
    write_obj(out / "spg.obj", result.mesh)
    corrections = {name: dataclasses.asdict(c) for name, c in result.corrections.items()}
    (out / "corrections.json").write_text(json.dumps({"frame": body_frame, "units": {"position": "km", "rotation": "rad"},
                                                      "images": corrections}, indent=1))
    (out / "spg.json").write_text(json.dumps({**result.stats, "pairs": [dataclasses.asdict(p) for p in result.pairs]}, indent=1))
    typer.echo(f"{result.stats['points']} points from {len(views)} images, residual {result.stats['residual_rms_px']:.2f} px RMS, "
               f"{result.stats['seconds']:.1f} s -> {out}")
