"""Shots grouped into tracks, and crossovers between tracks.

A track is a time window over which one rigid correction of the spots suffices (the seed's rule:
the data must not wind too far around the body): shots in time order are split at pauses longer
than LidarConfig.max_gap_s and wherever the sub-spacecraft point (the direction of the
instrument's position from the body's centre) has swept LidarConfig.max_sweep_deg along its path
since the track began. A crossover is a pair of spots of different tracks within a distance;
their height difference along the surface normal says how far apart the two tracks lie there.
A track's extent (`TrackExtent`): its span, and the cone about the body's centre and the box
that hold its spots, by which a catalog finds what it crosses. Lengths in km, body-fixed frame.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from pwm.lidar.config import LIDAR, LidarConfig
from pwm.lidar.shots import Shots

NO_TRACK = -1
"""The track of a shot that is not valid."""

_CROSSOVER_CANDIDATES = 8


def track_ids(shots: Shots, config: LidarConfig = LIDAR) -> np.ndarray:
    """(N,) each shot's track (0, 1, ... in time order; NO_TRACK for invalid shots). Tracks hold
    valid shots only; an invalid shot neither joins nor splits one."""
    valid = shots.valid & np.isfinite(shots.et) & np.isfinite(shots.origin_km).all(axis=1)
    out = np.full(len(shots), NO_TRACK, dtype=np.int64)
    index = np.flatnonzero(valid)
    if not len(index):
        return out
    index = index[np.argsort(shots.et[index], kind="stable")]
    origin = shots.origin_km[index]
    norm = np.linalg.norm(origin, axis=1)
    if not (norm > 0).all():
        raise ValueError("a shot leaves from the body's centre: origin_km must be the instrument's position")
    up = origin / norm[:, None]
    step = np.arccos(np.clip(np.einsum("ij,ij->i", up[1:], up[:-1]), -1.0, 1.0))
    gap = np.diff(shots.et[index]) > config.max_gap_s
    segment = np.concatenate([[0], np.cumsum(gap)])
    swept = np.concatenate([[0.0], np.cumsum(np.where(gap, 0.0, step))])
    # the sweep restarts at each pause: subtract what was swept before the segment began
    starts = np.flatnonzero(np.r_[True, gap])
    swept -= swept[starts][segment]
    window = np.floor(swept / np.radians(config.max_sweep_deg)).astype(np.int64)
    new = np.r_[True, (np.diff(segment) != 0) | (np.diff(window) != 0)]
    out[index] = np.cumsum(new) - 1
    return out


@dataclass(frozen=True)
class TrackExtent:
    """One track's span (TDB s), valid shots, the cone about the body's centre that holds its
    spots (unit axis, half-angle rad) and their bounding box (km)."""

    track: int
    start_et: float
    stop_et: float
    shots: int
    axis: np.ndarray
    half_angle_rad: float
    box_min_km: np.ndarray
    box_max_km: np.ndarray


def track_extents(spots_km: np.ndarray, et: np.ndarray, track: np.ndarray) -> list[TrackExtent]:
    """Each track's extent (NO_TRACK and spots that are not finite left out), by track id. The
    cone's axis is the mean of the spots' unit directions; its half-angle reaches the farthest."""
    keep = (track != NO_TRACK) & np.isfinite(spots_km).all(axis=1) & np.isfinite(et)
    keep &= np.linalg.norm(np.where(np.isfinite(spots_km), spots_km, 0.0), axis=1) > 0
    order = np.flatnonzero(keep)
    if not len(order):
        return []
    order = order[np.argsort(track[order], kind="stable")]
    ids, starts = np.unique(track[order], return_index=True)
    extents = []
    for t, part in zip(ids, np.split(order, starts[1:]), strict=True):
        spots = spots_km[part]
        unit = spots / np.linalg.norm(spots, axis=1)[:, None]
        mean = unit.mean(axis=0)
        # a track wound all about the centre has no mean direction: any axis, the whole sphere
        axis = mean / np.linalg.norm(mean) if np.linalg.norm(mean) > 1e-9 else np.array([0.0, 0.0, 1.0])
        half = float(np.arccos(np.clip(unit @ axis, -1.0, 1.0)).max())
        extents.append(TrackExtent(track=int(t), start_et=float(et[part].min()), stop_et=float(et[part].max()),
                                   shots=len(part), axis=axis, half_angle_rad=half,
                                   box_min_km=spots.min(axis=0), box_max_km=spots.max(axis=0)))
    return extents


@dataclass(frozen=True)
class Crossovers:
    """K crossovers: the shots `first` and `second` (indices into the spots, first's track below
    second's), their distance apart and the height of first above second along first's normal
    (km)."""

    first: np.ndarray
    second: np.ndarray
    distance_km: np.ndarray
    height_km: np.ndarray

    def __len__(self) -> int:
        return len(self.first)

    def rms_km(self) -> float:
        """RMS of the height differences (nan without crossovers)."""
        return float(np.sqrt(np.mean(self.height_km ** 2))) if len(self) else float("nan")


def crossovers(spots_km: np.ndarray, track: np.ndarray, normals: np.ndarray, *,
               radius_km: float = LIDAR.crossover_km) -> Crossovers:
    """Each spot's nearest spot of another track within radius_km (one crossover per pair of
    spots), and the height difference along the first spot's unit normal. Spots of NO_TRACK are
    left out."""
    if not radius_km > 0:
        raise ValueError(f"radius_km must be positive, not {radius_km}")
    if spots_km.shape != normals.shape or spots_km.shape != (len(track), 3):
        raise ValueError("spots_km, normals and track must describe the same spots")
    used = np.flatnonzero((track != NO_TRACK) & np.isfinite(spots_km).all(axis=1))
    empty = np.empty(0)
    if len(used) < 2:
        return Crossovers(empty.astype(np.int64), empty.astype(np.int64), empty, empty)
    points, tracks = spots_km[used], track[used]
    distance, which = cKDTree(points).query(points, k=min(_CROSSOVER_CANDIDATES, len(used)),
                                            distance_upper_bound=radius_km)
    found = np.isfinite(distance)
    other = np.where(found, which, 0)
    # a spot's own track's neighbours are not crossovers; the first of the rest is the nearest
    candidate = found & (tracks[other] != tracks[:, None])
    has = candidate.any(axis=1)
    column = np.argmax(candidate, axis=1)
    a = np.flatnonzero(has)
    b = other[a, column[a]]
    # one crossover per pair, held by the spot of the lower track
    lower = tracks[a] < tracks[b]
    a, b = np.where(lower, a, b), np.where(lower, b, a)
    pairs = np.unique(np.column_stack([a, b]), axis=0)
    a, b = pairs[:, 0], pairs[:, 1]
    first, second = used[a], used[b]
    gap = spots_km[first] - spots_km[second]
    return Crossovers(first, second, np.linalg.norm(gap, axis=1), np.einsum("ij,ij->i", gap, normals[first]))
