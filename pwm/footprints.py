"""Where on the surface the images see well enough to refine, and how finely (METHOD.md 4).

Each image's footprint is sampled by rays through a grid of up to FOOTPRINT_SAMPLES x
FOOTPRINT_SAMPLES of its pixels onto the shape (ground that several images sample is kept
once, at half the finest spacing of any footprint's samples); every sample is then judged in
every image as a maplet's node would be (pwm.weights.Rules): in the frame, in front, facing
the camera within the SPC emission rule, lit, not occluded. A sample that at least min_images
images see so is seen; its pixel scale (range over focal length) is the median of the finest of
those images that are enough: those no more than twice as coarse as the min_images-th finest
(SPC's rule that no image be over twice as coarse as the maplet), so that where a site's close
images and a survey's far ones both look, the site's decide.

Seen samples are grouped into places: samples of one level (pwm.tiling.level_of: an octave of
node spacing, spacing_gsd times the pixel scale), linked within two maplet sides at that scale;
each place is tiled at spacing_gsd times its median pixel scale. A global survey makes one place
of the whole body, a downlink over two sites two places, a downlink with a survey and a close
pass two places of different levels. Lengths in km.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from pwm.camera import project
from pwm.raytrace import RayTracer
from pwm.tiling import level_of
from pwm.views import Cones, View
from pwm.weights import Rules

FOOTPRINT_SAMPLES = 48
"""Rays per side of an image's pixel grid that sample its footprint, at most ..."""
SAMPLE_PX = 8
"""... and at least this many pixels apart (a small detector window gets few)."""
CELLS_PER_SIDE = 16
"""Cells along the longest extent of the samples, by which judges choose what they may see."""


@dataclass(frozen=True)
class Place:
    """Seen surface samples (N, 3) that one tiling covers, and the node spacing it gets."""

    points: np.ndarray
    spacing_km: float

    @property
    def level(self) -> int:
        """The level of the place's spacing (pwm.tiling.level_of)."""
        return int(level_of(self.spacing_km))

    @property
    def centre(self) -> np.ndarray:
        """The samples' surface point nearest their mean."""
        mean = self.points.mean(axis=0)
        return self.points[np.argmin(np.linalg.norm(self.points - mean, axis=1))]


@dataclass(frozen=True)
class Seen:
    """Surface samples (N, 3) seen by enough images, and the median pixel scale there (km/px)."""

    points: np.ndarray
    pixel_km: np.ndarray


@dataclass(frozen=True)
class Samples:
    """Surface samples (N, 3) of footprints and the shape's unit normals there (N, 3)."""

    points: np.ndarray
    normals: np.ndarray

    def cells(self) -> tuple[np.ndarray, float, np.ndarray]:
        """The samples binned into cubes, CELLS_PER_SIDE along their longest extent: the cubes'
        centres (C, 3), the radius of the ball about each that holds its cube (km), and each
        sample's cube (N,) -- to choose the views that may see them by their cones."""
        if not len(self.points):
            return np.empty((0, 3)), 0.0, np.empty(0, dtype=np.int64)
        low = self.points.min(axis=0)
        side = max(float(np.ptp(self.points, axis=0).max()) / CELLS_PER_SIDE, 1e-9)
        # the farthest samples lie on the last cubes' far faces, not in cubes beyond
        index = np.minimum(np.floor((self.points - low) / side), CELLS_PER_SIDE - 1).astype(np.int64)
        keys, inverse = np.unique(index, axis=0, return_inverse=True)
        return low + (keys + 0.5) * side, 0.5 * np.sqrt(3.0) * side, inverse.reshape(-1)


def seen_samples(tracer: RayTracer, views: Sequence[View], *, judged_by: Sequence[View] | None = None,
                 rules: Rules, min_images: int) -> Seen:
    """The samples of the views' footprints on the shape that at least min_images of the views
    `judged_by` (by default the same) see usably (see the module docstring)."""
    return judge_samples(tracer, footprint_samples(tracer, views), views if judged_by is None else judged_by,
                         rules=rules, min_images=min_images)


def footprint_samples(tracer: RayTracer, views: Sequence[View]) -> Samples:
    """The views' footprints on the shape, sampled by rays (see the module docstring)."""
    sampled = [_footprint(tracer, v) for v in views]
    if not sum(len(p) for p, _ in sampled):
        return Samples(np.empty((0, 3)), np.empty((0, 3)))
    return Samples(*_once(sampled))


def judge_samples(tracer: RayTracer, samples: Samples, judges: Sequence[View], *, rules: Rules,
                  min_images: int) -> Seen:
    """The samples that at least min_images of the judges see usably, with the median pixel
    scale there. Each judge looks only at the cells of samples its cone meets (pwm.views.Cones),
    so that a catalog of many images judges a downlink's footprints in proportion to the images
    that look there."""
    points, normals = samples.points, samples.normals
    if not len(points):
        return Seen(np.empty((0, 3)), np.empty(0))
    centres, radius, cell = samples.cells()
    in_cone = Cones.of(judges).seeing(centres, radius) if judges else np.zeros((0, len(centres)), bool)
    lifted = points + tracer.offset * normals
    pixel = np.full((len(judges), len(points)), np.nan)
    cos_emission = np.cos(np.radians(rules.max_emission_deg))
    cos_lit = np.cos(np.radians(rules.incidence_zero_deg))
    for k, view in enumerate(judges):
        idx = np.flatnonzero(in_cone[k][cell])
        to_camera = view.pose.position - points[idx]
        distance = np.linalg.norm(to_camera, axis=1)
        to_camera /= distance[:, None]
        usable = (np.einsum("ij,ij->i", normals[idx], to_camera) >= cos_emission) & (normals[idx] @ view.sun > cos_lit)
        usable &= view.pose.to_camera(points[idx])[:, 2] > 0
        px = project(points[idx[usable]], view.camera, view.pose)
        usable[usable] = ((px[:, 0] >= 0) & (px[:, 0] <= view.camera.width - 1) & (px[:, 1] >= 0)
                          & (px[:, 1] <= view.camera.height - 1))
        idx, to_camera, distance = idx[usable], to_camera[usable], distance[usable]
        blocked = tracer.occluded(lifted[idx], to_camera, distance)
        pixel[k, idx[~blocked]] = distance[~blocked] / view.camera.fx
    enough = np.isfinite(pixel).sum(axis=0) >= min_images
    if not enough.any():
        return Seen(np.empty((0, 3)), np.empty(0))
    ranked = np.sort(pixel[:, enough], axis=0)  # per sample, finest first, nan (not seen) last
    finest = np.where(ranked <= 2.0 * ranked[min_images - 1], ranked, np.nan)
    return Seen(points[enough], np.nanmedian(finest, axis=0))


def places(seen: Seen, *, nodes: int, spacing_gsd: float) -> list[Place]:
    """The seen samples grouped into places (see the module docstring), largest first."""
    out = []
    level = level_of(spacing_gsd * seen.pixel_km)
    for k in np.unique(level):
        member = np.flatnonzero(level == k)
        points, pixel = seen.points[member], seen.pixel_km[member]
        link = 2.0 * (nodes - 1) * spacing_gsd * float(np.median(pixel))
        pairs = cKDTree(points).query_pairs(link, output_type="ndarray")
        graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(len(points),) * 2)
        _, label = connected_components(graph, directed=False)
        for lab in np.unique(label):
            mine = label == lab
            out.append(Place(points=points[mine], spacing_km=spacing_gsd * float(np.median(pixel[mine]))))
    return sorted(out, key=lambda p: -len(p.points))


def _footprint(tracer: RayTracer, view: View) -> tuple[np.ndarray, np.ndarray]:
    """Surface points under a grid of the view's pixels (misses left out), and the shape's unit
    normals there (its vertex normals interpolated)."""
    samples = np.linspace(0, view.camera.width - 1, _count(view.camera.width))
    lines = np.linspace(0, view.camera.height - 1, _count(view.camera.height))
    s, line = np.meshgrid(samples, lines)
    directions = view.pose.to_body_directions(view.camera.pixel_directions(s.ravel(), line.ravel()))
    origins = np.broadcast_to(view.pose.position, directions.shape)
    hits = tracer.intersect(origins, directions)
    normals = tracer.interpolate(tracer.vertex_normals, hits)[hits.hit]
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    return tracer.hit_points(origins, directions, hits)[hits.hit], normals


def _once(sampled: list[tuple[np.ndarray, np.ndarray]]) -> tuple[np.ndarray, np.ndarray]:
    """The footprints' points and normals, with ground that several images sample (repeats,
    overlaps) kept once: one sample per cell of half the finest spacing of any footprint's samples."""
    points, normals = np.vstack([p for p, _ in sampled]), np.vstack([n for _, n in sampled])
    spacings = [float(np.median(np.linalg.norm(np.diff(p, axis=0), axis=1))) for p, _ in sampled if len(p) > 1]
    if not spacings:
        return points, normals
    _, first = np.unique(np.floor(points / (0.5 * min(spacings))).astype(np.int64), axis=0, return_index=True)
    first.sort()
    return points[first], normals[first]


def _count(pixels: int) -> int:
    """Samples along a side of `pixels` pixels (see FOOTPRINT_SAMPLES, SAMPLE_PX)."""
    return int(min(FOOTPRINT_SAMPLES, max(2, np.ceil((pixels - 1) / SAMPLE_PX) + 1)))
