"""Commands on files, without the catalog: simulate a downlink, refine a model, evaluate it."""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import TYPE_CHECKING

import typer

from pwm.config import DEFAULTS
from service.cli.app import (
    BODY_FRAME,
    INSTRUMENT,
    LATITUDE,
    LONGITUDE,
    TARGET,
    app,
    downlink_report,
    downlink_views,
    finite,
    refinement_config,
    setup_logging,
)

if TYPE_CHECKING:
    import numpy as np

    from pwm.knowledge import KnowledgeErrors
    from pwm.lidar.shots import Shots
    from pwm.maplets import Spots
    from pwm.mesh import Mesh


def _knowledge_error(value: str | None) -> KnowledgeErrors:
    from pwm.knowledge import IndependentErrors, parse_knowledge_errors

    if value is None:
        return IndependentErrors()
    try:
        return parse_knowledge_errors(value)
    except ValueError as exc:
        raise typer.BadParameter(str(exc), param_hint="--knowledge-error") from None


def _start_error(value: str) -> dict:
    """RMS_GSD[,SHORTEST_M,LONGEST_M] as the scenario's start-error fields."""
    expected = "expected RMS_GSD or RMS_GSD,SHORTEST_M,LONGEST_M, finite and >= 0, e.g. 1.0,10,40"
    parse = finite(ge=0.0)
    try:
        numbers = [parse(x) for x in value.split(",")]
    except typer.BadParameter:
        raise typer.BadParameter(expected, param_hint="--start-error") from None
    if len(numbers) not in (1, 3):
        raise typer.BadParameter(expected, param_hint="--start-error")
    fields: dict = {"start_error_rms_gsd": numbers[0]}
    if len(numbers) == 3:
        fields["start_error_band_m"] = (numbers[1], numbers[2])
    return fields


@app.command()
def simulate(
    out: Path = typer.Argument(..., help="output directory (downlink/ and truth/ are written in it)"),
    scenario: str = typer.Option("tiny", help="tiny | ryugu-tiny | site | site-hard | site-polar | global-coarse "
                                              "| global-tiny | castalia-survey | castalia-tiny | eros-survey | "
                                              "eros-tiny; or a campaign of downlinks in time order under "
                                              "OUT/downlinks/: campaign | campaign-tiny | campaign-castalia | "
                                              "campaign-eros"),
    seed: int = typer.Option(0, min=0, help="random seed: the same seed gives the same products"),
    knowledge_error: str | None = typer.Option(
        None, help="errors of the kernels' poses (the images are rendered from the truth). POS_M,POINT_RAD: "
                   "independent per image, 1 sigma per axis, position (m) and pointing (rad); "
                   "nav:ALONG_M,CROSS_M,MISALIGN_URAD,DRIFT_URAD (e.g. nav:3,1,50,20): navigation-like, smooth "
                   "over each arc of images, RMS along-track and cross-track (m), one camera misalignment and a "
                   "pointing drift over the downlink (microradians)"),
    photometry: str | None = typer.Option(None, help="the truth's reflectance law: mcewen (the solver's), "
                                                     "lunar-lambert-slow or hapke (default: the scenario's)"),
    supersample: int | None = typer.Option(None, min=1, help="rays per pixel along each axis, averaged"),
    psf_px: float | None = typer.Option(None, parser=finite(), help="Gaussian point-spread function sigma, pixels"),
    smear_px: float | None = typer.Option(None, parser=finite(), help="motion smear length, pixels"),
    flat_field: float | None = typer.Option(None, parser=finite(),
                                            help="relative RMS of the flat-field residual, e.g. 0.01"),
    start_error: str | None = typer.Option(None, help="RMS_GSD[,SHORTEST_M,LONGEST_M]: smooth undulations added "
                                                      "to the start model (default band 10-40 m)"),
    with_start_model: bool = typer.Option(False, "--with-start-model",
                                          help="put a start model into the downlink (start_model.obj), as an "
                                               "earlier campaign would leave it; without it, the downlink comes "
                                               "with no shape model, as a mission's first ones do"),
    verbose: bool = typer.Option(False, "--verbose", "-v"),
) -> None:
    """Simulate a mission downlink (PDS4 images, SPICE kernels, and with --with-start-model a start
    model) from a truth asteroid, or a campaign's downlinks of one; the options change the
    scenarios' photometry, camera and start-model error."""
    from pydantic import ValidationError

    from pwm.simulate.campaign import simulate as run_simulation, simulate_campaign
    from pwm.simulate.scenarios import CAMPAIGNS, Scenario, get_scenario
    from service.cli.progress import working

    setup_logging(verbose)
    errors = _knowledge_error(knowledge_error)
    campaign = CAMPAIGNS.get(scenario)
    try:
        parts = campaign.downlinks if campaign is not None else [get_scenario(scenario)]
    except ValueError as exc:
        raise typer.BadParameter(f"{exc}, or a campaign: {', '.join(CAMPAIGNS)}") from None
    changes: dict = {"photometry": photometry, "supersample": supersample}
    optics = {"psf_sigma_px": psf_px, "smear_px": smear_px, "flat_field_rms": flat_field}
    if start_error is not None:
        changes |= _start_error(start_error)

    def changed(sc: Scenario) -> Scenario:
        fields = {**changes, "optics": {**sc.optics.model_dump(), **{k: v for k, v in optics.items() if v is not None}}}
        return Scenario.model_validate({**sc.model_dump(), **{k: v for k, v in fields.items() if v is not None}})

    try:
        parts = [changed(sc) for sc in parts]
    except ValidationError as exc:
        raise typer.BadParameter("; ".join(": ".join(filter(None, (".".join(map(str, e["loc"])), e["msg"])))
                                           for e in exc.errors())) from None
    if campaign is None:
        with working(f"simulating {scenario}"):
            manifest = run_simulation(out, scenario=parts[0], seed=seed, knowledge=errors,
                                      with_start_model=with_start_model)
        typer.echo(f"{manifest['image_count']} images, GSD {manifest['gsd_m']:.3f} m -> {out}")
        return
    campaign = campaign.model_copy(update={"survey": parts[0], "sites": tuple(parts[1:])})
    with working(f"simulating the {len(parts)} downlinks of {scenario}"):
        summary = simulate_campaign(out, campaign=campaign, seed=seed, knowledge=errors,
                                    with_start_model=with_start_model)
    for entry in summary["downlinks"]:
        typer.echo(f"{entry['downlink']}: {entry['images']} images, GSD {entry['gsd_m']:.3f} m "
                   f"({entry['scope']}; truth in {entry['truth']})")


@app.command()
def evaluate(
    model: Path = typer.Argument(..., exists=True, dir_okay=False, help="model mesh (.obj or .ply, km, body-fixed)"),
    truth: Path | None = typer.Option(None, exists=True, file_okay=False,
                                      help="the simulation's truth/ directory (needed unless --lidar is given)"),
    lidar: Path | None = typer.Option(None, exists=True, file_okay=False,
                                      help="a directory of lidar products with its kernels (one meta-kernel): the "
                                           "spots' distances to MODEL, overall, per track and on a 10-degree map"),
    json_out: Path | None = typer.Option(None, "--json", help="write the figures as JSON here"),
    plots: Path | None = typer.Option(None, help="write PNG plots (height error, classes, profiles, views) here"),
    maplets: Path | None = typer.Option(None, exists=True, dir_okay=False,
                                        help="maplets.json of the `pwm refine` that made MODEL: the error at "
                                             "maplet edges too"),
    scope: str | None = typer.Option(None, help="site (the site disc of a site downlink's truth) | global (the "
                                                "whole body against a survey's truth); default: the truth's own"),
    verbose: bool = typer.Option(False, "--verbose", "-v"),
) -> None:
    """Measure a model against the truth: ICP, RMS and median error, NCC/SSIM, boulder heights;
    for a site, the error by wavelength band and where it lies (walls, rims, maplet edges,
    shadow, elsewhere); for the whole body, the coverage of the true surface. With --lidar, or
    instead: against laser altimetry, the mean, RMS and 95th percentile of the spots' distances
    to the model (no catalog needed)."""
    from pwm.evaluate.report import evaluate as run_evaluation, format_table, maplet_footprints

    setup_logging(verbose)
    if truth is None and lidar is None:
        raise typer.BadParameter("give --truth, --lidar or both")
    result: dict = {}
    if lidar is not None:
        result["lidar"] = _lidar_figures(model, lidar)
    if truth is None:
        if json_out is not None:
            json_out.parent.mkdir(parents=True, exist_ok=True)
            json_out.write_text(json.dumps(result, indent=2))
        return
    footprints = None
    if maplets is not None:
        try:
            footprints = maplet_footprints(json.loads(maplets.read_text()))
        except (ValueError, KeyError, TypeError) as exc:
            raise typer.BadParameter(f"{maplets}: not a maplets.json of pwm refine ({exc})",
                                     param_hint="--maplets") from None
    try:
        result = run_evaluation(model, truth_dir=truth, plots_dir=plots, maplets=footprints, scope=scope) | result
    except ValueError as exc:
        raise typer.BadParameter(str(exc)) from None
    typer.echo(format_table(result))
    if json_out is not None:
        json_out.parent.mkdir(parents=True, exist_ok=True)
        json_out.write_text(json.dumps(result, indent=2))


def _lidar_figures(model: Path, directory: Path) -> dict:
    """The lidar statistics of a mesh against a directory's lidar products (printed as well)."""
    from pwm.io.meshio import read_mesh
    from pwm.lidar.model import residual_summary
    from service.cli.versions import lidar_lines

    shots, tracks, products = _lidar_shots(directory)
    figures = residual_summary(shots, read_mesh(model), tracks)
    typer.echo(f"lidar: {products} products:")
    for line in lidar_lines(figures):
        typer.echo(line)
    return figures


def _lidar_shots(directory: Path) -> tuple[Shots, np.ndarray, int]:
    """The shots of a directory's lidar products placed through its kernels, joined, each shot's
    track (each product's numbered after the previous one's) and how many products; those it
    skipped are said on stderr. A bad directory or product set is a bad --lidar."""
    import numpy as np

    from pwm.io.lidar import read_lidar_directory
    from pwm.lidar.shots import Shots
    from pwm.lidar.tracks import NO_TRACK, track_ids

    try:
        products, skipped = read_lidar_directory(directory)
    except ValueError as exc:
        raise typer.BadParameter(str(exc), param_hint="--lidar") from None
    for label, why in skipped:
        typer.echo(f"skipped {label}: {why}", err=True)
    tracks, offset = [], 0
    for product in products:  # each product's tracks numbered after the previous one's
        ids = track_ids(product.shots)
        tracks.append(np.where(ids == NO_TRACK, NO_TRACK, ids + offset))
        offset += int(ids.max(initial=-1)) + 1
    try:
        shots = Shots.joined([p.shots for p in products])
    except ValueError as exc:
        raise typer.BadParameter(str(exc), param_hint="--lidar") from None
    return shots, np.concatenate(tracks), len(products)


def _strip_adjusted_spots(directory: Path, start: Mesh) -> Spots:
    """A directory's lidar spots with each track strip-adjusted to the start model, as the
    catalog's lidar stage adjusts a downlink's (pwm.lidar.strips.adjust, the model kept), with
    their sigmas (pwm.lidar.strips.corrected_spots)."""
    from pwm.lidar.strips import adjust, corrected_spots
    from pwm.maplets import Spots

    shots, _, products = _lidar_shots(directory)
    adjustment = adjust(shots, start, rebuild=False)
    body, sigma = corrected_spots(shots, adjustment.track, adjustment.corrections)
    logging.getLogger("pwm").info("lidar: %d products, %d tracks strip-adjusted to the start model, %d spots",
                                  products, len(adjustment.corrections), len(sigma))
    return Spots(body_km=body, sigma_km=sigma)


@app.command()
def refine(
    downlink: Path = typer.Argument(..., exists=True, file_okay=False,
                                    help="a downlink directory (PDS4 images, kernels with one meta-kernel)"),
    start: Path = typer.Option(..., exists=True, dir_okay=False,
                               help="starting shape model (.obj/.ply, km, body-fixed)"),
    out: Path = typer.Option(..., help="output directory: refined.ply (with albedo), refined.obj, maplets.json"),
    mode: str = typer.Option(DEFAULTS.mode, help="pwm (pixel and region weights) | standard (weights off)"),
    lat: float | None = typer.Option(None, parser=LATITUDE,
                                     help="region centre latitude, deg (default: where the images look)"),
    lon: float | None = typer.Option(None, parser=LONGITUDE, help="region centre east longitude, deg"),
    radius_km: float | None = typer.Option(None, "--radius-km", parser=finite(gt=0.0),
                                           help="region radius, km"),
    nodes: int = typer.Option(DEFAULTS.nodes, help="maplet nodes per side"),
    spacing_gsd: float = typer.Option(DEFAULTS.spacing_gsd, parser=finite(),
                                      help="node spacing in image GSDs (median pixel scale)"),
    overlap: float = typer.Option(DEFAULTS.overlap, parser=finite(),
                                  help="fraction of a maplet shared with each neighbour"),
    workers: int = typer.Option(2, min=1, help="processes refining maplets in parallel"),
    passes: int = typer.Option(DEFAULTS.passes,
                               help="refinement passes every maplet gets; each later one re-tiles the previous "
                                    "pass's fused model"),
    max_passes: int = typer.Option(DEFAULTS.max_passes,
                                   help="at most this many passes for a maplet whose last pass still changed it "
                                        "(never fewer than --passes)"),
    search_px: float = typer.Option(DEFAULTS.search_px, parser=finite(),
                                    help="how far images may be off the maplets (px), from the pose knowledge"),
    corrections: Path | None = typer.Option(None, exists=True, dir_okay=False,
                                            help="pose corrections to apply (corrections.json of pwm spg)"),
    lidar: Path | None = typer.Option(None, exists=True, file_okay=False,
                                      help="a directory of lidar products with its kernels (one meta-kernel): their "
                                           "tracks strip-adjusted to the start model, their spots place and refine "
                                           "the maplets they fall on"),
    instrument: str | None = INSTRUMENT,
    target: str | None = TARGET,
    body_frame: str | None = BODY_FRAME,
    verbose: bool = typer.Option(False, "--verbose", "-v"),
) -> None:
    """Refine a start model with a downlink's images, and a lidar's ranges where given: tile, weigh,
    photoclinometry, fuse."""
    import dataclasses
    import time

    from pwm.io.meshio import read_mesh, write_obj, write_ply
    from pwm.pipeline import imaged_region, refine_region
    from service.cli.progress import progress_bar
    from service.cli.spg import read_corrections

    setup_logging(verbose)
    config = refinement_config(mode=mode, nodes=nodes, spacing_gsd=spacing_gsd, overlap=overlap, passes=passes,
                               max_passes=max_passes, search_px=search_px)
    clock = time.perf_counter()
    read = downlink_views(downlink, instrument=instrument, target=target, body_frame=body_frame,
                          corrections=None if corrections is None else read_corrections(corrections))
    views = read.views
    start_model = read_mesh(start)
    region = imaged_region(views, start_model)
    if lat is not None and lon is not None:
        region = dataclasses.replace(region, lat_deg=lat, lon_deg=lon)
    if radius_km is not None:
        region = dataclasses.replace(region, radius_km=radius_km)
    region = dataclasses.replace(region, spacing_km=config.spacing_gsd * region.spacing_km)
    logging.getLogger("pwm").info("%d images, maplets at %.3f m around (%.3f, %.3f) within %.1f m", len(views),
                                  region.spacing_km * 1e3, region.lat_deg, region.lon_deg, region.radius_km * 1e3)
    spots = None if lidar is None else _strip_adjusted_spots(lidar, start_model)
    with progress_bar() as progress:
        model, results = refine_region(start_model, views, region, config=config, workers=workers, progress=progress,
                                       spots=spots)
    out.mkdir(parents=True, exist_ok=True)
    write_ply(out / "refined.ply", model)
    write_obj(out / "refined.obj", model)
    report = {"mode": mode, "passes": passes, "max_passes": config.most_passes,
              "region": dataclasses.asdict(region), "images": len(views),
              **downlink_report(read), "seconds": time.perf_counter() - clock,
              "maplets": [{"name": r.maplet.name, "origin_km": r.maplet.frame.origin.tolist(),
                           "rotation": r.maplet.frame.rotation.tolist(), "half_km": float(r.maplet.axis_km[-1]),
                           "images": r.images, "region_weight": r.region_weight,
                           "five_views": r.five_views,
                           "dropped": r.dropped, "iterations": r.iterations, "converged": r.converged,
                           "residual_rms": r.residual_rms, "seconds": r.seconds, "lidar_spots": r.lidar_spots,
                           "lidar_rms_sigmas": r.lidar_rms if r.lidar_spots else None} for r in results]}
    (out / "maplets.json").write_text(json.dumps(report, indent=1))
    typer.echo(f"{len(results)} maplets refined from {len(views)} images in {report['seconds']:.1f} s -> {out}")
