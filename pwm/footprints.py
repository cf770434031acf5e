"""Where on the surface the images see well enough to refine, and how finely (METHOD.md 4).

Each image's footprint is sampled by rays through a grid of up to FOOTPRINT_SAMPLES x
FOOTPRINT_SAMPLES of its pixels onto the shape (ground that several images sample is kept
once, at half the finest spacing of any footprint's samples); every sample is then judged in
every image as a maplet's node would be (pwm.weights.Rules): in the frame, in front, facing
the camera within the SPC emission rule, lit, not occluded. A sample that at least min_images
images see so is seen; its pixel scale is the median of theirs (range over focal length).

Seen samples are grouped into places: samples of one octave of pixel scale, linked within two
maplet sides at that scale; each place is tiled at spacing_gsd times its median pixel scale. A
global survey makes one place of the whole body, a downlink over two sites two places, a
downlink with a survey and a close pass two places of different spacings. Lengths in km.
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
from pwm.views import View
from pwm.weights import Rules

FOOTPRINT_SAMPLES = 48
"""Rays per side of an image's pixel grid that sample its footprint, at most ..."""
SAMPLE_PX = 8
"""... and at least this many pixels apart (a small detector window gets few)."""


@dataclass(frozen=True)
class Place:
    """Seen surface samples (N, 3) that one tiling covers, and the node spacing it gets."""

    points: np.ndarray
    spacing_km: float

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


def seen_samples(tracer: RayTracer, views: Sequence[View], *, judged_by: Sequence[View] | None = None,
                 rules: Rules, min_images: int) -> Seen:
    """The samples of the views' footprints on the shape that at least min_images of the views
    `judged_by` (by default the same) see usably (see the module docstring)."""
    judges = views if judged_by is None else judged_by
    sampled = [_footprint(tracer, v) for v in views]
    if not sum(len(p) for p, _ in sampled):
        return Seen(np.empty((0, 3)), np.empty(0))
    points, normals = _once(sampled)
    lifted = points + tracer.offset * normals
    pixel = np.full((len(judges), len(points)), np.nan)
    cos_emission = np.cos(np.radians(rules.max_emission_deg))
    cos_lit = np.cos(np.radians(rules.incidence_zero_deg))
    for k, view in enumerate(judges):
        to_camera = view.pose.position - points
        distance = np.linalg.norm(to_camera, axis=1)
        to_camera /= distance[:, None]
        usable = (np.einsum("ij,ij->i", normals, to_camera) >= cos_emission) & (normals @ view.sun > cos_lit)
        ahead = usable & (view.pose.to_camera(points)[:, 2] > 0)
        px = np.full((len(points), 2), -1.0)
        px[ahead] = project(points[ahead], view.camera, view.pose)
        usable = ahead & (px[:, 0] >= 0) & (px[:, 0] <= view.camera.width - 1) & (px[:, 1] >= 0) & (
            px[:, 1] <= view.camera.height - 1)
        idx = np.flatnonzero(usable)
        blocked = tracer.occluded(lifted[idx], to_camera[idx], distance[idx])
        idx = idx[~blocked]
        pixel[k, idx] = distance[idx] / view.camera.fx
    enough = np.isfinite(pixel).sum(axis=0) >= min_images
    return Seen(points[enough], np.nanmedian(pixel[:, enough], axis=0) if enough.any() else np.empty(0))


def places(seen: Seen, *, nodes: int, spacing_gsd: float) -> list[Place]:
    """The seen samples grouped into places (see the module docstring), largest first."""
    out = []
    octave = np.floor(np.log2(seen.pixel_km)).astype(np.int64)
    for o in np.unique(octave):
        member = np.flatnonzero(octave == o)
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
