"""Height change between two shape models of one body (body-fixed frame, km in, m out).

The change at a vertex of the new model is its height above the old surface along the new
model's local vertical (`local_verticals`: its outward normals averaged over about
vertical_scale_km): a ray from max_distance_km above the vertex, cast down that direction, meets
the old surface at distance t, so the change is t - max_distance_km (positive where the new
surface lies above the old). Vertices where the old surface is not within max_distance_km either
way are not compared. Statistics are weighted by the area each vertex stands for (a third of
its faces'), since fused regions are meshed far finer than the base.

Why not each vertex's own normal: on a boulder's wall it is nearly horizontal, and a ray along
it runs sideways until it meets the old surface metres away; a 0.5 m boulder the start model
lacked read as a 2.8 m change (bench/RESULTS.md).
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np

from pwm.mesh import Mesh
from pwm.raytrace import RayTracer
from pwm.voxels import pack, sum_by_key, unpack

VERTICAL_SCALE_KM = 0.005
"""Distance (km) over which the normals are averaged into the local vertical: a few metres, so
that boulders and crater walls do not tilt it."""


@dataclass
class HeightChange:
    """Per vertex of the new model: change (m, nan where not compared) and area (m^2)."""

    change_m: np.ndarray
    area_m2: np.ndarray

    @property
    def compared(self) -> np.ndarray:
        return np.isfinite(self.change_m)

    def mean_m(self) -> float:
        """Area-weighted mean change over the compared vertices, m (0 when none)."""
        c = self.compared
        return float(np.average(self.change_m[c], weights=self.area_m2[c])) if c.any() else 0.0

    def rms_m(self) -> float:
        """Area-weighted RMS change over the compared vertices, m (0 when none)."""
        c = self.compared
        return (float(np.sqrt(np.average(self.change_m[c] ** 2, weights=self.area_m2[c])))
                if c.any() else 0.0)

    def max_abs_m(self) -> float:
        return float(np.abs(self.change_m[self.compared]).max(initial=0.0))

    def changed(self, threshold_m: float) -> np.ndarray:
        """Vertices whose change exceeds threshold_m in magnitude."""
        out = np.zeros(len(self.change_m), dtype=bool)
        out[self.compared] = np.abs(self.change_m[self.compared]) > threshold_m
        return out


def vertex_areas(mesh: Mesh) -> np.ndarray:
    """The area each vertex stands for: a third of the area of its faces (km^2)."""
    return np.bincount(mesh.faces.ravel(), weights=np.repeat(mesh.face_areas() / 3.0, 3),
                       minlength=len(mesh.vertices))


def local_verticals(mesh: Mesh, *, scale_km: float) -> np.ndarray:
    """Unit local vertical at each vertex (N, 3): the vertices' area-weighted outward normals
    summed over the cube of side scale_km that holds it and the 26 around it (linear in the
    number of vertices); the vertex's own normal where they nearly cancel, on a surface thinner
    than scale_km."""
    if not scale_km > 0:
        raise ValueError(f"scale_km must be > 0, got {scale_km}")
    own = mesh.vertex_normals()
    area = vertex_areas(mesh)
    cells = pack(np.floor(mesh.vertices / scale_km))
    code, sums, _ = sum_by_key(cells, np.column_stack([own * area[:, None], area]))
    inverse = np.searchsorted(code, cells)
    keys = unpack(code)
    total = np.zeros_like(sums)
    for step in itertools.product((-1, 0, 1), repeat=3):
        wanted = pack(keys + np.array(step))
        at = np.minimum(np.searchsorted(code, wanted), len(code) - 1)
        found = code[at] == wanted
        total[found] += sums[at[found]]
    vertical = total[inverse, :3]
    length = np.linalg.norm(vertical, axis=1)
    kept = length > 0.25 * total[inverse, 3]  # nearly cancelled: both sides of a thin wall
    vertical[kept] /= length[kept, None]
    vertical[~kept] = own[~kept]
    return vertical


def height_change(old: Mesh, new: Mesh, *, max_distance_km: float = 0.01,
                  vertical_scale_km: float = VERTICAL_SCALE_KM) -> HeightChange:
    """The signed height change of every vertex of `new` from the `old` surface along `new`'s
    local vertical over vertical_scale_km (see the module docstring); max_distance_km must stay
    well below the body's radius."""
    normals = local_verticals(new, scale_km=vertical_scale_km)
    origins = new.vertices + max_distance_km * normals
    hits = RayTracer(old).intersect(origins, -normals)
    change = hits.t - max_distance_km
    change[~hits.hit | (hits.t > 2.0 * max_distance_km)] = np.nan
    return HeightChange(change_m=change * 1e3, area_m2=vertex_areas(new) * 1e6)
