"""Choose image pairs for stereo matching from the views' geometry alone: where two images
overlap on the previous model, the stereo angle between them there, and how much the Sun moved
between them (feature descriptors do not survive large illumination changes)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pwm.camera import Camera, project
from pwm.raytrace import RayTracer
from pwm.spg.config import SPG_DEFAULTS, SpgConfig
from pwm.views import View


@dataclass(frozen=True)
class Pair:
    """Two views (indices) worth matching. overlap: fraction of the first view's footprint seen
    by the second; stereo_deg: angle between the lines of sight at the common footprint;
    sun_deg: angle between the two Sun directions (body-fixed)."""

    first: int
    second: int
    overlap: float
    stereo_deg: float
    sun_deg: float


@dataclass(frozen=True)
class Footprint:
    """Surface points (body-fixed, km) seen through a grid of pixels of one view, with the
    model's normals there and those pixels (sample, line)."""

    points: np.ndarray
    normals: np.ndarray
    pixels: np.ndarray

    def window(self, camera: Camera, *, margin_px: float) -> tuple[slice, slice]:
        """(lines, samples) slices of the frame around the pixels that see the model, `margin_px`
        wider on each side (the whole frame when none does)."""
        if len(self.pixels) == 0:
            return slice(0, camera.height), slice(0, camera.width)
        lo = np.floor(self.pixels.min(axis=0) - margin_px).astype(int)
        hi = np.ceil(self.pixels.max(axis=0) + margin_px).astype(int) + 1
        return (slice(max(lo[1], 0), min(hi[1], camera.height)), slice(max(lo[0], 0), min(hi[0], camera.width)))


def footprints(views: list[View], tracer: RayTracer, *, config: SpgConfig = SPG_DEFAULTS) -> list[Footprint]:
    """Where a lattice of `config.footprint_grid` x `config.footprint_grid` of each view's pixels
    meets the model."""
    grid = config.footprint_grid
    out = []
    for v in views:
        s, line = np.meshgrid(np.linspace(0, v.camera.width - 1, grid), np.linspace(0, v.camera.height - 1, grid))
        dirs = v.pose.to_body_directions(v.camera.pixel_directions(s.ravel(), line.ravel()))
        origins = np.broadcast_to(v.pose.position, dirs.shape)
        hits = tracer.intersect(origins, dirs)
        points = tracer.hit_points(origins, dirs, hits)[hits.hit]
        out.append(Footprint(points=points, normals=tracer.face_normals[hits.face[hits.hit]],
                             pixels=np.column_stack([s.ravel(), line.ravel()])[hits.hit]))
    return out


def _seen_by(footprint: Footprint, view: View) -> np.ndarray:
    """True for footprint points inside `view`'s frame on surfaces facing it (no occlusion test)."""
    to_camera = view.pose.position - footprint.points
    facing = np.einsum("ij,ij->i", to_camera, footprint.normals) > 0
    in_front = view.pose.to_camera(footprint.points)[:, 2] > 0
    px = project(footprint.points, view.camera, view.pose)
    inside = ((px[:, 0] >= 0) & (px[:, 0] <= view.camera.width - 1)
              & (px[:, 1] >= 0) & (px[:, 1] <= view.camera.height - 1))
    return facing & in_front & inside


def _angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    c = np.dot(a, b) / (np.linalg.norm(a) * np.linalg.norm(b))
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


def choose_pairs(views: list[View], prints: list[Footprint], *, config: SpgConfig = SPG_DEFAULTS) -> list[Pair]:
    """Pairs (first < second) that overlap by at least `config.min_overlap` (of either
    footprint), see the common ground at a stereo angle within `config.stereo_deg` (deg) and
    under Suns at most `config.max_sun_deg` apart. Each image keeps its `config.per_image` best
    partners (by overlap over the Sun angle); a pair stays when either image keeps it. prints:
    the views' `footprints`."""
    min_overlap, stereo_deg = config.min_overlap, config.stereo_deg
    candidates: dict[tuple[int, int], Pair] = {}
    for i, fi in enumerate(prints):
        for j in range(i + 1, len(views)):
            if len(fi.points) == 0 or len(prints[j].points) == 0:
                continue
            sun = _angle_deg(views[i].sun, views[j].sun)
            if sun > config.max_sun_deg:
                continue
            seen_ij, seen_ji = _seen_by(fi, views[j]), _seen_by(prints[j], views[i])
            overlap = max(seen_ij.mean(), seen_ji.mean())
            if overlap < min_overlap:
                continue
            common = np.concatenate([fi.points[seen_ij], prints[j].points[seen_ji]]).mean(axis=0)
            stereo = _angle_deg(views[i].pose.position - common, views[j].pose.position - common)
            if stereo_deg[0] <= stereo <= stereo_deg[1]:
                candidates[(i, j)] = Pair(i, j, float(overlap), stereo, sun)
    kept: set[tuple[int, int]] = set()
    for k in range(len(views)):
        mine = [p for key, p in candidates.items() if k in key]
        mine.sort(key=lambda p: p.overlap / (1.0 + p.sun_deg / 10.0), reverse=True)
        kept.update((p.first, p.second) for p in mine[:config.per_image])
    return [candidates[key] for key in sorted(kept)]
