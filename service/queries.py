"""The catalog read by maplet: which images see a surface point, which maplets an image sees,
which maplets a lidar track may cross, how well a maplet's image set covers it, and maplet
listings.

A surface point is given by planetocentric latitude and east longitude (deg). It lies in a
maplet when the radial line through it meets the maplet's plane (local z = 0) inside the
maplet's square (|x|, |y| <= size_km / 2 in its local frame), or within radius_km of that
square. Candidates come from a range scan of the (center_lat_deg, center_lon_deg) index over
the angle that the largest maplet's half-diagonal (plus radius_km) subtends at the body centre
from the origin nearest it; that bound holds when a maplet's centre latitude and longitude are
those of its origin, as pwm.tiling makes them. An image sees a maplet when its coverage row has
a visible fraction above 0.

Results are small frozen pydantic models, not ORM objects: they outlive the session and
serialise to JSON as they are.
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Sequence
from datetime import datetime
from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, computed_field
from sqlalchemy import ColumnElement, Result, Row, Select, and_, func, or_, select, true
from sqlalchemy.orm import Session

from pwm.frames import LocalFrame, latlon_to_unit
from pwm.weights import azimuth_spread_deg
from service.rows import Coverage, CoverageRole, Image, ImageGeometry, LidarTrack, Maplet, MapletRevision


class _Result(BaseModel):
    model_config = ConfigDict(frozen=True)


class ImageHit(_Result):
    """An image that sees a surface point, through the maplet in which it weighs most there.
    Angles (deg) and resolution are those of its coverage row of that maplet."""

    image_id: int
    lidvid: str
    start_utc: datetime | None
    maplet_id: int
    maplet: str
    visible_fraction: float
    incidence_deg: float
    emission_deg: float
    phase_deg: float
    sun_azimuth_deg: float
    resolution_m_per_px: float
    range_km: float
    weight: float
    role: CoverageRole | None


class MapletCoverage(_Result):
    """One maplet an image sees, and how (its coverage row)."""

    maplet_id: int
    maplet: str
    center_lat_deg: float
    center_lon_deg: float
    visible_fraction: float
    shadowed_fraction: float
    incidence_deg: float
    emission_deg: float
    phase_deg: float
    sun_azimuth_deg: float
    resolution_m_per_px: float
    weight: float
    role: CoverageRole | None


class CoverageSummary(_Result):
    """How well a maplet's images cover it. image_count: images that see it; used_count: those
    of them with a weight above 0, over which the ranges and the Sun azimuth spread (deg) are
    taken (None when there are none). views: the LIDVID filling each of the five roles, None
    where the role is empty."""

    maplet_id: int
    maplet: str
    image_count: int
    used_count: int
    incidence_deg: tuple[float, float] | None
    emission_deg: tuple[float, float] | None
    sun_azimuth_spread_deg: float | None
    views: dict[CoverageRole, str | None]
    region_weight: float
    current_revision: int | None

    @computed_field  # type: ignore[prop-decorator]
    @property
    def five_views(self) -> bool:
        """Nadir, east, west, north and south all filled."""
        return all(self.views.values())


class MapletInfo(_Result):
    """A maplet for listings. image_count: images that see it; distance_km: from the queried
    point to the maplet's square, in its plane (0 inside), None for a plain listing."""

    id: int
    name: str
    center_lat_deg: float
    center_lon_deg: float
    size_km: float
    gsd_m: float
    level: int
    nodes_per_side: int
    region_weight: float
    current_revision: int | None
    image_count: int
    distance_km: float | None


def distance_to_square_km(frame: LocalFrame, direction: np.ndarray, half_km: float) -> float:
    """Distance (km) in the frame's x-y plane from where the radial line along the unit
    `direction` (body-fixed) meets that plane to the square |x|, |y| <= half_km; inf when the
    line meets the plane behind the body centre or not at all."""
    facing = float(frame.normal @ direction)
    along_km = float(frame.normal @ frame.origin) / facing if facing > 0 else -1.0
    if not along_km > 0:
        return math.inf
    x, y, _ = frame.to_local(along_km * direction)
    return math.hypot(max(abs(x) - half_km, 0.0), max(abs(y) - half_km, 0.0))


def images_covering(
    session: Session, *, lat_deg: float, lon_deg: float, radius_km: float = 0.0,
    order: Literal["weight", "time"] = "weight", limit: int | None = None,
) -> list[ImageHit]:
    """Images that see the surface point (lat_deg, lon_deg), or any point within radius_km of
    it, through the maplets that hold it; each image once, by weight (highest first) or by time
    (earliest first), the first `limit` of them (all for None)."""
    if order not in ("weight", "time"):
        raise ValueError(f"order must be 'weight' or 'time', not {order!r}")
    if limit is not None and limit < 0:
        raise ValueError("limit must be >= 0")
    names = {row.id: row.name for row, _ in _maplets_near(
        session, lat_deg=lat_deg, lon_deg=lon_deg, radius_km=radius_km)}
    if not names:
        return []
    # An image's heaviest row among the maplets, chosen before the joins to images and geometry.
    ranked = (
        select(Coverage.image_id, Coverage.maplet_id, Coverage.visible_fraction,
               Coverage.incidence_deg, Coverage.emission_deg, Coverage.phase_deg,
               Coverage.sun_azimuth_deg, Coverage.resolution_m_per_px, Coverage.weight,
               Coverage.role, func.row_number().over(
                   partition_by=Coverage.image_id,
                   order_by=(Coverage.weight.desc(), Coverage.visible_fraction.desc(),
                             Coverage.maplet_id)).label("rank"))
        .where(Coverage.maplet_id.in_(names), Coverage.visible_fraction > 0)).subquery()
    ordering = ((ranked.c.weight.desc(), ranked.c.image_id) if order == "weight" else
                (Image.start_utc.asc().nulls_last(), ranked.c.image_id))
    rows = _records(session.execute(
        select(*(c for c in ranked.c if c.name != "rank"), Image.lidvid, Image.start_utc,
               ImageGeometry.range_km)
        .join(Image, Image.id == ranked.c.image_id)
        .join(ImageGeometry, ImageGeometry.image_id == ranked.c.image_id)
        .where(ranked.c.rank == 1)
        .order_by(*ordering)
        .limit(limit)))
    return [ImageHit(maplet=names[row["maplet_id"]], **row) for row in rows]


def maplets_seen_by(
    session: Session, *, image_id: int | None = None, lidvid: str | None = None
) -> list[MapletCoverage]:
    """The maplets an image (by id or LIDVID) sees, by weight, highest first. LookupError if
    the catalog has no such image."""
    if (image_id is None) == (lidvid is None):
        raise ValueError("give image_id or lidvid")
    which = Image.id == image_id if lidvid is None else Image.lidvid == lidvid
    found = session.scalar(select(Image.id).where(which))
    if found is None:
        raise LookupError(f"no image {lidvid if image_id is None else image_id} in the catalog")
    rows = _records(session.execute(
        select(Coverage.maplet_id, Maplet.name.label("maplet"), Maplet.center_lat_deg,
               Maplet.center_lon_deg, Coverage.visible_fraction, Coverage.shadowed_fraction,
               Coverage.incidence_deg, Coverage.emission_deg, Coverage.phase_deg,
               Coverage.sun_azimuth_deg, Coverage.resolution_m_per_px, Coverage.weight,
               Coverage.role)
        .join(Maplet, Maplet.id == Coverage.maplet_id)
        .where(Coverage.image_id == found, Coverage.visible_fraction > 0)
        .order_by(Coverage.weight.desc(), Maplet.name)))
    return [MapletCoverage(**row) for row in rows]


def maplet_coverage(
    session: Session, *, name: str | None = None, maplet_id: int | None = None
) -> CoverageSummary:
    """The coverage summary of a maplet (by name or id). LookupError if there is no such
    maplet."""
    if (name is None) == (maplet_id is None):
        raise ValueError("give name or maplet_id")
    which = Maplet.id == maplet_id if name is None else Maplet.name == name
    maplet = session.execute(
        select(Maplet.id, Maplet.name, Maplet.region_weight, MapletRevision.revision)
        .outerjoin(MapletRevision, MapletRevision.id == Maplet.current_revision_id)
        .where(which)).one_or_none()
    if maplet is None:
        raise LookupError(f"no maplet {name if maplet_id is None else maplet_id} in the catalog")
    rows = session.execute(
        select(Coverage.image_id, Coverage.incidence_deg, Coverage.emission_deg,
               Coverage.sun_azimuth_deg, Coverage.weight, Coverage.role)
        .where(Coverage.maplet_id == maplet.id, Coverage.visible_fraction > 0)).all()
    used = np.array([(r.incidence_deg, r.emission_deg, r.sun_azimuth_deg) for r in rows
                     if r.weight > 0]).reshape(-1, 3)
    # The heaviest image keeps a role that bad data gave to several.
    holders: dict[CoverageRole, int] = {}
    for r in sorted((r for r in rows if r.role is not None), key=lambda r: (-r.weight, r.image_id)):
        holders.setdefault(r.role, r.image_id)
    lidvids = {image_id: lidvid for image_id, lidvid in session.execute(
        select(Image.id, Image.lidvid).where(Image.id.in_(holders.values())))} if holders else {}
    views = {role: lidvids.get(holders[role]) if role in holders else None for role in CoverageRole}

    def extent(values: np.ndarray) -> tuple[float, float] | None:
        return (float(values.min()), float(values.max())) if values.size else None

    return CoverageSummary(
        maplet_id=maplet.id, maplet=maplet.name, image_count=len(rows), used_count=len(used),
        incidence_deg=extent(used[:, 0]), emission_deg=extent(used[:, 1]),
        sun_azimuth_spread_deg=azimuth_spread_deg(used[:, 2]) if len(used) else None,
        views=views, region_weight=maplet.region_weight, current_revision=maplet.revision)


def list_maplets(
    session: Session, *, lat_deg: float | None = None, lon_deg: float | None = None,
    radius_km: float = 0.0, level: int | None = None, limit: int = 100, offset: int = 0,
) -> list[MapletInfo]:
    """Maplets by name; or, given lat_deg and lon_deg, those holding that surface point or
    within radius_km of it, nearest first; of one level (pwm.tiling.level_of) if given."""
    if limit < 0 or offset < 0:
        raise ValueError("limit and offset must be >= 0")
    if (lat_deg is None) != (lon_deg is None):
        raise ValueError("give lat_deg and lon_deg together, or neither")
    if lat_deg is None or lon_deg is None:  # both, checked above
        rows = session.execute(_maplet_rows(level).order_by(Maplet.name).limit(limit).offset(offset))
        page: Sequence[tuple[Row[Any], float | None]] = [(row, None) for row in rows]
    else:
        near = _maplets_near(session, lat_deg=lat_deg, lon_deg=lon_deg, radius_km=radius_km, level=level)
        page = sorted(near, key=lambda item: (item[1], item[0].name))[offset:offset + limit]
    counts: dict[int, int] = {maplet_id: n for maplet_id, n in session.execute(
        select(Coverage.maplet_id, func.count())
        .where(Coverage.maplet_id.in_([row.id for row, _ in page]), Coverage.visible_fraction > 0)
        .group_by(Coverage.maplet_id))} if page else {}
    return [MapletInfo(
        id=row.id, name=row.name, center_lat_deg=row.center_lat_deg,
        center_lon_deg=row.center_lon_deg, size_km=row.size_km, gsd_m=row.gsd_m, level=row.level,
        nodes_per_side=row.nodes_per_side, region_weight=row.region_weight,
        current_revision=row.revision, image_count=counts.get(row.id, 0), distance_km=distance)
        for row, distance in page]


def _records(result: Result[Any]) -> Iterator[dict[str, Any]]:
    """The rows as dicts, column name to value: a model built from these is built several
    times faster than from Row._mapping."""
    keys = tuple(result.keys())
    return (dict(zip(keys, row, strict=True)) for row in result)


def _maplet_rows(level: int | None = None) -> Select[Any]:
    query = (select(Maplet.id, Maplet.name, Maplet.center_lat_deg, Maplet.center_lon_deg,
                    Maplet.origin_x_km, Maplet.origin_y_km, Maplet.origin_z_km, Maplet.rotation,
                    Maplet.size_km, Maplet.gsd_m, Maplet.level, Maplet.nodes_per_side, Maplet.region_weight,
                    MapletRevision.revision)
             .outerjoin(MapletRevision, MapletRevision.id == Maplet.current_revision_id))
    return query if level is None else query.where(Maplet.level == level)


def _maplets_near(
    session: Session, *, lat_deg: float, lon_deg: float, radius_km: float, level: int | None = None
) -> list[tuple[Row[Any], float]]:
    """Maplets (of one level if given) holding the surface point, or within radius_km of it,
    with that distance (km)."""
    if not -90.0 <= lat_deg <= 90.0 or not math.isfinite(lon_deg):
        raise ValueError(f"latitude {lat_deg} or longitude {lon_deg} out of range")
    if not radius_km >= 0.0:
        raise ValueError(f"radius_km must be >= 0, not {radius_km}")
    prefilter = _prefilter(session, lat_deg=lat_deg, lon_deg=lon_deg, radius_km=radius_km)
    if prefilter is None:
        return []
    direction = latlon_to_unit(lat_deg, lon_deg)
    near = []
    for row in session.execute(_maplet_rows(level).where(prefilter)):
        distance = distance_to_square_km(Maplet.frame_of(row), direction, row.size_km / 2)
        if distance <= radius_km:
            near.append((row, distance))
    return near


def _prefilter(
    session: Session, *, lat_deg: float, lon_deg: float, radius_km: float
) -> ColumnElement[bool] | None:
    """A condition on the maplets' centre latitude and longitude that every maplet within
    radius_km of the point meets; None when there are no maplets.

    Such a maplet's origin O lies within reach = half-diagonal + radius_km of a point on the
    radial line of the point, so the angle between that line and O is at most
    asin(reach / |O|): a spherical cap about the point.
    """
    # One pass over the maplets (about 1 ms for 5000); an index on the size and on the origin
    # radius would bound it in O(log n) should the tiling grow by orders of magnitude.
    size_km, radius2_km2 = session.execute(select(
        func.max(Maplet.size_km),
        func.min(Maplet.origin_x_km * Maplet.origin_x_km + Maplet.origin_y_km * Maplet.origin_y_km
                 + Maplet.origin_z_km * Maplet.origin_z_km))).one()
    if size_km is None:
        return None
    reach_km = size_km / math.sqrt(2.0) + radius_km
    if reach_km >= math.sqrt(radius2_km2):
        return true()
    return _in_cap(lat_deg, lon_deg, math.degrees(math.asin(reach_km / math.sqrt(radius2_km2))))


def _in_cap(lat_deg: float, lon_deg: float, cap_deg: float) -> ColumnElement[bool]:
    """A condition on the maplets' centre latitude and longitude that holds for every centre
    within cap_deg of (lat_deg, lon_deg) on the sphere (a range scan of their index)."""
    if cap_deg >= 180.0:
        return true()
    in_latitude = Maplet.center_lat_deg.between(lat_deg - cap_deg, lat_deg + cap_deg)
    if abs(lat_deg) + cap_deg >= 90.0:
        return in_latitude  # the cap holds a pole: every longitude
    half_deg = math.degrees(math.asin(math.sin(math.radians(cap_deg))
                                      / math.cos(math.radians(lat_deg))))
    lon = lon_deg % 360.0
    # Longitudes may be stored in [0, 360) or (-180, 180]; the window may cross 0/360.
    return and_(in_latitude, or_(*(
        Maplet.center_lon_deg.between(lon - half_deg + turn, lon + half_deg + turn)
        for turn in (-360.0, 0.0, 360.0))))


class TrackCrossing(_Result):
    """A maplet a lidar track may cross: its spots' cone (about the body's centre) meets the
    maplet's square. angle_deg: from the cone's axis to the maplet's centre."""

    maplet_id: int
    maplet: str
    center_lat_deg: float
    center_lon_deg: float
    level: int
    angle_deg: float


def maplets_crossed(session: Session, *, track_id: int) -> list[TrackCrossing]:
    """The maplets a lidar track (service.rows.LidarTrack, by id) may cross, nearest its
    cone's axis first: those whose square reaches into the cone of its spots about the body's
    centre, found as images' maplets are, by a range scan of the maplets' centres over the cap
    the cone and the largest maplet's half-diagonal span, then each maplet's own reach. A
    superset of those its spots fall in (a cone holds a track's whole sweep). LookupError if
    the catalog has no such track."""
    track = session.get(LidarTrack, track_id)
    if track is None:
        raise LookupError(f"no lidar track {track_id} in the catalog")
    size_km, radius2_km2 = session.execute(select(
        func.max(Maplet.size_km),
        func.min(Maplet.origin_x_km * Maplet.origin_x_km + Maplet.origin_y_km * Maplet.origin_y_km
                 + Maplet.origin_z_km * Maplet.origin_z_km))).one()
    if size_km is None:
        return []
    half_diagonal = size_km / math.sqrt(2.0)
    radius_km = math.sqrt(radius2_km2)
    # a maplet whose origin is nearer the centre than its half-diagonal may be seen from anywhere
    reach_deg = 180.0 if half_diagonal >= radius_km else math.degrees(math.asin(half_diagonal / radius_km))
    cap_deg = math.degrees(track.cone_half_angle_rad) + reach_deg
    axis = np.array([track.cone_axis_x, track.cone_axis_y, track.cone_axis_z])
    rows = session.execute(select(Maplet.id, Maplet.name, Maplet.center_lat_deg, Maplet.center_lon_deg,
                                  Maplet.level, Maplet.origin_x_km, Maplet.origin_y_km, Maplet.origin_z_km,
                                  Maplet.size_km)
                           .where(_in_cap(track.axis_lat_deg, track.axis_lon_deg, cap_deg))).all()
    if not rows:
        return []
    origin = np.array([(r.origin_x_km, r.origin_y_km, r.origin_z_km) for r in rows])
    distance = np.linalg.norm(origin, axis=1)
    angle = np.degrees(np.arccos(np.clip(origin @ axis / np.maximum(distance, 1e-300), -1.0, 1.0)))
    own = np.array([r.size_km for r in rows]) / math.sqrt(2.0)
    reach = np.degrees(np.arcsin(np.clip(own / np.maximum(distance, 1e-300), 0.0, 1.0)))
    within = angle <= math.degrees(track.cone_half_angle_rad) + reach
    found = [TrackCrossing(maplet_id=r.id, maplet=r.name, center_lat_deg=r.center_lat_deg,
                           center_lon_deg=r.center_lon_deg, level=r.level, angle_deg=float(a))
             for r, a, inside in zip(rows, angle, within, strict=True) if inside]
    return sorted(found, key=lambda c: (c.angle_deg, c.maplet))


class MapletImage(_Result):
    """An image in a maplet's image set: how it sees the maplet (its coverage row) and its
    weight there."""

    image_id: int
    lidvid: str
    start_utc: datetime | None
    weight: float
    role: CoverageRole | None
    visible_fraction: float
    shadowed_fraction: float
    incidence_deg: float
    emission_deg: float
    phase_deg: float
    resolution_m_per_px: float


class RevisionInfo(_Result):
    """One solved state of a maplet; statistics hold its residuals and solver figures."""

    revision: int
    mode: str
    created_at: datetime
    input_hash: str
    sha256: str
    statistics: dict[str, Any]
    current: bool


def maplet_images(session: Session, *, maplet_id: int) -> list[MapletImage]:
    """The images that see a maplet, by weight (highest first), then by id."""
    rows = _records(session.execute(
        select(Coverage.image_id, Image.lidvid, Image.start_utc, Coverage.weight, Coverage.role,
               Coverage.visible_fraction, Coverage.shadowed_fraction, Coverage.incidence_deg,
               Coverage.emission_deg, Coverage.phase_deg, Coverage.resolution_m_per_px)
        .join(Image, Image.id == Coverage.image_id)
        .where(Coverage.maplet_id == maplet_id, Coverage.visible_fraction > 0)
        .order_by(Coverage.weight.desc(), Coverage.image_id)))
    return [MapletImage(**row) for row in rows]


def maplet_revisions(session: Session, *, maplet_id: int) -> list[RevisionInfo]:
    """A maplet's revisions, oldest first, the current one marked."""
    current = session.scalar(select(Maplet.current_revision_id).where(Maplet.id == maplet_id))
    revisions = session.scalars(select(MapletRevision).where(MapletRevision.maplet_id == maplet_id)
                                .order_by(MapletRevision.revision))
    return [RevisionInfo(revision=r.revision, mode=r.mode, created_at=r.created_at,
                         input_hash=r.input_hash, sha256=r.sha256, statistics=r.statistics,
                         current=r.id == current) for r in revisions]


def count_maplets(session: Session, *, lat_deg: float | None = None, lon_deg: float | None = None,
                  radius_km: float = 0.0, level: int | None = None) -> int:
    """How many maplets list_maplets pages through with the same arguments."""
    if (lat_deg is None) != (lon_deg is None):
        raise ValueError("give lat_deg and lon_deg together, or neither")
    if lat_deg is None or lon_deg is None:  # both, checked above
        query = select(func.count(Maplet.id))
        return session.scalar(query if level is None else query.where(Maplet.level == level)) or 0
    return len(_maplets_near(session, lat_deg=lat_deg, lon_deg=lon_deg, radius_km=radius_km, level=level))
