"""The image-maplet coverage rows of the catalog: which maplets the accepted images see, and how.

After a downlink's images are in, and given the current shape model (body-fixed, km):
1. the places that the downlink's images look at and that enough catalogued images see usably
   (pwm.footprints: a whole body for a survey, one place per site), where no catalogued maplet
   as fine as their images support (within a factor two) lies yet, are tiled (pwm.tiling.tile),
   each at the spacing of the finest images enough to refine it, and stored: a site imaged at
   10 cm inside a survey tiled at 2 m gets maplets of its own level (pwm.tiling.level_of),
   nested under the survey's, which stay; places no image sees stay untiled;
2. every maplet that one of the downlink's images may see is weighed with the refinement's own
   rules (pwm.weights.views_over_maplet, pwm.weights.weigh_images): the new images are traced
   by Embree against the shape (in frame, not occluded, lit) on a subsample of the maplet's
   nodes, angles at the maplet origin in its frame; the images already catalogued bring their
   stored rows, so that the work grows with the downlink, not with the catalog (a maplet tiled
   now is traced in every catalogued image that may see it). From the rows of all: image
   weights (0 where the SPC rules drop the image), the five-view roles and the region weight
   w_PWM, which is stored on the maplet.

Rows are upserted (one per image and maplet) and written only where a value changed, so a
repeated ingest changes nothing; rows of images that no longer see a maplet are deleted.
"""

from __future__ import annotations

import logging
from collections.abc import Collection, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.spatial import cKDTree
from sqlalchemy import func, select, update
from sqlalchemy.orm import Session

from pwm.camera import project
from pwm.config import DEFAULTS, RefinementConfig
from pwm.footprints import Samples, footprint_samples, judge_samples, places
from pwm.frames import LocalFrame, unit_to_latlon
from pwm.maplets import MapletGrid
from pwm.mesh import Mesh
from pwm.raytrace import RayTracer
from pwm.tiling import sample_heights, tile
from pwm.views import Cones, View
from pwm.weights import MapletGeometry, views_over_maplet, weigh_images
from service.rows import Coverage, CoverageRole, Image, Maplet, utcnow
from service.views import catalog_cones, catalog_views

log = logging.getLogger(__name__)

FACING_COS = -0.5
"""Cameras more than 120 deg from a maplet's normal, seen from its origin, cannot see it (its
relief and its curvature allowed for): they look at the other side of the body."""
SAMPLE_NODES = 25
"""Nodes per side on which visibility is traced: enough for the fractions, fast for the catalog."""

_GEOMETRY = ("visible_fraction", "shadowed_fraction", "incidence_deg", "emission_deg", "phase_deg",
             "sun_azimuth_deg", "camera_azimuth_deg", "resolution_m_per_px")
"""The columns of a coverage row that the image's geometry over the maplet gives; weight and role
follow from those of all the maplet's images (pwm.weights.weigh_images)."""


@dataclass
class CoverageReport:
    """What one coverage update did: maplets tiled and weighed, images traced over a maplet
    (each image and maplet once), coverage rows written."""

    maplets_added: int = 0
    maplets_weighed: int = 0
    pairs_traced: int = 0
    rows_added: int = 0
    rows_updated: int = 0
    rows_deleted: int = 0


def unweighed_images(session: Session) -> set[int]:
    """The images not weighed yet (Image.coverage_computed_at): a new downlink's, those ingested
    while the catalog had no shape, and those whose pose was corrected since."""
    return set(session.scalars(select(Image.id).where(Image.coverage_computed_at.is_(None))))


def update_coverage(session: Session, shape: Mesh, *, downlink_id: int | None = None,
                    image_ids: Collection[int] | None = None, config: RefinementConfig = DEFAULTS,
                    sample_nodes: int = SAMPLE_NODES) -> CoverageReport:
    """Tile the places the new images look at where no maplet covers them, then weigh every
    maplet that a new image may see: the new images traced, with the stored rows of the others.

    New images: the accepted images with geometry of image_ids if given, else of downlink
    `downlink_id` (all such images when None); their coverage_computed_at is set. config: how
    maplets are tiled here (nodes, overlap, spacing in the images' median pixel scale, tile
    radius) and weighed (rules); sample_nodes: nodes per side on which visibility is traced.

    The work grows with the new images and the maplets and images about them, not with the
    catalog: the catalogued images are chosen by their stored cones (service.views.catalog_cones)
    and made views of only when their cone meets a place in question.
    """
    report = CoverageReport()
    ids, cones = catalog_cones(session)
    query = select(Image.id)
    if downlink_id is not None:
        query = query.where(Image.downlink_id == downlink_id)
    if image_ids is not None:
        query = query.where(Image.id.in_(list(image_ids)))
    wanted = set(session.scalars(query)).intersection(ids.tolist())
    if not wanted:
        return report
    views = _Views(session, ids, cones)
    new = list(views.get(sorted(wanted)).values())
    tracer = RayTracer(shape)
    added = _tile_seen(session, tracer, new, views, config=config)
    report.maplets_added = len(added)
    rows = session.execute(select(Maplet.id, Maplet.origin_x_km, Maplet.origin_y_km, Maplet.origin_z_km,
                                  Maplet.size_km).order_by(Maplet.id)).all()
    if rows:
        table = np.array([row[1:] for row in rows], float)
        # a maplet's square lies within its half-diagonal of its origin, its relief within a side
        balls = table[:, :3], np.sqrt(1.5) * table[:, 3]
        in_cone = Cones.of(new).seeing(*balls)  # (new images, maplets)
        candidates = np.flatnonzero(in_cone.any(axis=0))
    else:
        in_cone, candidates = np.zeros((len(new), 0), bool), np.empty(0, dtype=np.int64)
    chosen = session.scalars(select(Maplet).where(Maplet.id.in_([rows[m][0] for m in candidates.tolist()])))
    by_id = {maplet.id: maplet for maplet in chosen}
    cameras = np.array([v.pose.position for v in new])
    for m in candidates.tolist():
        maplet = by_id[rows[m][0]]
        frame = Maplet.frame_of(maplet)
        # none of the new images sees it: it stays as it was (the images whose cone meets its
        # ball, on the side it faces, are asked; the frame alone tells both)
        asked = in_cone[:, m] & _facing(frame, cameras)
        if not asked.any():
            continue
        grid = _subsample(maplet, tracer, sample_nodes)
        corners = _box(grid.nodes_body().reshape(-1, 3))
        if not any(_may_see(corners, v) for v, ask in zip(new, asked, strict=True) if ask):
            continue
        stored = {row.image_id: row for row in session.scalars(
            select(Coverage).where(Coverage.maplet_id == maplet.id))}
        # Traced: the new images; all of a new maplet's; and those of rows that lack a column.
        # The other stored rows stand: their image's pose and the shape they were traced on
        # are those of their day, and weighing them again is what made a downlink's work grow
        # with the catalog.
        again = wanted | {i for i, row in stored.items() if row.camera_azimuth_deg is None}
        # a cone passes through the body: the cameras on the side the maplet faces
        near = ids[cones.seeing(balls[0][m], balls[1][m])[:, 0] & _facing(frame, cones.apex)]
        if maplet.id not in added:
            near = near[np.isin(near, list(again))]
        traced = {i: v for i, v in views.get(near.tolist()).items() if _may_see(corners, v)}
        if not wanted.intersection(traced):
            continue
        report.maplets_weighed += 1
        report.pairs_traced += len(traced)
        _store(session, maplet, grid, traced, stored, again, tracer, report, config=config)
    session.execute(update(Image).where(Image.id.in_(sorted(wanted))).values(
        coverage_computed_at=utcnow()))
    session.flush()
    log.info("coverage: %d maplets tiled, %d weighed of %d catalogued (%d image-maplet pairs traced); rows %d "
             "added, %d updated, %d deleted; %d of %d images made views", report.maplets_added,
             report.maplets_weighed, len(rows), report.pairs_traced, report.rows_added, report.rows_updated,
             report.rows_deleted, len(views.made), len(ids))
    return report


class _Views:
    """The catalogued images as views, made once each and only when asked for."""

    def __init__(self, session: Session, ids: np.ndarray, cones: Cones) -> None:
        self.session, self.ids, self.cones = session, ids, cones
        self.made: dict[int, View] = {}

    def get(self, image_ids: Sequence[int]) -> dict[int, View]:
        """The views of image_ids, by id, in their order."""
        missing = [i for i in image_ids if i not in self.made]
        if missing:
            self.made.update(catalog_views(self.session, image_ids=missing))
        return {i: self.made[i] for i in image_ids}

    def seeing(self, samples: Samples) -> list[View]:
        """The views whose cones meet a cell of the samples."""
        centres, radius, _ = samples.cells()
        return list(self.get(self.ids[self.cones.seeing(centres, radius).any(axis=1)].tolist()).values())


def _tile_seen(session: Session, tracer: RayTracer, new: list[View], views: _Views, *,
               config: RefinementConfig) -> set[int]:
    """Tile and store the places that the new views look at, that enough catalogued views see
    usably (pwm.footprints), and that no catalogued maplet about as fine covers yet (`_about`:
    a finer level nests under a coarser one), each at the spacing its images support (within
    config.tile_radius_km of each place's centre, if given); the ids of the maplets added."""
    samples = footprint_samples(tracer, new)
    if not len(samples.points):
        return set()
    # a maplet covers points within sqrt(3)/2 of its side of its origin (`_covered`): those of
    # the rest of the catalog need not be read
    reach = np.sqrt(3.0) / 2 * float(session.scalar(select(func.max(Maplet.size_km))) or 0.0)
    low, high = samples.points.min(axis=0) - reach, samples.points.max(axis=0) + reach
    catalogued = session.execute(select(Maplet.origin_x_km, Maplet.origin_y_km, Maplet.origin_z_km,
                                        Maplet.rotation, Maplet.size_km, Maplet.gsd_m).where(
        *(column.between(float(a), float(b)) for column, a, b in zip(
            (Maplet.origin_x_km, Maplet.origin_y_km, Maplet.origin_z_km), low, high, strict=True)))).all()
    # Nothing to tile where maplets as fine as the new images could make cover every sample:
    # spare judging the footprints in the many images of a well-imaged place.
    nearest_km = min(float(np.linalg.norm(samples.points - v.pose.position, axis=1).min()) / v.camera.fx
                     for v in new)
    if _covered(_about(catalogued, config.spacing_gsd * nearest_km), samples.points).all():
        return set()
    seen = judge_samples(tracer, samples, views.seeing(samples), rules=config.rules, min_images=config.min_images)
    added: list[MapletGrid] = []
    # places of all that is seen, covered or not, so that a place and its centre stay where they
    # were when a later downlink sees it again
    for place in places(seen, nodes=config.nodes, spacing_gsd=config.spacing_gsd):
        points = place.points
        if config.tile_radius_km is not None:
            points = points[np.linalg.norm(points - place.centre, axis=1) <= config.tile_radius_km]
        points = points[~_covered(_about(catalogued, place.spacing_km), points)]
        if not len(points):
            continue
        maplets = tile(tracer.mesh, spacing_km=place.spacing_km, nodes=config.nodes, overlap=config.overlap,
                       where=points)
        taken = set(session.scalars(select(Maplet.name).where(
            Maplet.name.in_([m.name for m in maplets])))) | {m.name for m in added}
        new_here = [m for m in maplets if m.name not in taken]
        lat, lon = unit_to_latlon(place.centre)
        log.info("tiled %d maplets of %d nodes at %.3f m (level %d) over a place about (%.4f, %.4f) seen at %d "
                 "samples", len(new_here), config.nodes, place.spacing_km * 1e3, place.level, lat, lon, len(points))
        added += new_here
    records = [Maplet.of(m) for m in added]
    session.add_all(records)
    session.flush()
    return {m.id for m in records}


def _about(maplets: Sequence[Sequence[Any]], spacing_km: float) -> list[Sequence[Any]]:
    """The maplets (rows ending in gsd_m) within a factor two of spacing_km, or finer: a place is
    tiled at a new level where its images are at least twice as fine as the maplets there, so
    that two downlinks of about one spacing (on either side of a level's bound) share maplets."""
    return [row for row in maplets if row[-1] < 2e3 * spacing_km]


def _covered(maplets: Sequence[Sequence[Any]], points: np.ndarray) -> np.ndarray:
    """Which points lie over one of the maplets' squares (within its half-size of its plane);
    maplets: rows of origin x, y, z (km), rotation and size (km), and what follows."""
    covered = np.zeros(len(points), dtype=bool)
    if not maplets or not len(points):
        return covered
    tree = cKDTree(points)
    for x, y, z, rotation, size, *_ in maplets:
        origin = np.array([x, y, z])
        idx = np.asarray(tree.query_ball_point(origin, np.sqrt(3.0) * 0.5 * size), dtype=np.int64)
        if len(idx):
            local = (points[idx] - origin) @ np.asarray(rotation, float).reshape(3, 3).T
            covered[idx[np.all(np.abs(local) <= 0.5 * size, axis=1)]] = True
    return covered


def _subsample(maplet: Maplet, tracer: RayTracer, sample_nodes: int) -> MapletGrid:
    """The maplet's square on at most sample_nodes x sample_nodes nodes, heights from the shape."""
    grid = maplet.grid(nodes=min(sample_nodes, maplet.nodes_per_side))
    grid.heights = sample_heights(tracer, grid)
    return grid


def _facing(frame: LocalFrame, cameras_km: np.ndarray) -> np.ndarray:
    """Which cameras (N, 3) lie on the side of the body a maplet in this frame faces (FACING_COS)."""
    to_camera = cameras_km - frame.origin
    return to_camera @ frame.normal > FACING_COS * np.linalg.norm(to_camera, axis=1)


def _box(points: np.ndarray) -> np.ndarray:
    """The 8 corners (8, 3) of the axis-aligned box of the points: whatever of the points a
    camera sees ahead of it projects within what the corners do."""
    low, high = np.nanmin(points, axis=0), np.nanmax(points, axis=0)
    return np.array([[(low, high)[i][0], (low, high)[j][1], (low, high)[k][2]]
                     for i in (0, 1) for j in (0, 1) for k in (0, 1)])


def _may_see(points: np.ndarray, view: View) -> bool:
    """Whether the image's frame meets the box of the points (body-fixed, km) projected, when all
    are in front of it: a cheap test before any ray is traced."""
    ahead = view.pose.to_camera(points)[:, 2] > 0
    if not ahead.all():  # about the camera's plane: let the ray tracing judge
        return bool(ahead.any())
    px = project(points, view.camera, view.pose)
    return bool(px[:, 0].max() >= 0 and px[:, 0].min() <= view.camera.width - 1
                and px[:, 1].max() >= 0 and px[:, 1].min() <= view.camera.height - 1)


def _store(session: Session, maplet: Maplet, grid: MapletGrid, traced: dict[int, View],
           stored: dict[int, Coverage], again: set[int], tracer: RayTracer, report: CoverageReport, *,
           config: RefinementConfig) -> None:
    """Trace the maplet in the `traced` views, weigh them together with the rows of `stored` (the
    maplet's rows by image id) whose image is neither traced nor to be traced `again`, and upsert
    the rows and the region weight; stored rows of images traced and not seen are deleted."""
    spacing_km = maplet.gsd_m * 1e-3
    values: dict[int, dict[str, Any]] = {i: {c: getattr(row, c) for c in _GEOMETRY} for i, row in stored.items()
                                         if i not in again and i not in traced}
    _, _, geom = views_over_maplet(grid, list(traced.values()), tracer, spacing_km=spacing_km)
    for k, image_id in enumerate(traced):
        if geom.visible_fraction[k] > 0:
            values[image_id] = dict(zip(_GEOMETRY, (float(v) for v in (
                geom.visible_fraction[k], geom.shadow_fraction[k], geom.incidence_deg[k], geom.emission_deg[k],
                geom.phase_deg[k], geom.sun_azimuth_deg[k], geom.camera_azimuth_deg[k],
                geom.resolution_ratio[k] * spacing_km * 1e3)), strict=True))
    order = sorted(values)
    weights = weigh_images(_geometry([values[i] for i in order], gsd_m=maplet.gsd_m), config.rules)
    roles = {order[k]: CoverageRole(name) for name, k in vars(weights.views).items() if k is not None}
    for k, image_id in enumerate(order):
        row_values = values[image_id] | {"weight": float(weights.image[k]), "role": roles.get(image_id)}
        row = stored.pop(image_id, None)
        if row is None:
            session.add(Coverage(image_id=image_id, maplet_id=maplet.id, **row_values))
            report.rows_added += 1
        elif any(getattr(row, c) != v for c, v in row_values.items()):
            for column, value in row_values.items():
                setattr(row, column, value)
            report.rows_updated += 1
    for row in stored.values():
        session.delete(row)
        report.rows_deleted += 1
    if maplet.region_weight != weights.region:
        maplet.region_weight = float(weights.region)


def _geometry(rows: list[dict[str, Any]], *, gsd_m: float) -> MapletGeometry:
    """The images' geometry over a maplet of spacing gsd_m from their coverage rows' values (new
    and stored alike, so that weighing them again gives the same weights)."""
    def column(name: str) -> np.ndarray:
        return np.array([row[name] for row in rows], float)
    return MapletGeometry(
        incidence_deg=column("incidence_deg"), emission_deg=column("emission_deg"), phase_deg=column("phase_deg"),
        camera_azimuth_deg=column("camera_azimuth_deg"), sun_azimuth_deg=column("sun_azimuth_deg"),
        resolution_ratio=column("resolution_m_per_px") / gsd_m, visible_fraction=column("visible_fraction"),
        shadow_fraction=column("shadowed_fraction"))
