"""`pwm spg`: stereo photogrammetry on a downlink directory, without the catalog; `pwm spg-catalog`:
on the catalogued images, publishing a photogrammetric version and storing pose corrections."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import typer

from pwm.camera import PoseCorrection
from pwm.spg.config import SPG_DEFAULTS, SpgConfig
from service.cli.app import BODY_FRAME, INSTRUMENT, TARGET, app, downlink_report, downlink_views, finite, setup_logging

# options both commands take, their defaults pwm.spg.config's
SIGMA_POSITION_M = SPG_DEFAULTS.sigma_position_km * 1e3
SIGMA_POINTING = typer.Option(SPG_DEFAULTS.sigma_pointing_rad, parser=finite(ge=0.0),
                              help="pointing knowledge, 1 sigma per axis, rad")
MAX_FEATURES = typer.Option(SPG_DEFAULTS.max_features, min=64, help="SIFT features per image at most")
FIRST_OCTAVE = typer.Option(SPG_DEFAULTS.first_octave, min=-1, max=1,
                            help="SIFT first octave: -1 doubles the images (more features, ~3x slower); "
                                 f"default -1 where the target fills under {SPG_DEFAULTS.double_below:.0%} of the "
                                 "frame, else 0")
PER_IMAGE = typer.Option(SPG_DEFAULTS.per_image, min=1, help="stereo partners matched per image")
THREADS = typer.Option(SPG_DEFAULTS.threads, min=1, help="threads for extraction and matching")
MAX_SUN_DEG = typer.Option(SPG_DEFAULTS.max_sun_deg, parser=finite(gt=0.0, le=180.0),
                           help="largest angle between the body-fixed Sun directions of a stereo pair, deg (the body "
                                "turns between images taken apart in time)")


def spg_config(*, sigma_position_m: float, sigma_pointing_rad: float, max_features: int, first_octave: int | None,
               per_image: int, threads: int, max_sun_deg: float) -> SpgConfig:
    """The photogrammetry's settings from the options (the rest at their defaults)."""
    return SpgConfig(sigma_position_km=sigma_position_m * 1e-3, sigma_pointing_rad=sigma_pointing_rad,
                     max_features=max_features, first_octave=first_octave, per_image=per_image, threads=threads,
                     max_sun_deg=max_sun_deg)


def write_corrections(path: Path, corrections: dict[str, PoseCorrection], *, body_frame: str) -> None:
    """Per-image pose corrections (by view name; km and rad, body-fixed) as JSON."""
    images = {name: dataclasses.asdict(c) for name, c in corrections.items()}
    path.write_text(json.dumps({"frame": body_frame, "units": {"position": "km", "rotation": "rad"}, "images": images},
                               indent=1))


def read_corrections(path: Path) -> dict[str, PoseCorrection]:
    """The pose corrections that `write_corrections` wrote, by view name."""
    images = json.loads(Path(path).read_text())["images"]
    return {name: PoseCorrection(tuple(c["position_km"]), tuple(c["rotation_rad"])) for name, c in images.items()}


@app.command()
def spg(
    downlink: Path = typer.Argument(..., exists=True, file_okay=False,
                                    help="a downlink directory (PDS4 images, kernels with one meta-kernel)"),
    start: Path = typer.Option(..., exists=True, dir_okay=False,
                               help="previous shape model (.obj/.ply, km, body-fixed): fills where points are missing"),
    out: Path = typer.Option(..., help="output directory: spg.ply, spg.obj, corrections.json, spg.json"),
    sigma_position: float = typer.Option(SIGMA_POSITION_M, parser=finite(ge=0.0),
                                         help="navigation position knowledge, 1 sigma per axis, m"),
    sigma_pointing: float = SIGMA_POINTING,
    max_features: int = MAX_FEATURES,
    first_octave: int | None = FIRST_OCTAVE,
    per_image: int = PER_IMAGE,
    threads: int = THREADS,
    max_sun_deg: float = MAX_SUN_DEG,
    instrument: str | None = INSTRUMENT,
    target: str | None = TARGET,
    body_frame: str | None = BODY_FRAME,
    verbose: bool = typer.Option(False, "--verbose", "-v"),
) -> None:
    """Photogrammetric model and per-image pose corrections from a downlink's images."""
    from pwm.io.meshio import read_mesh, write_obj, write_ply
    from pwm.spg import stereo_photogrammetry
    from service.cli.progress import working

    setup_logging(verbose)
    read = downlink_views(downlink, instrument=instrument, target=target, body_frame=body_frame)
    views = read.views
    config = spg_config(sigma_position_m=sigma_position, sigma_pointing_rad=sigma_pointing, max_features=max_features,
                        first_octave=first_octave, per_image=per_image, threads=threads, max_sun_deg=max_sun_deg)
    try:
        with working(f"photogrammetry on {len(views)} images"):
            result = stereo_photogrammetry(views, read_mesh(start), config=config)
    except ValueError as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(1) from None
    out.mkdir(parents=True, exist_ok=True)
    write_ply(out / "spg.ply", result.mesh)
    write_obj(out / "spg.obj", result.mesh)
    write_corrections(out / "corrections.json", result.corrections, body_frame=read.body_frame)
    (out / "spg.json").write_text(json.dumps({**result.stats, **downlink_report(read),
                                              "pairs": [dataclasses.asdict(p) for p in result.pairs]}, indent=1))
    typer.echo(f"{result.stats['points']} points from {len(views)} images, "
               f"residual {result.stats['residual_rms_px']:.2f} px RMS, "
               f"{result.stats['seconds']:.1f} s -> {out}")


@app.command(name="spg-catalog")
def spg_catalog(
    sigma_position: float = typer.Option(SIGMA_POSITION_M, parser=finite(ge=0.0),
                                         help="pose knowledge about the images' current poses, 1 sigma per axis, m"),
    sigma_pointing: float = SIGMA_POINTING,
    max_features: int = MAX_FEATURES,
    first_octave: int | None = FIRST_OCTAVE,
    per_image: int = PER_IMAGE,
    threads: int = THREADS,
    max_sun_deg: float = MAX_SUN_DEG,
    verbose: bool = typer.Option(False, "--verbose", "-v"),
) -> None:
    """Stereo photogrammetry on the catalogued images from the latest version: publish a photogrammetric version
    and store each image's pose correction (its maplets then become stale; the next ingest re-weighs its
    coverage)."""
    from service.catalog import open_catalog
    from service.cli.progress import working
    from service.settings import get_settings
    from service.spg import photogrammetry_version

    setup_logging(verbose)
    settings = get_settings()
    config = spg_config(sigma_position_m=sigma_position, sigma_pointing_rad=sigma_pointing, max_features=max_features,
                        first_octave=first_octave, per_image=per_image, threads=threads, max_sun_deg=max_sun_deg)
    try:
        sessions = open_catalog(settings)
        with working("photogrammetry on the catalogued images"):
            number = photogrammetry_version(sessions, data_dir=settings.data_dir, config=config)
    except (LookupError, ValueError) as exc:
        typer.echo(str(exc), err=True)
        raise typer.Exit(1) from None
    typer.echo(f"published version {number} (photogrammetric)")
