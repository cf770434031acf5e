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
def refine(
    downlink: Path = typer.Argument(..., exists=True, file_okay=False, help="a downlink directory (PDS4 images, kernels with one meta-kernel)"),
    start: Path = typer.Option(..., exists=True, dir_okay=False, help="starting shape model (.obj/.ply, km, body-fixed)"),
    out: Path = typer.Option(..., help="output directory: refined.ply (with albedo), refined.obj, maplets.json"),
    mode: str = typer.Option("pwm", help="pwm (pixel and region weights) | standard (weights off)"),
    lat: Optional[float] = typer.Option(None, help="region centre latitude, deg (default: where the images look)"),
    lon: Optional[float] = typer.Option(None, help="region centre east longitude, deg"),
    radius: Optional[float] = typer.Option(None, min=0.0, help="region radius, km"),
    nodes: int = typer.Option(100, min=8, help="maplet nodes per side"),
    overlap: float = typer.Option(0.25, min=0.0, max=0.75, help="fraction of a maplet shared with each neighbour"),
    workers: int = typer.Option(2, min=1, help="processes refining maplets in parallel"),
    instrument: int = typer.Option(-64361, help="NAIF id of the camera"),
    target: str = typer.Option("BENNU"),
    body_frame: str = typer.Option("IAU_BENNU"),
    verbose: bool = typer.Option(False, "--verbose", "-v"),
) -> None:
    """Refine a start model with a downlink's images: tile, weigh, photoclinometry, fuse."""
    import dataclasses
    import time

    from pwm.io.downlink import read_views
    from pwm.io.meshio import read_mesh, write_obj, write_ply
    from pwm.pipeline import fuse, imaged_region, refine_maplets
    from pwm.tiling import tile

    _logging(verbose)
    if mode not in ("pwm", "standard"):
        raise typer.BadParameter("mode is pwm or standard")
    clock = time.perf_counter()
    views = read_views(downlink, instrument_id=instrument, target=target, body_frame=body_frame)
    start_model = read_mesh(start)
    region = imaged_region(views, start_model)
    if lat is not None and lon is not None:
        region = dataclasses.replace(region, lat_deg=lat, lon_deg=lon)
    if radius is not None:
        region = dataclasses.replace(region, radius_km=radius)
    maplets = tile(start_model, spacing_km=region.spacing_km, nodes=nodes, overlap=overlap, centre_lat_deg=region.lat_deg,
                   centre_lon_deg=region.lon_deg, radius_km=region.radius_km)
    logging.getLogger("pwm").info("%d images, %d maplets of %d nodes at %.3f m around (%.3f, %.3f) within %.1f m",
                                  len(views), len(maplets), nodes, region.spacing_km * 1e3, region.lat_deg, region.lon_deg, region.radius_km * 1e3)
    results = refine_maplets(maplets, views, start_model, mode=mode, workers=workers)
    model, _ = fuse([r.maplet for r in results], start_model, overlap=overlap)
    out.mkdir(parents=True, exist_ok=True)
    write_ply(out / "refined.ply", model)
    write_obj(out / "refined.obj", model)
    report = {"mode": mode, "region": dataclasses.asdict(region), "images": len(views), "seconds": time.perf_counter() - clock,
              "maplets": [{"name": r.maplet.name, "images": r.images, "region_weight": r.region_weight, "five_views": r.five_views,
                           "dropped": r.dropped, "iterations": r.iterations, "converged": r.converged,
                           "residual_rms": r.residual_rms, "seconds": r.seconds} for r in results]}
    (out / "maplets.json").write_text(json.dumps(report, indent=1))
    typer.echo(f"{len(results)} maplets refined from {len(views)} images in {report['seconds']:.1f} s -> {out}")


@app.command()
def ingest(
    directory: Path = typer.Argument(..., exists=True, file_okay=False, help="a downlink directory (PDS4 labels, SPICE kernels)"),
    shape: Optional[Path] = typer.Option(None, exists=True, dir_okay=False, help="current shape model for boresight intercepts and maplet coverage (.obj/.ply, km); default: the PCK ellipsoid, no coverage"),
    name: Optional[str] = typer.Option(None, help="downlink name (default: the directory name)"),
    maplet_nodes: int = typer.Option(100, min=8, help="nodes per side of maplets tiled where the images look and no maplet is catalogued yet (with --shape)"),
    verbose: bool = typer.Option(False, "--verbose", "-v"),
) -> None:
    """Catalogue a downlink: kernels first, then every PDS4 product, accepted or rejected with a reason.

    Idempotent. The exit status is the number of files that failed (capped at 100); 0 means all went in.
    """
    from pwm.io.meshio import read_mesh
    from service.catalog import open_catalog
    from service.ingest import ingest_directory

    _logging(verbose)
    report = ingest_directory(open_catalog(), directory, downlink_name=name, shape=read_mesh(shape) if shape else None,
                              maplet_nodes=maplet_nodes)
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


def _json(value: object) -> None:
    typer.echo(json.dumps(value, indent=2))


@app.command()
def images_near(
    lat: float = typer.Option(..., min=-90.0, max=90.0, help="planetocentric latitude of the surface point, deg"),
    lon: float = typer.Option(..., help="east longitude of the surface point, deg"),
    radius: float = typer.Option(0.0, min=0.0, help="also through maplets within this distance of the point, km"),
    order: str = typer.Option("weight", help="weight (highest first) | time (earliest first)"),
    limit: int = typer.Option(50, min=1, help="at most this many rows"),
    json_out: bool = typer.Option(False, "--json", help="print JSON instead of a table"),
) -> None:
    """Images that see a surface point, through the maplets that hold it: each image once, with its angles there."""
    from service.catalog import open_catalog
    from service.queries import images_covering

    if order not in ("weight", "time"):
        raise typer.BadParameter("expected weight or time", param_hint="--order")
    with open_catalog()() as session:
        hits = images_covering(session, lat_deg=lat, lon_deg=lon, radius_km=radius, order=order, limit=limit)
    if json_out:
        _json([h.model_dump(mode="json") for h in hits])
        return
    typer.echo(f"{'LIDVID':<60} {'start (UTC)':<23} {'maplet':<20} {'weight':>6} {'inc':>5} {'emi':>5} {'pha':>5} {'vis':>5} {'m/px':>6}  role")
    for h in hits:
        start = h.start_utc.strftime("%Y-%m-%dT%H:%M:%S.%f")[:23] if h.start_utc else "-"
        typer.echo(f"{h.lidvid:<60} {start:<23} {h.maplet:<20} {h.weight:>6.3f} {h.incidence_deg:>5.1f} {h.emission_deg:>5.1f} "
                   f"{h.phase_deg:>5.1f} {h.visible_fraction:>5.2f} {h.resolution_m_per_px:>6.3f}  {h.role or '-'}")
    typer.echo(f"{len(hits)} images")


@app.command()
def maplets(
    lat: Optional[float] = typer.Option(None, min=-90.0, max=90.0, help="only maplets holding this latitude (deg) ..."),
    lon: Optional[float] = typer.Option(None, help="... and east longitude (deg), nearest first"),
    radius: float = typer.Option(0.0, min=0.0, help="or within this distance of that point, km"),
    limit: int = typer.Option(50, min=1, help="at most this many rows"),
    offset: int = typer.Option(0, min=0, help="skip this many rows first"),
    json_out: bool = typer.Option(False, "--json", help="print JSON instead of a table"),
) -> None:
    """List maplets by name, or those at a surface point: centre, size, region weight, revision, images that see them."""
    from service.catalog import open_catalog
    from service.queries import list_maplets

    if (lat is None) != (lon is None):
        raise typer.BadParameter("give --lat and --lon together")
    with open_catalog()() as session:
        rows = list_maplets(session, lat_deg=lat, lon_deg=lon, radius_km=radius, limit=limit, offset=offset)
    if json_out:
        _json([m.model_dump(mode="json") for m in rows])
        return
    typer.echo(f"{'maplet':<20} {'lat':>8} {'lon':>8} {'size m':>7} {'gsd m':>6} {'nodes':>5} {'w_PWM':>6} {'rev':>4} {'images':>6} {'dist m':>7}")
    for m in rows:
        distance = "-" if m.distance_km is None else f"{m.distance_km * 1e3:.2f}"
        typer.echo(f"{m.name:<20} {m.center_lat_deg:>8.3f} {m.center_lon_deg:>8.3f} {m.size_km * 1e3:>7.2f} {m.gsd_m:>6.3f} {m.nodes_per_side:>5} "
                   f"{m.region_weight:>6.3f} {m.current_revision if m.current_revision is not None else '-':>4} {m.image_count:>6} {distance:>7}")


@app.command()
def coverage(
    maplet: str = typer.Argument(..., help="maplet name, or its id (all digits)"),
    json_out: bool = typer.Option(False, "--json", help="print JSON instead of a table"),
) -> None:
    """How well a maplet's images cover it: counts, incidence and emission ranges, Sun azimuth spread, the five views."""
    from service.catalog import open_catalog
    from service.queries import maplet_coverage

    with open_catalog()() as session:
        try:
            summary = (maplet_coverage(session, maplet_id=int(maplet)) if maplet.isdigit()
                       else maplet_coverage(session, name=maplet))
        except LookupError as exc:
            typer.echo(str(exc), err=True)
            raise typer.Exit(1) from None
    if json_out:
        _json(summary.model_dump(mode="json"))
        return

    def extent(values: Optional[tuple[float, float]]) -> str:
        return "-" if values is None else f"{values[0]:.1f} to {values[1]:.1f} deg"

    spread = "-" if summary.sun_azimuth_spread_deg is None else f"{summary.sun_azimuth_spread_deg:.1f} deg"
    revision = "none" if summary.current_revision is None else str(summary.current_revision)
    rows = [("maplet", f"{summary.maplet} (id {summary.maplet_id})"),
            ("images", f"{summary.image_count} see it, {summary.used_count} weighted"),
            ("incidence", extent(summary.incidence_deg)), ("emission", extent(summary.emission_deg)),
            ("Sun azimuth spread", spread), ("region weight", f"{summary.region_weight:.3f}"),
            ("current revision", revision), ("five views", "yes" if summary.five_views else "no"),
            *((f"  {role}", lidvid or "missing") for role, lidvid in summary.views.items())]
    for name, value in rows:
        typer.echo(f"{name:<20}{value}")


if __name__ == "__main__":
    app()
