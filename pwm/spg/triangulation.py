"""Tracks from pairwise matches, and their triangulation with known poses (body-fixed, km)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from pwm.camera import Camera, Pose, project


@dataclass
class Tracks:
    """Observations of surface points: observation k is point `point[k]` seen in image
    `image[k]` at `xy[k]` (sample, line), px."""

    point: np.ndarray
    image: np.ndarray
    xy: np.ndarray

    @property
    def n_points(self) -> int:
        return int(self.point.max()) + 1 if len(self.point) else 0

    def joined(self, other: Tracks) -> Tracks:
        """These observations and `other`'s, whose points are numbered after these."""
        return Tracks(point=np.concatenate([self.point, other.point + self.n_points]).astype(np.int64),
                      image=np.concatenate([self.image, other.image]).astype(np.int64),
                      xy=np.concatenate([self.xy.reshape(-1, 2), other.xy.reshape(-1, 2)]))

    def subset(self, keep: np.ndarray) -> Tracks:
        """The observations where `keep`, dropping points left with fewer than two, renumbered."""
        point, image, xy = self.point[keep], self.image[keep], self.xy[keep]
        count = np.bincount(point, minlength=self.n_points)
        ok = count[point] >= 2
        _, renumbered = np.unique(point[ok], return_inverse=True)
        return Tracks(point=renumbered.astype(np.int64), image=image[ok], xy=xy[ok])


def build_tracks(matches: dict[tuple[int, int], np.ndarray], keypoints: list[np.ndarray]) -> Tracks:
    """Join pairwise matches {(i, j): (k, 2) keypoint indices} into tracks over the keypoints
    `keypoints[i]` ((n_i, 2) px). A track that meets one image twice is inconsistent and dropped."""
    offsets = np.concatenate([[0], np.cumsum([len(k) for k in keypoints])])
    edges = [np.column_stack([offsets[i] + m[:, 0], offsets[j] + m[:, 1]]) for (i, j), m in matches.items() if len(m)]
    if not edges:
        return Tracks(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 2)))
    e = np.concatenate(edges)
    n = int(offsets[-1])
    graph = coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(n, n))
    _, label = connected_components(graph, directed=False)
    used = np.zeros(n, bool)
    used[e.ravel()] = True
    node = np.flatnonzero(used)
    image = np.searchsorted(offsets, node, side="right") - 1
    track = label[node]
    # a track with two keypoints in one image joined different surface points
    order = np.lexsort((image, track))
    dup = (np.diff(track[order]) == 0) & (np.diff(image[order]) == 0)
    bad = np.zeros(n, bool)
    bad[track[order][1:][dup]] = True
    keep = ~bad[track]
    xy = np.concatenate(keypoints)[node]
    _, point = np.unique(track[keep], return_inverse=True)
    return Tracks(point=point.astype(np.int64), image=image[keep].astype(np.int64), xy=xy[keep])


def rays(tracks: Tracks, cameras: list[Camera], poses: list[Pose]) -> tuple[np.ndarray, np.ndarray]:
    """Origins (km) and unit directions (body-fixed) of every observation's line of sight."""
    origins = np.array([p.position for p in poses])[tracks.image]
    dirs = np.empty((len(tracks.image), 3))
    for i in np.unique(tracks.image):
        k = tracks.image == i
        dirs[k] = poses[i].to_body_directions(cameras[i].pixel_directions(tracks.xy[k, 0], tracks.xy[k, 1]))
    return origins, dirs


def triangulate(tracks: Tracks, cameras: list[Camera], poses: list[Pose]) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares intersection of each track's rays (km, body-fixed) and its largest angle
    between a ray and the mean ray (rad)."""
    origins, dirs = rays(tracks, cameras, poses)
    n = tracks.n_points
    centre = origins.mean(axis=0)
    proj = np.eye(3) - dirs[:, :, None] * dirs[:, None, :]
    a = np.zeros((n, 3, 3))
    b = np.zeros((n, 3))
    np.add.at(a, tracks.point, proj)
    np.add.at(b, tracks.point, np.einsum("kij,kj->ki", proj, origins - centre))
    points = np.linalg.solve(a + 1e-12 * np.eye(3), b[:, :, None])[:, :, 0] + centre
    mean_dir = np.zeros((n, 3))
    np.add.at(mean_dir, tracks.point, dirs)
    mean_dir /= np.linalg.norm(mean_dir, axis=1, keepdims=True)
    angle = np.zeros(n)
    np.maximum.at(angle, tracks.point, np.arccos(np.clip(np.einsum("ij,ij->i", dirs, mean_dir[tracks.point]), -1, 1)))
    return points, angle


def reprojection_errors(points: np.ndarray, tracks: Tracks, cameras: list[Camera], poses: list[Pose]) -> np.ndarray:
    """Distance (px) between each observation and its point projected with the poses; inf
    where the point is behind the camera."""
    err = np.empty(len(tracks.image))
    for i in np.unique(tracks.image):
        k = tracks.image == i
        p = points[tracks.point[k]]
        behind = poses[i].to_camera(p)[:, 2] <= 0
        err[k] = np.where(behind, np.inf, np.linalg.norm(project(p, cameras[i], poses[i]) - tracks.xy[k], axis=1))
    return err
