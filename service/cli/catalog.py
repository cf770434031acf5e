"""Catalog commands: ingest a downlink and query images, maplets and coverage."""

from __future__ import annotations

from pathlib import Path
from typing import Literal, cast

import typer

from service.cli.app import (
    LATITUDE,
    LONGITUDE,
    MAX_ROW_ID,
    app,
    echo_json,
    echo_rejected,
    exit_status,
    finite,
    refinement_config,
    setup_logging,
)


@app.command()
def ingest(
    directory: Path = typer.Argument(..., exists=True, file_okay=False,
                                     help="a downlink directory (PDS4 labels, SPICE kernels)"),
    shape: Path | None = typer.Option(None, exists=True, dir_okay=False,
                                      help="current shape model for boresight intercepts and maplet coverage "
                                           "(.obj/.ply, km); default: the PCK ellipsoid, no coverage"),
    name: str | None = typer.Option(None, help="downlink name (default: the directory name)"),
    maplet_nodes: int | None = typer.Option(None,
                                            help="nodes per side of maplets tiled where the images look and no maplet "
                                                 "is catalogued yet (with --shape); default PWM_MAPLET_NODES"),
    verbose: bool = typer.Option(False, "--verbose", "-v"),
) -> None:
    """Catalogue a downlink: kernels first, then every PDS4 product, accepted or rejected with a reason.

    Idempotent. The exit status is the number of files that failed (capped at 100); 0 means all went in.
    """
    from pwm.io.meshio import read_mesh
    from service.catalog import open_catalog
    from service.cli.progress import progress_bar
    from service.conductor import weigh
    from service.ingest import IngestTakenOver, ingest_directory
    from service.settings import get_settings

    setup_logging(verbose)
    settings = get_settings()
    config = refinement_config(settings.refinement(), nodes=maplet_nodes)
    sessions = open_catalog(settings)
    model = read_mesh(shape) if shape else None
    try:
        with progress_bar(unit="products") as progress:
            report = ingest_directory(sessions, directory, downlink_name=name, shape=model, progress=progress)
    except IngestTakenOver as exc:  # the other ingest finishes the downlink
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(1) from None
    if model is not None:  # no pose adjustment here: the poses the kernels give are final
        weigh(sessions, model, config=config)
    echo_rejected(report.failures)
    typer.echo(report.summary())
    raise typer.Exit(exit_status(report.failed))


@app.command()
def images(
    status: str | None = typer.Option(None, help="accepted | rejected | conflict"),
    limit: int = typer.Option(50, min=1, max=MAX_ROW_ID, help="at most this many rows"),
) -> None:
    """List catalogued images: LIDVID, status, time, range and angles at the boresight intercept,
    and the pose correction photogrammetry stored (offset m, rotation microradians)."""
    import math

    from sqlalchemy import select

    from pwm.spg.uncertainty import determined
    from service.catalog import open_catalog
    from service.rows import Image

    with open_catalog()() as session:
        query = select(Image).order_by(Image.start_utc, Image.id).limit(limit)
        if status:
            query = query.where(Image.status == status)
        typer.echo(f"{'LIDVID':<60} {'status':<8} {'start (UTC)':<23} {'range km':>9} {'inc':>5} {'emi':>5} "
                   f"{'pha':>5}  pose correction, or why no geometry")
        for image in session.scalars(query):
            g = image.geometry
            angles = g is not None and g.incidence_deg is not None
            where = (f"{g.range_km:>9.3f} {g.incidence_deg:>5.1f} {g.emission_deg:>5.1f} {g.phase_deg:>5.1f}"
                     if g is not None and angles else f"{'-':>9} {'-':>5} {'-':>5} {'-':>5}")
            note = "" if angles else (image.rejection_reason or image.geometry_unavailable_reason or "")
            stored = image.pose_correction()
            corrected = ("" if stored is None else f"corrected {math.hypot(*stored.position_km) * 1e3:.2f} m, "
                                                   f"{math.hypot(*stored.rotation_rad) * 1e6:.0f} urad")
            sigmas = image.pose_sigmas()
            if sigmas is not None:
                prior, posterior = sigmas
                corrected += (f"  sigma: line of sight {prior.los_px:.1f}>{posterior.los_px:.1f} px, lateral "
                              f"{prior.lateral_m:.2f}>{posterior.lateral_m:.2f} m, pointing "
                              f"{prior.pointing_urad:.0f}>{posterior.pointing_urad:.0f} urad "
                              f"(determined: {', '.join(determined(prior, posterior)) or 'none'})")
            start = image.start_utc.strftime("%Y-%m-%dT%H:%M:%S.%f")[:23] if image.start_utc is not None else "-"
            typer.echo(f"{image.lidvid:<60} {image.status:<8} {start:<23} {where}  "
                       f"{'  '.join(filter(None, (note, corrected))) or '-'}")


@app.command()
def images_near(
    lat: float = typer.Option(..., parser=LATITUDE, help="planetocentric latitude of the surface point, deg"),
    lon: float = typer.Option(..., parser=LONGITUDE, help="east longitude of the surface point, deg"),
    radius_km: float = typer.Option(0.0, parser=finite(ge=0.0),
                                    help="also through maplets within this distance of the point, km"),
    order: str = typer.Option("weight", help="weight (highest first) | time (earliest first)"),
    limit: int = typer.Option(50, min=1, max=MAX_ROW_ID, help="at most this many rows"),
    json_out: bool = typer.Option(False, "--json", help="print JSON instead of a table"),
) -> None:
    """Images that see a surface point, through the maplets that hold it: each image once, with its angles there."""
    from service.catalog import open_catalog
    from service.queries import images_covering

    if order not in ("weight", "time"):
        raise typer.BadParameter("expected weight or time", param_hint="--order")
    with open_catalog()() as session:
        hits = images_covering(session, lat_deg=lat, lon_deg=lon, radius_km=radius_km,
                               order=cast(Literal["weight", "time"], order), limit=limit)
    if json_out:
        echo_json([h.model_dump(mode="json") for h in hits])
        return
    typer.echo(f"{'LIDVID':<60} {'start (UTC)':<23} {'maplet':<20} {'weight':>6} {'inc':>5} {'emi':>5} {'pha':>5} "
               f"{'vis':>5} {'m/px':>6}  role")
    for h in hits:
        start = h.start_utc.strftime("%Y-%m-%dT%H:%M:%S.%f")[:23] if h.start_utc else "-"
        typer.echo(f"{h.lidvid:<60} {start:<23} {h.maplet:<20} {h.weight:>6.3f} {h.incidence_deg:>5.1f} "
                   f"{h.emission_deg:>5.1f} "
                   f"{h.phase_deg:>5.1f} {h.visible_fraction:>5.2f} {h.resolution_m_per_px:>6.3f}  {h.role or '-'}")
    typer.echo(f"{len(hits)} images")


@app.command()
def maplets(
    lat: float | None = typer.Option(None, parser=LATITUDE, help="only maplets holding this latitude (deg) ..."),
    lon: float | None = typer.Option(None, parser=LONGITUDE, help="... and east longitude (deg), nearest first"),
    radius_km: float = typer.Option(0.0, parser=finite(ge=0.0), help="or within this distance of that point, km"),
    level: int | None = typer.Option(
        None, min=-64, max=64, help="only maplets of this level: node spacings within a factor sqrt(2) of 2^level m"),
    limit: int = typer.Option(50, min=1, max=MAX_ROW_ID, help="at most this many rows"),
    offset: int = typer.Option(0, min=0, max=MAX_ROW_ID, help="skip this many rows first"),
    json_out: bool = typer.Option(False, "--json", help="print JSON instead of a table"),
) -> None:
    """List maplets by name, or those at a surface point: centre, size, spacing and level, region weight,
    revision, images that see them."""
    from service.catalog import open_catalog
    from service.queries import list_maplets

    if (lat is None) != (lon is None):
        raise typer.BadParameter("give --lat and --lon together")
    with open_catalog()() as session:
        rows = list_maplets(session, lat_deg=lat, lon_deg=lon, radius_km=radius_km, level=level, limit=limit,
                            offset=offset)
    if json_out:
        echo_json([m.model_dump(mode="json") for m in rows])
        return
    typer.echo(f"{'maplet':<24} {'lat':>8} {'lon':>8} {'size m':>7} {'gsd m':>6} {'level':>5} {'nodes':>5} "
               f"{'w_PWM':>6} {'rev':>4} {'images':>6} {'dist m':>7}")
    for m in rows:
        distance = "-" if m.distance_km is None else f"{m.distance_km * 1e3:.2f}"
        typer.echo(f"{m.name:<24} {m.center_lat_deg:>8.3f} {m.center_lon_deg:>8.3f} {m.size_km * 1e3:>7.2f} "
                   f"{m.gsd_m:>6.3f} {m.level:>5} {m.nodes_per_side:>5} "
                   f"{m.region_weight:>6.3f} {m.current_revision if m.current_revision is not None else '-':>4} "
                   f"{m.image_count:>6} {distance:>7}")


@app.command()
def coverage(
    maplet: str = typer.Argument(..., help="maplet name, or its id (all digits)"),
    json_out: bool = typer.Option(False, "--json", help="print JSON instead of a table"),
) -> None:
    """How well a maplet's images cover it: counts, incidence and emission ranges, Sun azimuth spread, the five
    views."""
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
        echo_json(summary.model_dump(mode="json"))
        return

    def extent(values: tuple[float, float] | None) -> str:
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
