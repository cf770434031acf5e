"""Cutting a shape model into overlapping square maplets (PWM paper section 3.3.1; METHOD.md 4).

Each maplet has its origin on the surface, z along the regional normal (the area-weighted mean
normal of the facets within the maplet's half-size), x parallel to the equator
(pwm.frames.local_frame), and heights sampled by casting rays along -z from above every node.
Maplets of side L = (nodes - 1) * spacing sit (1 - overlap) * L apart:

- a region (a disc about a latitude/longitude): centres on a square grid of the region's plane;
- the whole body: centres on rows of constant latitude spaced (1 - overlap) L apart, and as far
  apart along each row, on the sphere of the body's area-equivalent radius (staggered from row to
  row), projected radially onto the outermost surface. Rows keep neighbouring squares aligned
  (x is east for all), which covers with far fewer gaps than a hexagonal or spiral layout.

- about given surface points (a place the images see, pwm.footprints): the disc's or the whole
  body's centres and samples near those points.

Each way, surface samples every twentieth of a side that no maplet covers (with a margin of
half a sample spacing) get maplets of their own, one per patch of them, so the tiling covers
every part of the region visible radially (whole body) or from above (region); surface under
overhangs is not tiled. Names encode the planetocentric latitude and east longitude of the
origin and the level of the spacing (`level_of`), so re-tiling the same mesh with the same
parameters gives the same names, and maplets of two levels never share one. Lengths in km,
angles in degrees.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from pwm.frames import LocalFrame, latlon_to_unit, local_frame, unit_to_latlon
from pwm.maplets import MapletGrid
from pwm.mesh import Mesh
from pwm.raytrace import RayTracer
from pwm.sampling import drop_rays

COVERAGE_SAMPLES_PER_SIDE = 20
"""Surface samples per maplet side used to check, and complete, the coverage."""
COVERAGE_MARGIN = 0.5
"""A sample counts as covered only this many sample spacings inside a maplet's square, so that
gaps between samples are covered too."""
_NEAR = 2.0 * np.sqrt(3.0)
"""Radius, in half-sizes, of the ball about a maplet's origin holding the box that `_span_km` searches."""


def level_of(spacing_km: float | np.ndarray) -> np.ndarray:
    """The level of node spacings: level k holds the spacings within a factor sqrt(2) of 2^k m
    (the nearest power of two), so that the round spacings of a plan (10 cm, 2 m) lie mid-level.
    A survey's maplets and the finer ones of a site nested in it fall into levels apart, two
    sites imaged alike into one."""
    return np.rint(np.log2(np.asarray(spacing_km, float) * 1e3)).astype(np.int64)


def tile(
    mesh: Mesh, *, spacing_km: float, nodes: int, overlap: float = 0.25, centre_lat_deg: float | None = None,
    centre_lon_deg: float | None = None, radius_km: float | None = None, where: np.ndarray | None = None,
) -> list[MapletGrid]:
    """Square maplets of nodes x nodes heights every spacing_km covering the whole body, or the
    disc of radius_km about (centre_lat_deg, centre_lon_deg) when all three are given, or the
    surface about the points `where` (N, 3; a place seen by images, pwm.footprints): those of the
    whole body's or of the disc's maplets that reach within a sample gap of them, completed until
    every surface sample near them is covered.

    overlap: fraction of a maplet's side shared with each neighbour. Albedo is sampled from the
    mesh where it has one. meta["filled_nodes"] counts the nodes whose ray missed the mesh and
    that took the height of the nearest node that did not.
    """
    region = (centre_lat_deg, centre_lon_deg, radius_km)
    if any(v is None for v in region) and any(v is not None for v in region):
        raise ValueError("give centre_lat_deg, centre_lon_deg and radius_km together, or none of them")
    if where is not None and centre_lat_deg is not None:
        raise ValueError("give a disc or points to tile about, not both")
    if nodes < 2 or spacing_km <= 0 or not 0.0 <= overlap < 1.0:
        raise ValueError("need nodes >= 2, spacing_km > 0 and 0 <= overlap < 1")
    surface = _Surface(mesh)
    half = 0.5 * (nodes - 1) * spacing_km
    step = (1.0 - overlap) * 2.0 * half
    fine = 2.0 * half / COVERAGE_SAMPLES_PER_SIDE
    if where is not None:
        centres, samples = _centres_about(surface, where, step, half, fine)
    elif centre_lat_deg is None or centre_lon_deg is None or radius_km is None:  # all None, checked above
        centres, samples = _body_centres(surface, step, fine)
    else:
        centres, samples = _region_centres(surface, centre_lat_deg, centre_lon_deg, radius_km, step, half, fine)
    frames = [local_frame(p, n) for p, n in zip(centres, surface.regional_normals(centres, half), strict=True)]
    frames += _complete(surface, frames, samples, half, margin=COVERAGE_MARGIN * fine, link=1.5 * fine)
    axis = (np.arange(nodes) - (nodes - 1) / 2) * spacing_km
    level = int(level_of(spacing_km))
    maplets = []
    for frame in frames:
        lat, lon = unit_to_latlon(frame.origin)
        heights, albedo, filled = _drop(surface.tracer, frame, axis, surface.near_vertices(frame.origin, half), half)
        maplets.append(MapletGrid(name=f"M{lat:+08.4f}E{lon:08.4f}L{level:+d}", frame=frame, spacing_km=spacing_km,
                                  heights=heights, albedo=albedo, meta={"filled_nodes": filled}))
    if len({m.name for m in maplets}) != len(maplets):
        raise ValueError("two maplet origins share a name: spacing too fine for the name's 1e-4 degree grid")
    return maplets


def sample_heights(model: Mesh | RayTracer, maplet: MapletGrid) -> np.ndarray:
    """Heights (n, n) along the maplet's z (km) of the first surface of `model` under each node,
    seen from above; nodes whose ray misses take the height of the nearest node that hits."""
    return sample_surface(model, maplet)[0]


def sample_surface(model: Mesh | RayTracer, maplet: MapletGrid) -> tuple[np.ndarray, np.ndarray | None]:
    """Heights (n, n, km) and interpolated albedo (n, n, or None if the model has none) of `model`
    under the maplet's nodes, as in `sample_heights`."""
    tracer = model if isinstance(model, RayTracer) else RayTracer(model)
    half = 0.5 * (maplet.n - 1) * maplet.spacing_km
    near = tracer.mesh.vertices[tracer.vertex_tree.query_ball_point(maplet.frame.origin, _NEAR * half)]
    heights, albedo, _ = _drop(tracer, maplet.frame, maplet.axis_km, near, half)
    return heights, albedo


@dataclass
class _Surface:
    """A mesh with the search structures that tiling needs."""

    mesh: Mesh

    def __post_init__(self) -> None:
        self.tracer = RayTracer(self.mesh)
        tri = self.mesh.vertices[self.mesh.faces]
        self.area_vectors = 0.5 * np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        self.centroids = cKDTree(tri.mean(axis=1))
        self.far_km = 2.0 * float(np.linalg.norm(self.mesh.vertices, axis=1).max())

    def regional_normals(self, points: np.ndarray, radius_km: float) -> np.ndarray:
        """Area-weighted mean normal of the facets whose centroid lies within radius_km of each
        point (of the nearest facet where none does), (N, 3) unnormalised."""
        out = np.empty((len(points), 3))
        for k, (p, idx) in enumerate(zip(points, self.centroids.query_ball_point(points, radius_km), strict=True)):
            out[k] = self.area_vectors[idx or [self.centroids.query(p)[1]]].sum(axis=0)
        return out

    def near_vertices(self, origin: np.ndarray, half_km: float) -> np.ndarray:
        """The vertices `_span_km` needs for a square of half-side half_km about origin."""
        return self.mesh.vertices[self.tracer.vertex_tree.query_ball_point(origin, _NEAR * half_km)]

    def outer_points(self, directions: np.ndarray) -> np.ndarray:
        """Outermost surface point along each unit direction from the body centre, nan on a miss."""
        origins = self.far_km * directions
        hits = self.tracer.intersect(origins, -directions)
        return self.tracer.hit_points(origins, -directions, hits)


def _latitude_rows(step_rad: float) -> np.ndarray:
    """Unit vectors on rows of constant latitude step_rad apart, step_rad apart along each row,
    every other row shifted by half a step."""
    n_rows = max(1, int(round(np.pi / step_rad)))
    rows = []
    for i in range(n_rows):
        lat = -90.0 + (i + 0.5) * 180.0 / n_rows
        m = max(1, int(round(2.0 * np.pi * np.cos(np.radians(lat)) / step_rad)))
        rows.append(latlon_to_unit(np.full(m, lat), (np.arange(m) + 0.5 * (i % 2)) * 360.0 / m))
    return np.vstack(rows)


def _body_centres(surface: _Surface, step: float, fine: float) -> tuple[np.ndarray, np.ndarray]:
    """MapletGrid centres over the whole body, and samples every `fine` km to check their coverage."""
    radius = np.sqrt(surface.mesh.face_areas().sum() / (4.0 * np.pi))
    centres = surface.outer_points(_latitude_rows(step / radius))
    samples = surface.outer_points(_latitude_rows(fine / radius))
    return centres[np.isfinite(centres[:, 0])], samples[np.isfinite(samples[:, 0])]


def _centres_about(surface: _Surface, where: np.ndarray, step: float, half: float,
                   fine: float) -> tuple[np.ndarray, np.ndarray]:
    """Centres and coverage samples about the points `where`: of the disc that holds them, or of
    the whole body when that disc would reach round it; kept where they lie within a sample gap
    of a point (the centres, within a half-side more)."""
    if not len(where):
        raise ValueError("no points to tile about")
    centre = where[np.argmin(np.linalg.norm(where - where.mean(axis=0), axis=1))]
    extent = float(np.linalg.norm(where - centre, axis=1).max())
    body_radius = np.sqrt(surface.mesh.face_areas().sum() / (4.0 * np.pi))
    if extent + half > 0.5 * body_radius:
        centres, samples = _body_centres(surface, step, fine)
    else:
        lat, lon = unit_to_latlon(centre)
        centres, samples = _region_centres(surface, float(lat), float(lon), extent + half, step, half, fine)
    near = cKDTree(where)
    gap = max(fine, 1.5 * float(np.median(near.query(where, k=2)[0][:, 1]))) if len(where) > 1 else fine
    return (centres[near.query(centres)[0] <= gap + half],
            samples[near.query(samples)[0] <= gap])


def _region_centres(surface: _Surface, lat: float, lon: float, radius: float, step: float, half: float,
                    fine: float) -> tuple[np.ndarray, np.ndarray]:
    """Centres on a square grid in the plane of the disc about (lat, lon), keeping those whose grid
    cell meets the disc, and samples of the disc every `fine` km to check their coverage."""
    origin = surface.outer_points(latlon_to_unit(lat, lon)[None])[0]
    if not np.isfinite(origin[0]):
        raise ValueError(f"no surface along latitude {lat}, longitude {lon}")
    site = local_frame(origin, surface.regional_normals(origin[None], radius)[0])
    k = int(np.ceil(radius / step + 0.5))
    i, j = np.meshgrid(np.arange(-k, k + 1), np.arange(-k, k + 1), indexing="ij")
    x, y = j.ravel() * step, i.ravel() * step
    gap = np.hypot(np.maximum(np.abs(x) - step / 2, 0.0), np.maximum(np.abs(y) - step / 2, 0.0))
    keep = gap <= radius
    reach = radius + step + half
    span = _span_km(site, surface.near_vertices(origin, reach), reach)
    centres = _drop_points(surface.tracer, site, x[keep], y[keep], span)
    m = int(np.ceil(radius / fine))
    sx, sy = np.meshgrid(np.arange(-m, m + 1) * fine, np.arange(-m, m + 1) * fine)
    inside = np.hypot(sx, sy).ravel() <= radius
    samples = _drop_points(surface.tracer, site, sx.ravel()[inside], sy.ravel()[inside], span)
    return centres[np.isfinite(centres[:, 0])], samples[np.isfinite(samples[:, 0])]


def _inside(frame: LocalFrame, points: np.ndarray, half: float, margin: float) -> np.ndarray:
    """Points over the maplet's square shrunk by margin, within twice its half-size of its plane
    (which keeps out the far side of the body)."""
    local = frame.to_local(points)
    return np.all(np.abs(local[:, :2]) <= half - margin, axis=1) & (np.abs(local[:, 2]) <= 2.0 * half)


def _complete(surface: _Surface, frames: list[LocalFrame], samples: np.ndarray, half: float,
              margin: float, link: float) -> list[LocalFrame]:
    """Frames for extra maplets until every sample is covered (see `_inside`): one per patch of
    uncovered samples (linked within `link` km), on the sample nearest the patch's mean, repeated
    while any remain."""
    covered = np.zeros(len(samples), dtype=bool)
    tree = cKDTree(samples)
    for frame in frames:
        idx = np.asarray(tree.query_ball_point(frame.origin, np.sqrt(6.0) * half), dtype=np.int64)
        covered[idx[_inside(frame, samples[idx], half, margin)]] = True
    uncovered = samples[~covered]
    extra: list[LocalFrame] = []
    while len(uncovered):
        pairs = cKDTree(uncovered).query_pairs(link, output_type="ndarray")
        graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(len(uncovered),) * 2)
        n_patches, patch = connected_components(graph, directed=False)
        size = np.bincount(patch, minlength=n_patches)
        mean = np.column_stack([np.bincount(patch, weights=uncovered[:, c]) for c in range(3)]) / size[:, None]
        dist = np.linalg.norm(uncovered - mean[patch], axis=1)
        # first sample of each patch in order of distance to its mean
        order = np.lexsort((dist, patch))
        centres = uncovered[order[np.searchsorted(patch[order], np.arange(n_patches))]]
        new = [local_frame(p, n) for p, n in zip(centres, surface.regional_normals(centres, half), strict=True)]
        extra += new
        for frame in new:
            uncovered = uncovered[~_inside(frame, uncovered, half, margin)]
    return extra


def _span_km(frame: LocalFrame, vertices: np.ndarray, half_km: float) -> tuple[float, float]:
    """Heights along the frame's z (km) below and above the surface over the square of half-side
    half_km: half_km beyond the lowest nearby vertex over it, and above the highest (at least
    half_km, enough for a facet tilted by 45 deg)."""
    local = frame.to_local(vertices)
    over = np.all(np.abs(local) <= 2.0 * half_km, axis=1)
    return (float(local[over, 2].min(initial=0.0)) - half_km,
            max(float(local[over, 2].max(initial=0.0)), half_km) + 0.01 * half_km)


def _drop_points(tracer: RayTracer, frame: LocalFrame, x: np.ndarray, y: np.ndarray,
                 span: tuple[float, float]) -> np.ndarray:
    """Body-fixed surface points (km) under local (x, y) within span (`_span_km`), nan on a miss."""
    bottom, top = span
    hits, h = drop_rays(tracer, frame, x, y, top_km=top, bottom_km=bottom)
    return np.where(hits.hit[:, None], frame.to_body(np.column_stack([x, y, np.where(hits.hit, h, 0.0)])), np.nan)


def _drop(tracer: RayTracer, frame: LocalFrame, axis: np.ndarray, near: np.ndarray,
          half: float) -> tuple[np.ndarray, np.ndarray | None, int]:
    """Heights and albedo (n, n) under the grid nodes of `axis`, misses filled from the nearest hit,
    and the number filled. near: the mesh vertices about the maplet (to bound the surface)."""
    n = len(axis)
    x, y = np.meshgrid(axis, axis)
    bottom, top = _span_km(frame, near, half)
    hits, h = drop_rays(tracer, frame, x.ravel(), y.ravel(), top_km=top, bottom_km=bottom)
    hit = hits.hit.reshape(n, n)
    if not hit.any():
        raise ValueError(f"no surface under the maplet at {frame.origin} km")
    # nearest hit node for every node (itself where it hit)
    src = ndimage.distance_transform_edt(~hit, return_distances=False, return_indices=True)
    heights = h.reshape(n, n)[src[0], src[1]]
    albedo = None
    if tracer.mesh.albedo is not None:
        albedo = tracer.interpolate(tracer.mesh.albedo, hits).reshape(n, n)[src[0], src[1]]
    return heights, albedo, int((~hit).sum())
