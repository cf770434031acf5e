"""Model version commands: run a downlink through to a new version, import a model, list, show and
compare versions."""

from __future__ import annotations

from pathlib import Path

import typer

from service.cli.app import (
    HELP_MARKUP,
    MAX_ROW_ID,
    app,
    echo_json,
    echo_rejected,
    exit_status,
    finite,
    refinement_config,
    setup_logging,
    version_ref,
)

version_app = typer.Typer(help="One model version.", no_args_is_help=True, rich_markup_mode=HELP_MARKUP)
app.add_typer(version_app, name="version")


@app.command()
def run(
    directory: Path = typer.Argument(..., exists=True, file_okay=False,
                                     help="a downlink directory (PDS4 labels, SPICE kernels)"),
    start: Path | None = typer.Option(None, exists=True, dir_okay=False,
                                      help="start model (km, any format pwm exports) when the catalog has no "
                                           "version yet; default DIR/start_model.obj"),
    mode: str | None = typer.Option(None,
                                    help="pwm (pixel and region weights) | standard (weights off); default "
                                         "PWM_REFINE_MODE"),
    workers: int = typer.Option(1, min=1, help="processes refining maplets in parallel"),
    passes: int | None = typer.Option(None, help="refinement passes, each fused into a version of its own; "
                                                 "default PWM_REFINE_PASSES"),
    max_passes: int | None = typer.Option(None, help="at most this many passes for a maplet whose last pass still "
                                                     "changed it (never fewer than --passes); default "
                                                     "PWM_REFINE_MAX_PASSES"),
    maplet_nodes: int | None = typer.Option(None,
                                            help="nodes per side of maplets tiled where the images look and none is "
                                                 "catalogued; default PWM_MAPLET_NODES"),
    tile_radius_km: float | None = typer.Option(None, "--tile-radius-km", parser=finite(gt=0.0),
                                                help="radius (km) of the region tiled about where the images look; "
                                                     "default PWM_TILE_RADIUS_KM, else from their footprints"),
    verbose: bool = typer.Option(False, "--verbose", "-v"),
) -> None:
    """Ingest a downlink, refine the maplets whose images changed, and publish a new model version per pass, in this
    process.

    The exit status is the number of files that failed (capped at 100), as `pwm ingest` gives it.
    """
    from service.catalog import open_catalog
    from service.cli.progress import progress_bar
    from service.ingest import IngestTakenOver
    from service.run import run_directory
    from service.settings import get_settings

    setup_logging(verbose)
    settings = get_settings()
    config = refinement_config(settings.refinement(), mode=mode, passes=passes, max_passes=max_passes,
                               nodes=maplet_nodes, tile_radius_km=tile_radius_km)
    try:
        with progress_bar() as progress:
            report = run_directory(open_catalog(settings), directory, data_dir=settings.data_dir, start=start,
                                   config=config, workers=workers,
                                   refine_on_config_change=settings.refine_on_config_change, progress=progress)
    except (FileNotFoundError, IngestTakenOver) as exc:
        typer.echo(str(exc), err=True)
        raise typer.Exit(1) from None
    echo_rejected(report.plan.ingest.failures)
    typer.echo(report.summary())
    raise typer.Exit(exit_status(report.plan.ingest.failed))


@app.command(name="import")
def import_(
    model: Path = typer.Argument(..., exists=True, dir_okay=False,
                                 help="shape model (km, body-fixed) in any mesh format pwm exports, told by its "
                                      "content: OBJ, PLY, SPICE DSK type 2 or ICQ (a LAS point cloud or a site's "
                                      "terrain is refused: no faces)"),
    kind: str = typer.Option("imported", help="imported | start | photogrammetric"),
) -> None:
    """Publish a shape model file as a new model version."""
    from service.catalog import open_catalog
    from service.db import session_scope
    from service.rows import ModelKind
    from service.settings import get_settings
    from service.versions import import_model

    if kind not in ("imported", "start", "photogrammetric"):
        raise typer.BadParameter("kind is imported, start or photogrammetric", param_hint="--kind")
    settings = get_settings()
    try:
        with session_scope(open_catalog(settings)) as session:
            version = import_model(session, data_dir=settings.data_dir, path=model, kind=ModelKind(kind))
    except (ValueError, OSError) as exc:  # not a shape model, or it could not be read or stored
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(1) from None
    typer.echo(f"version {version.version} ({kind}): {version.statistics['vertices']} vertices, "
               f"{version.statistics['faces']} faces")


@app.command()
def versions(
    limit: int = typer.Option(50, min=1, max=MAX_ROW_ID, help="at most this many, newest first"),
    json_out: bool = typer.Option(False, "--json", help="print JSON instead of a table"),
) -> None:
    """List model versions, newest first: kind, parent, time, size, maplets and downlinks."""
    from sqlalchemy import select

    from service.catalog import open_catalog
    from service.rows import ModelVersion

    with open_catalog()() as session:
        rows = list(session.scalars(select(ModelVersion).order_by(ModelVersion.version.desc()).limit(limit)))
        if json_out:  # each as the API's GET /versions/V gives it (the API's modules take seconds to load)
            from service.api.routers.versions import detail

            echo_json([detail(v).model_dump(mode="json") for v in rows])
            return
        typer.echo(f"{'version':>7} {'kind':<15} {'parent':>6} {'created (UTC)':<19} {'faces':>8} {'maplets':>7} "
                   f"{'changed':>7}  downlinks  release")
        for v in rows:
            s = v.statistics
            typer.echo(f"{v.version:>7} {v.kind:<15} {v.parent.version if v.parent else '-':>6} "
                       f"{v.created_at.isoformat()[:19]:<19} {s.get('faces', 0):>8} {len(v.maplet_revisions):>7} "
                       f"{s.get('maplets_changed', '-'):>7}  {','.join(sorted(d.name for d in v.downlinks)) or '-'}  "
                       f"{v.release_tag or '-'}")


@version_app.command("show")
def version_show(
    version: str = typer.Argument(..., parser=version_ref, help="version number, release tag, latest or released"),
    lidar: bool = typer.Option(False, "--lidar", help="instead, its lidar residuals in words: overall, per "
                               "track and a map over longitude and latitude"),
) -> None:
    """A version in full (JSON, as the API's GET /versions/V gives it): kind, parent, lineage, statistics and
    artifacts with checksums; with --lidar, how far the catalog's lidar spots lie from it."""
    from service.catalog import open_catalog
    from service.versions import get_version

    with open_catalog()() as session:
        try:
            found = get_version(session, version)
        except LookupError as exc:
            typer.echo(str(exc), err=True)
            raise typer.Exit(1) from None
        if not lidar:
            from service.api.routers.versions import detail

            echo_json(detail(found).model_dump(mode="json"))
            return
        figures = found.statistics.get("lidar")
        if figures is None:
            typer.echo(f"version {found.version} was not checked against the lidar: the catalog had no usable "
                       "shot when it was published", err=True)
            raise typer.Exit(1)
        typer.echo(f"version {found.version} ({found.kind}) against {figures['products']} lidar products "
                   f"({figures['usable_shots']} usable shots):")
        for line in lidar_lines(figures):
            typer.echo(line)


# The map's shades, from no residual to the map's largest.
SHADES = " .:-=+*#%@"


def lidar_lines(figures: dict) -> list[str]:
    """Lidar statistics (pwm.lidar.model.residual_summary) in words, in metres: overall, per track
    and, where there is one, the RMS map drawn north up in shades of its largest cell."""

    def metres(value: float | None) -> str:
        return "-" if value is None else f"{value * 1e3:.3f}"

    lines = [f"{figures['shots']} shots, {figures['measured']} measured, {figures['missed']} without a surface "
             f"near their spot; mean {metres(figures['mean_km'])} m, RMS {metres(figures['rms_km'])} m, "
             f"95th percentile {metres(figures['p95_km'])} m"]
    flagged = {str(t) for t in figures.get("disagreeing_tracks", [])}
    lines += [f"  track {track:>6}: {t['shots']:>7} shots, mean {metres(t['mean_km'])} m, "
              f"RMS {metres(t['rms_km'])} m, 95th percentile {metres(t['p95_km'])} m"
              + (f"; {t['crossovers']} crossovers, RMS {metres(t['crossover_rms_km'])} m" if "crossovers" in t else "")
              + (f"; DISAGREES by {t['disagreement_sigmas']:.1f} sigma" if track in flagged else "")
              for track, t in figures["tracks"].items()]
    if flagged:
        lines.append(f"{len(flagged)} track(s) disagree with this version by more than {figures['disagree_sigmas']:g} "
                     f"of their sigmas: {', '.join(sorted(flagged, key=int))}")
    grid = figures.get("map")
    cells = [c for row in grid["rms_km"] for c in row if c is not None] if grid else []
    if not grid or not cells:
        return lines
    top, rows = max(cells), len(grid["rms_km"])
    step = 180.0 / rows

    def shade(rms: float | None) -> str:
        if rms is None:
            return " "
        return SHADES[1 + min(len(SHADES) - 2, int(rms / top * (len(SHADES) - 1)))] if top > 0 else SHADES[1]

    lines.append(f"RMS map (north up, east longitude 0 to 360 left to right; blank: no spot; "
                 f"'{SHADES[1]}' to '{SHADES[-1]}': up to {metres(top)} m):")
    for r in range(rows - 1, -1, -1):  # stored from the south
        lines.append(f"  {-90 + (r + 1) * step:+6.1f} |{''.join(shade(c) for c in grid['rms_km'][r])}|")
    return lines


@app.command()
def diff(
    old: str = typer.Argument(..., parser=version_ref, help="the earlier version (number, tag, latest or released)"),
    new: str = typer.Argument(..., parser=version_ref, help="the later version"),
    png: Path | None = typer.Option(None, dir_okay=False, help="write a latitude/longitude map of the change here"),
    threshold_m: float = typer.Option(0.01, parser=finite(ge=0.0),
                                      help="height change (m) above which the surface counts as changed"),
    json_out: bool = typer.Option(False, "--json", help="print JSON instead of a table"),
) -> None:
    """Height change from one version to another along the new model's outward normal (m): mean, RMS, max, area
    changed."""
    from service.catalog import open_catalog
    from service.diff import diff_versions
    from service.settings import get_settings

    settings = get_settings()
    with open_catalog(settings)() as session:
        try:
            result = diff_versions(session, data_dir=settings.data_dir, old=old, new=new, png=png,
                                   threshold_m=threshold_m)
        except LookupError as exc:
            typer.echo(str(exc), err=True)
            raise typer.Exit(1) from None
    if json_out:
        echo_json(result.model_dump(mode="json"))
        return
    rows = [("versions", f"{result.old} -> {result.new}"),
            ("vertices compared", f"{result.vertices_compared} of {result.vertices_total}"),
            *(((name, "-" if value is None else f"{value:{spec}} m") for name, value, spec in
               (("mean", result.mean_m, "+.4f"), ("RMS", result.rms_m, ".4f"),
                ("max |change|", result.max_abs_m, ".4f")))),
            (f"changed > {result.threshold_m:g} m",
             f"{result.area_changed_m2:.2f} m^2 ({result.vertices_changed} vertices)"),
            *((("map", result.png),) if result.png else ())]
    for name, value in rows:
        typer.echo(f"{name:<20}{value}")
