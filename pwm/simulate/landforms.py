"""Craters and boulders over the whole body, for a truth that a global survey can be judged on.

A site's landforms live on its height-field grid (pwm.simulate.terrain); these are placed at
random over a body mesh instead, each in its own local frame (origin on the surface, z the mean
normal about it), and displace the mesh's vertices along that z by the same profiles. Pure
computation on meshes; lengths in km.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from pwm.frames import LocalFrame, local_frame
from pwm.mesh import Mesh, surface_points
from pwm.simulate.terrain import CRATER_EXTENT, Boulder, Crater, boulder_profile, crater_profile, power_law

PLACEMENT_TRIES = 50
"""Candidate centres drawn per landform before the body is declared too crowded."""


@dataclass(frozen=True)
class Landform:
    """A crater or a boulder (`shape`, centred at x = y = 0 of its frame) placed on the body.
    origin_km: its centre on the surface before any landform was added; normal: its frame's z."""

    origin_km: tuple[float, float, float]
    normal: tuple[float, float, float]
    shape: Crater | Boulder

    @property
    def frame(self) -> LocalFrame:
        return local_frame(np.asarray(self.origin_km), np.asarray(self.normal))

    @property
    def reach_km(self) -> float:
        """How far from the centre the landform changes the surface."""
        if isinstance(self.shape, Crater):
            return CRATER_EXTENT * self.shape.diameter_km / 2
        return self.shape.diameter_km / 2


@dataclass(frozen=True)
class Clearing:
    """A place landforms keep out of (a site and its margin): centre on the surface, radius, km."""

    centre_km: np.ndarray
    radius_km: float


def sample_landforms(
    mesh: Mesh, rng: np.random.Generator, *, n_craters: int, n_boulders: int, n_steep: int,
    crater_diameter_km: tuple[float, float], boulder_diameter_km: tuple[float, float],
    clearings: Sequence[Clearing] = (),
) -> list[Landform]:
    """Craters (cumulative size slope 2, depth/diameter 0.1-0.2) and boulders (slope 2.5; the
    first n_steep with near-vertical sides, height/radius 0.6-1, the others rounded caps at
    0.3-0.5) at centres drawn uniformly over the area, boulders apart from each other and
    everything clear of the clearings. ValueError when they cannot all be placed."""
    if not 0 <= n_steep <= n_boulders:
        raise ValueError("n_steep must lie between 0 and n_boulders")
    tree = cKDTree(mesh.vertices)
    normals = mesh.vertex_normals()
    craters = power_law(rng, n_craters, *crater_diameter_km, 2.0)
    depth = craters * rng.uniform(0.1, 0.2, n_craters)
    sizes = power_law(rng, n_boulders, *boulder_diameter_km, 2.5)
    steep = np.arange(n_boulders) < n_steep
    ratio = np.where(steep, rng.uniform(0.6, 1.0, n_boulders), rng.uniform(0.3, 0.5, n_boulders))
    albedo = np.exp(rng.uniform(-0.35, 0.35, n_boulders))

    shapes: list[Crater | Boulder] = [
        Crater(x_km=0.0, y_km=0.0, diameter_km=float(d), depth_km=float(h), rim_height_km=float(0.25 * h))
        for d, h in zip(craters, depth, strict=True)]
    shapes += [Boulder(x_km=0.0, y_km=0.0, diameter_km=float(d), height_km=float(r * d / 2), steep=bool(s),
                       albedo_factor=float(a)) for d, r, s, a in zip(sizes, ratio, steep, albedo, strict=True)]
    placed: list[Landform] = []
    for shape in shapes:
        radius = (CRATER_EXTENT if isinstance(shape, Crater) else 1.0) * shape.diameter_km / 2
        for centre in surface_points(mesh, PLACEMENT_TRIES, rng):
            if any(np.linalg.norm(centre - c.centre_km) < c.radius_km + radius for c in clearings):
                continue
            if isinstance(shape, Boulder) and any(
                    isinstance(p.shape, Boulder) and np.linalg.norm(centre - p.origin_km) < p.reach_km + radius
                    for p in placed):
                continue
            near = tree.query_ball_point(centre, radius)
            normal = normals[near].sum(axis=0) if near else normals[tree.query(centre)[1]]
            normal = normal / np.linalg.norm(normal)
            placed.append(Landform(origin_km=(float(centre[0]), float(centre[1]), float(centre[2])),
                                   normal=(float(normal[0]), float(normal[1]), float(normal[2])), shape=shape))
            break
        else:
            raise ValueError(f"cannot place a {shape.diameter_km * 1e3:g} m landform: the body is too crowded")
    return placed


def apply_landforms(mesh: Mesh, landforms: list[Landform]) -> Mesh:
    """The mesh with each landform's relief added along its normal (and boulders' albedo)."""
    vertices = mesh.vertices.copy()
    albedo = mesh.require_albedo().copy()
    tree = cKDTree(mesh.vertices)
    for form in landforms:
        near = np.asarray(tree.query_ball_point(form.origin_km, 1.5 * form.reach_km), dtype=np.int64)
        if near.size == 0:
            continue
        local = form.frame.to_local(mesh.vertices[near])
        r = np.hypot(local[:, 0], local[:, 1])
        # only the side of the body the landform is on: a thin body's far side may lie within reach
        near, r = near[np.abs(local[:, 2]) < form.reach_km], r[np.abs(local[:, 2]) < form.reach_km]
        shape = form.shape
        if isinstance(shape, Crater):
            relief = crater_profile(shape, r)
        else:
            relief = np.where(r < shape.diameter_km / 2, boulder_profile(shape, r), 0.0)
            albedo[near] *= np.exp(np.log(shape.albedo_factor) * np.clip(relief / (0.1 * shape.height_km), 0.0, 1.0))
        vertices[near] += relief[:, None] * np.asarray(form.normal)
    return Mesh(vertices, mesh.faces, albedo)
