"""`pwm diff V1 V2`: how the surface moved from one model version to another (pwm.compare), as
figures and a latitude/longitude map; the API's maps kept in the artifact store's cache."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.axes import Axes
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from mpl_toolkits.axes_grid1.anchored_artists import AnchoredSizeBar
from pydantic import BaseModel
from sqlalchemy.orm import Session

from pwm.compare import HeightChange, height_change
from pwm.evaluate.plots import north_arrow
from pwm.frames import unit_to_latlon
from pwm.mesh import Mesh
from service.artifacts import cached_artifact, digest
from service.rows import ModelVersion
from service.versions import get_version, version_mesh

THRESHOLD_M = 0.01
"""Height change above which a vertex counts as changed, m."""


class VersionDiff(BaseModel):
    """Signed height change of version `new` against `old`, along the new model's outward
    normal (m; positive: the new surface is higher), area-weighted over the vertices compared
    (None when no vertex of the new model lies near the old one)."""

    old: int
    new: int
    vertices_compared: int
    vertices_total: int
    mean_m: float | None
    rms_m: float | None
    max_abs_m: float | None
    threshold_m: float
    vertices_changed: int
    area_changed_m2: float
    png: str | None = None


def diff_versions(session: Session, *, data_dir: Path, old: int | str, new: int | str,
                  png: Path | None = None, threshold_m: float = THRESHOLD_M,
                  max_distance_km: float = 0.01) -> VersionDiff:
    """Compare two versions (numbers, tags, latest or released); with `png`, also write a map
    of the change over latitude and longitude there. max_distance_km: farthest a surface may
    have moved and still be compared."""
    old_version, new_version = get_version(session, old), get_version(session, new)
    new_mesh = version_mesh(data_dir, new_version)
    change = height_change(version_mesh(data_dir, old_version), new_mesh,
                           max_distance_km=max_distance_km)
    changed = change.changed(threshold_m)
    compared = bool(change.compared.any())
    if png is not None:
        _plot(png, new_mesh, change, changed, title=(
            f"height change, version {new_version.version} - version {old_version.version}"))
    return VersionDiff(old=old_version.version, new=new_version.version,
                       vertices_compared=int(change.compared.sum()),
                       vertices_total=len(change.change_m),
                       mean_m=change.mean_m() if compared else None,
                       rms_m=change.rms_m() if compared else None,
                       max_abs_m=change.max_abs_m() if compared else None,
                       threshold_m=threshold_m, vertices_changed=int(changed.sum()),
                       area_changed_m2=float(change.area_m2[changed].sum()),
                       png=None if png is None else str(png))


def change_map(session: Session, *, data_dir: Path, old: ModelVersion, new: ModelVersion,
               cache_bytes: int, threshold_m: float = THRESHOLD_M,
               max_distance_km: float = 0.01) -> dict[str, Any]:
    """The record of the map (PNG) of `diff_versions`, made once and kept in the artifact
    store's cache (service.artifacts.cached_artifact; cache_bytes as there). The session's
    transaction is ended first, so that no connection is held while the map waits for the
    making lock (making it reads the catalog again)."""
    key = digest({"diff": [v.mesh_artifact["sha256"] for v in (old, new)],
                  "threshold_m": threshold_m, "max_distance_km": max_distance_km})
    numbers = old.version, new.version

    def make(path: Path) -> None:
        diff_versions(session, data_dir=data_dir, old=numbers[0], new=numbers[1], png=path,
                      threshold_m=threshold_m, max_distance_km=max_distance_km)

    session.rollback()
    return cached_artifact(data_dir, key, suffix=".png", make=make, cache_bytes=cache_bytes)


def _north_and_scale(ax: Axes, *, radius_km: float, cos_lat: float) -> None:
    """A north arrow (latitude grows upwards: north is up) and a scale bar of a round length
    about a fifth of the map's width, at the map's middle latitude (cos_lat)."""
    north_arrow(ax)
    left, right = ax.get_xlim()
    km_per_deg = np.radians(1.0) * radius_km * cos_lat
    wanted_km = abs(right - left) * km_per_deg / 5.0
    if not wanted_km > 0:
        return
    length_km = 10.0 ** np.floor(np.log10(wanted_km))
    length_km *= max(step for step in (1.0, 2.0, 5.0) if step * length_km <= wanted_km)
    label = f"{length_km:g} km" if length_km >= 1.0 else f"{length_km * 1e3:g} m"
    ax.add_artist(AnchoredSizeBar(ax.transData, length_km / km_per_deg, label, "lower left",
                                  pad=0.4, frameon=True, size_vertical=0))


def _plot(path: Path, mesh: Mesh, change: HeightChange, changed: np.ndarray, *,
          title: str) -> None:
    """Change (m) at the vertices over east longitude and latitude, framed on the changed
    region (the whole body when nothing changed)."""
    lat, lon = unit_to_latlon(mesh.vertices)
    shown = changed if changed.any() else change.compared
    pad_lat = max(np.ptp(lat[shown]) * 0.25, 1e-3) if shown.any() else 0.0
    pad_lon = max(np.ptp(lon[shown]) * 0.25, 1e-3) if shown.any() else 0.0
    frame = change.compared.copy()
    if changed.any():
        frame &= ((lat >= lat[shown].min() - pad_lat) & (lat <= lat[shown].max() + pad_lat)
                  & (lon >= lon[shown].min() - pad_lon) & (lon <= lon[shown].max() + pad_lon))
    limit = max(float(np.abs(change.change_m[frame]).max(initial=0.0)), 1e-6)
    fig = Figure(figsize=(7, 5.5))
    FigureCanvasAgg(fig)
    ax = fig.add_subplot()
    points = ax.scatter(lon[frame], lat[frame], c=change.change_m[frame], s=2, cmap="RdBu_r",
                        vmin=-limit, vmax=limit, linewidths=0)
    fig.colorbar(points, ax=ax, label="height change (m)")
    ax.set(xlabel="east longitude (deg)", ylabel="latitude (deg)", title=title)
    cos_lat = max(float(np.cos(np.radians(np.median(lat[frame]) if frame.any() else 0.0))), 0.1)
    ax.set_aspect(1.0 / cos_lat)
    _north_and_scale(ax, radius_km=float(np.linalg.norm(mesh.vertices, axis=1).mean()), cos_lat=cos_lat)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120, bbox_inches="tight")
