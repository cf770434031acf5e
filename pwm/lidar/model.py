"""A closed shape model from lidar spots, and the spots' distances to any model.

Normals: each spot's from a plane fitted to its neighbours, turned to face where its shot came
from (outside, since a shot leaves from outside the body: right for bodies of any shape, where a
direction from the centre is not). Surface: the spots' signed distances (along their normals,
averaged over the spots near each lattice point with Gaussian weights) go into the volumetric
fusion the images use (pwm.volume.DistanceGrid), whose marching cubes make one closed mesh. The
spots of a survey leave bare strips between tracks, so a first surface on a lattice
LidarConfig.coarse_factor coarser (whose reach bridges them) is made first and serves as the
fine one's base, which DistanceGrid closes over whatever the spots did not reach (on the fine
lattice the spots lay distances only over themselves, as a maplet does, not beside them over a
gap). Spots whose shot grazed the surface are left out (their normals are unreliable), and
where tracks still disagree by about the kernel (the first model, from unadjusted spots) the
kernel is widened until the surface closes. pwm.volume's marching cubes, largest piece and
base bending are reused as they are; nothing of the fusion is written twice.

Limits: the tangent planes of a convex surface stand outside it, so the model swells by about
the kernel squared over the radius of curvature (a few decimetres on the tests' Castalia), and
the loop (pwm.lidar.strips.adjust), whose tracks follow the model, adds a little each round;
planes fitted with curvature, or a screened Poisson solve, would remove it.

Distances to a model are measured along each shot: from the first hit of the shot's ray, along
that face's normal (positive outside), which for a spot near the surface is its distance to it;
`residual_summary` gives them as a model's statistics: overall, per track and on a coarse map
over longitude and latitude, from a bounded sample of the shots. Lengths in km, body-fixed frame.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from pwm.evaluate.closure import closure
from pwm.lidar.config import LIDAR, LidarConfig
from pwm.lidar.shots import Shots
from pwm.lidar.tracks import NO_TRACK
from pwm.mesh import Mesh
from pwm.raytrace import RayTracer
from pwm.volume import DistanceGrid
from pwm.voxels import pack, sum_by_key, unpack

_FUSE_NEIGHBOURS = 8
_WIDEN = 1.5
_CHUNK = 200_000


def usable(shots: Shots) -> np.ndarray:
    """(N,) the valid shots whose numbers can be used: finite origin and direction, a positive
    finite range and sigma (a product that lies about them is not trusted to have flagged it)."""
    return (shots.valid & np.isfinite(shots.origin_km).all(axis=1) & np.isfinite(shots.direction).all(axis=1)
            & np.isfinite(shots.range_km) & (shots.range_km > 0) & np.isfinite(shots.sigma_km) & (shots.sigma_km > 0))


def along_shots(shots: Shots, tracer: RayTracer, *,
                near_km: float = LIDAR.intercept_km) -> tuple[np.ndarray, np.ndarray]:
    """Each spot's signed distance to the tracer's mesh (N,) (positive outside; nan where the
    shot is not `usable`, or its ray misses the mesh or meets it further than near_km from the
    spot: other ground, as a grazing shot's ray past a limb) and the unit normal of the face its
    ray hit (N, 3; nan where the distance is)."""
    distance = np.full(len(shots), np.nan)
    normal = np.full((len(shots), 3), np.nan)
    valid = np.flatnonzero(usable(shots))
    if not len(valid):
        return distance, normal
    origin, direction = shots.origin_km[valid], shots.direction[valid]
    hits = tracer.intersect(origin, direction)
    point = tracer.hit_points(origin, direction, hits)
    face_normal = np.asarray(tracer.face_normals)[np.where(hits.hit, hits.face, 0)]
    spot = origin + shots.range_km[valid, None] * direction
    d = np.einsum("ij,ij->i", spot - point, face_normal)
    met = hits.hit & (np.abs(shots.range_km[valid] - hits.t) <= near_km)
    distance[valid] = np.where(met, d, np.nan)
    normal[valid] = np.where(met[:, None], face_normal, np.nan)
    return distance, normal


@dataclass(frozen=True)
class Residuals:
    """The spots' signed distances to a model (km): per shot (nan where not measured), and their
    mean, RMS and 95th percentile of the absolute value, overall and per track (dict by track
    id); `missed`: usable shots whose ray met no surface of the model near the spot."""

    distance_km: np.ndarray
    mean_km: float
    rms_km: float
    p95_km: float
    per_track: dict[int, tuple[float, float, float]]
    missed: int


def _stats(d: np.ndarray) -> tuple[float, float, float]:
    if not len(d):
        return float("nan"), float("nan"), float("nan")
    return float(d.mean()), float(np.sqrt(np.mean(d ** 2))), float(np.percentile(np.abs(d), 95))


def lidar_residuals(shots: Shots, mesh: Mesh, track: np.ndarray | None = None, *,
                    config: LidarConfig = LIDAR) -> Residuals:
    """The valid spots' signed distances to `mesh` (see the module docstring), with statistics
    overall and per track (`track`: each shot's id, pwm.lidar.tracks.track_ids; None: one track
    0)."""
    track = np.zeros(len(shots), dtype=np.int64) if track is None else np.asarray(track)
    if track.shape != (len(shots),):
        raise ValueError(f"track has shape {track.shape}, expected ({len(shots)},)")
    distance, _ = along_shots(shots, RayTracer(mesh), near_km=config.intercept_km)
    measured = np.isfinite(distance)
    per_track = {int(t): _stats(distance[measured & (track == t)])
                 for t in np.unique(track[measured]) if t != NO_TRACK}
    mean, rms, p95 = _stats(distance[measured])
    return Residuals(distance, mean, rms, p95, per_track, int((usable(shots) & ~measured).sum()))


def spot_normals(spots_km: np.ndarray, origins_km: np.ndarray, neighbours: int = LIDAR.normal_neighbours) -> np.ndarray:
    """(N, 3) unit normals of the surface through the spots: the least-variance direction of each
    spot's `neighbours` nearest, turned towards the spot's shot origin (outside)."""
    if len(spots_km) < 3:
        raise ValueError(f"{len(spots_km)} spots cannot give a surface normal: at least 3 are needed")
    k = min(neighbours, len(spots_km))
    _, which = cKDTree(spots_km).query(spots_km, k=k)
    normals = np.empty_like(spots_km)
    for s in range(0, len(spots_km), _CHUNK):
        near = spots_km[which[s:s + _CHUNK]]
        centred = near - near.mean(axis=1, keepdims=True)
        _, vectors = np.linalg.eigh(np.einsum("nki,nkj->nij", centred, centred))
        normals[s:s + _CHUNK] = vectors[:, :, 0]
    outward = np.einsum("ij,ij->i", normals, origins_km - spots_km) >= 0
    return np.where(outward[:, None], normals, -normals)


def fuse_spots(spots_km: np.ndarray, normals: np.ndarray, *, voxel_km: float, reach_km: float, kernel_km: float,
               base: Mesh | None = None) -> Mesh:
    """The largest connected piece of the surface through the spots (outward unit normals; whether
    it is watertight is the caller's to check, as `model_from_spots` does): at the lattice points within
    reach_km, the mean of the nearest spots' plane distances weighted by a Gaussian of kernel_km
    in their distance beyond the nearest's, fused by pwm.volume.DistanceGrid (with `base` filling
    what they do not reach).

    A spot's tangent plane lies outside a convex surface by the square of the distance from it
    over twice the radius of curvature, so the kernel is kept to about a spot spacing: wider, the
    surface swells by kernel_km squared over the radius (the loop would compound it)."""
    if spots_km.ndim != 2 or spots_km.shape[1:] != (3,) or normals.shape != spots_km.shape or not len(spots_km):
        raise ValueError(f"need (N, 3) spots and normals alike, N > 0: got {spots_km.shape}, {normals.shape}")
    if not (0 < voxel_km <= reach_km and np.isfinite(reach_km) and 0 < kernel_km < np.inf):
        raise ValueError(f"need 0 < voxel_km <= reach_km and kernel_km > 0, finite: got {voxel_km}, "
                         f"{reach_km}, {kernel_km}")
    steps = int(np.ceil(reach_km / voxel_km))
    keys = np.unique(pack(np.floor(spots_km / voxel_km).astype(np.int64)))
    # the lattice points about the spots' cells: their corners, dilated by the reach one axis
    # at a time (each step's duplicates dropped before the next)
    for axis in range(3):
        step = np.zeros((steps + 2 + steps, 3), dtype=np.int64)
        step[:, axis] = np.arange(-steps, steps + 2)
        keys = np.unique(pack((unpack(keys)[:, None, :] + step[None]).reshape(-1, 3)))
    tree = cKDTree(spots_km)
    truncation = DistanceGrid(voxel_km=voxel_km).truncation_km
    weight_parts, distance_parts, kept = [], [], []
    for s in range(0, len(keys), _CHUNK):
        x = unpack(keys[s:s + _CHUNK]) * voxel_km
        gap, which = tree.query(x, k=min(_FUSE_NEIGHBOURS, len(spots_km)), distance_upper_bound=reach_km)
        gap, which = gap.reshape(len(x), -1), which.reshape(len(x), -1)
        found = np.isfinite(gap)
        near = np.where(found, which, 0)
        # weights relative to the nearest spot's, which never underflow to none
        gap = np.where(found, gap, 0.0)
        beyond = np.where(found, gap ** 2 - gap[:, :1] ** 2, 0.0)
        w = np.where(found, np.exp(-0.5 * beyond / kernel_km ** 2), 0.0)
        plane = np.einsum("nkc,nkc->nk", x[:, None, :] - spots_km[near], normals[near])
        total = w.sum(axis=1)
        some = total > 0
        mean = np.where(some, (w * plane).sum(axis=1) / np.where(some, total, 1.0), np.inf)
        # within the grid's truncation of the surface; and over a base, as a maplet's: only over
        # the spots, not beside them, where their planes would reach out over a gap that the
        # base fills (without one, they must: nothing else closes the surface)
        some &= np.abs(mean) <= truncation
        if base is not None:
            some &= gap[:, 0] ** 2 - plane[:, 0] ** 2 <= voxel_km ** 2
        kept.append(keys[s:s + _CHUNK][some])
        weight_parts.append(total[some])
        distance_parts.append(mean[some])
    weight, distance = np.concatenate(weight_parts), np.concatenate(distance_parts)
    columns = np.zeros((len(weight), 4))
    # DistanceGrid's columns: weight, weighted distance, albedo weight, weighted albedo (none)
    columns[:, 0], columns[:, 1] = weight, weight * distance
    grid = DistanceGrid(voxel_km=voxel_km)
    grid.merge(*sum_by_key(np.concatenate(kept), columns, np.ones(len(weight), dtype=np.int64)),
               sign=+1, name="the spots")
    return grid.mesh(base)


def spot_spacing_km(spots_km: np.ndarray) -> float:
    """The median distance of a spot to its nearest neighbour."""
    if len(spots_km) < 2:
        raise ValueError("at least two spots are needed for a spacing")
    gap, _ = cKDTree(spots_km).query(spots_km, k=2)
    spacing = float(np.median(gap[:, 1]))
    if not spacing > 0:
        raise ValueError("the spots coincide: no spacing to build a lattice on")
    return spacing


def model_from_spots(shots: Shots, config: LidarConfig = LIDAR, *, voxel_km: float | None = None) -> Mesh:
    """A closed, watertight mesh of the body from the valid shots' spots alone (the module
    docstring), on a lattice of voxel_km (default: LidarConfig.voxel_spacings spot spacings).
    ValueError where the spots do not enclose the body (the coarse surface is not closed)."""
    valid = usable(shots)
    if valid.sum() < config.normal_neighbours:
        raise ValueError(f"{int(valid.sum())} valid spots cannot make a shape model")
    spots, origins = shots.spots_km()[valid], shots.origin_km[valid]
    normals = spot_normals(spots, origins, config.normal_neighbours)
    # a grazing shot's normal is unreliable (its footprint smears along the surface, and which
    # side faces the shot is nearly a tie): such spots would lay wrong-signed distances
    facing = np.einsum("ij,ij->i", normals, origins - spots) / np.linalg.norm(origins - spots, axis=1)
    steep = facing >= np.cos(np.radians(config.max_incidence_deg))
    spots, normals = spots[steep], normals[steep]
    spacing = spot_spacing_km(spots)
    voxel = config.voxel_spacings * spacing if voxel_km is None else voxel_km
    kernel = config.kernel_spacings * spacing
    coarse_voxel = config.coarse_factor * voxel
    coarse = fuse_spots(spots, normals, voxel_km=coarse_voxel, reach_km=config.reach_voxels * coarse_voxel,
                        kernel_km=config.coarse_factor * kernel)
    shut = closure(coarse)
    if not shut.closed:
        raise ValueError(f"the spots do not enclose the body at {coarse_voxel * 1000:.1f} m: {shut.describe()}")
    # where tracks still disagree by about a kernel (the first model, from unadjusted spots), the
    # distances jump from one track's planes to the next and can open the surface: the kernel is
    # widened until it closes (the narrowest swells the model least)
    for widen in range(config.kernel_widenings + 1):
        model = fuse_spots(spots, normals, voxel_km=voxel, reach_km=config.reach_voxels * voxel,
                           kernel_km=kernel * _WIDEN ** widen, base=coarse)
        shut = closure(model)
        if shut.closed:
            break
    else:
        raise ValueError(f"the lidar model is not one closed surface: {shut.describe()}")
    return model


MAP_CELLS = (36, 18)
"""The residual map's cells in longitude and latitude: 10 degrees square."""


def sample_shots(valid: np.ndarray, at_most: int, *, seed: int = 0) -> np.ndarray:
    """The indices (ascending) of at most `at_most` of the `valid` shots, chosen uniformly at
    random (a fixed seed: the same shots give the same sample)."""
    index = np.flatnonzero(valid)
    if at_most < 0:
        raise ValueError(f"at_most must be >= 0, not {at_most}")
    if len(index) <= at_most:
        return index
    return np.sort(np.random.default_rng(seed).choice(index, size=at_most, replace=False))


def residual_map(spots_km: np.ndarray, distance_km: np.ndarray, cells: tuple[int, int] = MAP_CELLS
                 ) -> list[list[float | None]]:
    """The RMS of the measured distances (finite ones) in each cell of longitude (east, 0-360
    deg) and planetocentric latitude of the spots: rows from the south, columns from longitude
    0; None for a cell with none."""
    measured = np.isfinite(distance_km) & np.isfinite(spots_km).all(axis=1)
    x, y, z = spots_km[measured].T
    d = distance_km[measured]
    lon = np.degrees(np.arctan2(y, x)) % 360.0
    lat = np.degrees(np.arctan2(z, np.hypot(x, y)))
    columns, rows = cells
    col = np.minimum((lon / (360.0 / columns)).astype(np.int64), columns - 1)
    row = np.minimum(((lat + 90.0) / (180.0 / rows)).astype(np.int64), rows - 1)
    cell = row * columns + col
    count = np.bincount(cell, minlength=rows * columns)
    square = np.bincount(cell, weights=d ** 2, minlength=rows * columns)
    rms = np.sqrt(square / np.maximum(count, 1))
    return [[float(rms[r * columns + c]) if count[r * columns + c] else None for c in range(columns)]
            for r in range(rows)]


def residual_summary(shots: Shots, mesh: Mesh, track: np.ndarray, *, config: LidarConfig = LIDAR,
                     cells: tuple[int, int] = MAP_CELLS) -> dict:
    """A model's lidar statistics from these shots (`lidar_residuals`): the shots given and
    measured, those that met no surface near their spot, mean, RMS and 95th percentile of the
    signed distances (km) overall and per track ({track: {shots, mean_km, rms_km, p95_km}}),
    and the RMS map (`residual_map`, km). JSON-ready."""
    residuals = lidar_residuals(shots, mesh, track, config=config)
    measured = np.isfinite(residuals.distance_km)
    counts = dict(zip(*np.unique(np.asarray(track)[measured], return_counts=True), strict=True))

    def figures(mean: float, rms: float, p95: float) -> dict[str, float | None]:
        return {"mean_km": _finite(mean), "rms_km": _finite(rms), "p95_km": _finite(p95)}

    return {"shots": len(shots), "measured": int(measured.sum()), "missed": residuals.missed,
            **figures(residuals.mean_km, residuals.rms_km, residuals.p95_km),
            "tracks": {str(t): {"shots": int(counts.get(t, 0)), **figures(*v)} for t, v in residuals.per_track.items()},
            "map": {"lon_cells": cells[0], "lat_cells": cells[1],
                    "rms_km": residual_map(shots.spots_km(), residuals.distance_km, cells)}}


def disagreement(figures: dict, placement_km: float | None) -> float | None:
    """How far a track's spots lie off a model on the mean, in its own sigmas: |mean| over the
    root sum of squares of its placement's sigma (placement_km, from its strip correction) and
    its spots' scatter over their number (figures: one track's of `residual_summary`). None
    where the track is not placed (never corrected, or free in some direction) or not measured."""
    mean, rms, shots = figures.get("mean_km"), figures.get("rms_km"), figures.get("shots", 0)
    if placement_km is None or not np.isfinite(placement_km) or mean is None or rms is None or not shots:
        return None
    sigma = float(np.hypot(placement_km, rms / np.sqrt(shots)))
    return abs(mean) / sigma if sigma > 0 else None


def _finite(value: float) -> float | None:
    return float(value) if np.isfinite(value) else None
