"""Export and release commands: a model version written to a file, a version released under a tag."""

from __future__ import annotations

import json
import os
import shutil
import tempfile
from pathlib import Path

import typer

from service.cli.app import LATITUDE, LONGITUDE, app, finite, version_ref


@app.command()
def export(
    version: str = typer.Argument(..., parser=version_ref, help="version number, release tag, latest or released"),
    format: str = typer.Option(..., "--format",
                               help="obj | ply | icq | dsk | las | site | geotiff | isis (the last three "
                                    "about a site)"),
    out: Path = typer.Option(..., "--out", help="file to write (with --tile all: a folder)"),
    surface: str = typer.Option("model", "--surface",
                                help="model (every level) | global (the whole body's levels, beneath the sites)"),
    faces: int | None = typer.Option(None, min=4, help="decimate to about this many faces first"),
    lat: float | None = typer.Option(None, parser=LATITUDE, help="site latitude, deg (site formats)"),
    lon: float | None = typer.Option(None, parser=LONGITUDE, help="site east longitude, deg (site formats)"),
    radius_km: float | None = typer.Option(None, "--radius-km", parser=finite(gt=0.0, le=100.0),
                                           help="site half-width, km (site formats)"),
    body: str | None = typer.Option(None, help="NAIF body name or ID (dsk, las, site formats; default: the "
                                                "catalog's)"),
    frame: str | None = typer.Option(None, help="body-fixed frame (default: the catalog's)"),
    tile: str | None = typer.Option(None, help="of a version stored in tiles (obj, ply, las): one tile's key, "
                                               "or `all`: every tile into the folder --out, with their index"),
) -> None:
    """Export a model version. A site product is a zip of its PDS4 label, data file and PNG preview; geotiff and isis
    hold the same layers as a GeoTIFF or an ISIS3 cube in an orthographic projection about the site; las is the
    vertices as a point cloud (m, body-fixed, albedo per point; uncompressed LAS, no LAZ). A version whose mesh is
    too big for one file (PWM_MESH_TILE_FACES) is exported as obj, ply or las a tile at a time (--tile), or
    decimated (--faces); its dsk has a segment per tile."""
    from service.artifacts import ArtifactError
    from service.catalog import open_catalog
    from service.exports import (
        SITE_FORMATS,
        ExportError,
        ExportFormat,
        ExportSurface,
        Site,
        make_export,
        plan_export,
        version_tiles,
    )
    from service.settings import get_settings
    from service.versions import get_version

    try:
        fmt = ExportFormat(format)
    except ValueError:
        raise typer.BadParameter(f"expected one of {', '.join(ExportFormat)}", param_hint="--format") from None
    try:
        which = ExportSurface(surface)
    except ValueError:
        raise typer.BadParameter(f"expected one of {', '.join(ExportSurface)}", param_hint="--surface") from None
    site_args = (lat, lon, radius_km)
    if (fmt in SITE_FORMATS) != all(a is not None for a in site_args) or (
            fmt not in SITE_FORMATS and any(a is not None for a in site_args)):
        raise typer.BadParameter(f"--lat, --lon and --radius-km go together, with --format "
                                 f"{' | '.join(sorted(SITE_FORMATS))} only")
    settings = get_settings()
    with open_catalog(settings)() as session:
        try:
            chosen = get_version(session, version)
            index = version_tiles(settings.data_dir, chosen) if tile == "all" else None
            if tile == "all" and index is None:
                raise ExportError(f"version {chosen.version} is stored whole, not in tiles: export it without --tile")
            keys = [t.key for t in index.tiles] if index is not None else [tile]
            plans = [plan_export(session, data_dir=settings.data_dir, version=chosen,
                                 fmt=fmt, surface=which, faces=faces, body=body, frame=frame, tile=key,
                                 site=Site(lat_deg=lat, lon_deg=lon, radius_km=radius_km)
                                 if lat is not None and lon is not None and radius_km is not None else None)
                     for key in keys]
            session.close()
            for plan in plans:
                made = make_export(plan, cache_bytes=settings.export_cache_bytes)
                target = out / made.filename if index is not None else out
                _copy_whole(made.path, target)
                typer.echo(f"{target} ({made.path.stat().st_size} bytes, sha256 {made.sha256})")
        except (LookupError, ExportError, ArtifactError) as exc:
            typer.echo(str(exc), err=True)
            raise typer.Exit(1) from None
        except OSError as exc:
            typer.echo(f"error: cannot write {out}: {exc.strerror or exc}", err=True)
            raise typer.Exit(1) from None
    if index is not None:
        (out / "tiles.json").write_text(json.dumps({
            "version": chosen.version, "vertices": index.vertices, "faces": index.faces,
            "tiles": [{"key": t.key, "faces": t.faces, "vertices": t.vertices, "box_km": t.box_km,
                       "file": plans[n].filename} for n, t in enumerate(index.tiles)]}, indent=1))
        typer.echo(f"{out / 'tiles.json'} ({len(index.tiles)} tiles, {index.faces} faces)")


def _copy_whole(source: Path, out: Path) -> None:
    """Copy `source` to `out` whole or not at all: through a scratch file beside `out`, renamed
    over it once complete, and removed if the copy fails (a full disk leaves nothing behind)."""
    out.parent.mkdir(parents=True, exist_ok=True)
    handle, name = tempfile.mkstemp(prefix=f".{out.name}.", dir=out.parent)
    os.close(handle)
    try:
        shutil.copyfile(source, name)
        os.replace(name, out)
    finally:
        Path(name).unlink(missing_ok=True)


@app.command()
def release(
    version: str = typer.Argument(..., parser=version_ref, help="version number, or latest"),
    tag: str = typer.Option(..., "--tag", help="release tag, set once (a letter first)"),
) -> None:
    """Mark a model version released under a tag; a release is never changed or undone."""
    from pydantic import ValidationError

    from service.api.schemas import ReleaseRequest
    from service.catalog import open_catalog
    from service.db import session_scope
    from service.releases import ReleaseConflict, release_version

    try:
        ReleaseRequest(tag=tag)
    except ValidationError as exc:
        raise typer.BadParameter(exc.errors()[0]["msg"], param_hint="--tag") from None
    try:
        with session_scope(open_catalog()) as session:
            number = release_version(session, version, tag=tag).version
    except (LookupError, ReleaseConflict) as exc:
        typer.echo(str(exc), err=True)
        raise typer.Exit(1) from None
    typer.echo(f"version {number} released as {tag}")
