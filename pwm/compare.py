"""Height change between two shape models of one body (body-fixed frame, km in, m out).

The change at a vertex of the new model is its height above the old surface along the new
model's outward vertex normal: a ray from max_distance_km above the vertex, cast down the
normal, meets the old surface at distance t, so the change is t - max_distance_km (positive
where the new surface lies above the old). Vertices where the old surface is not within
max_distance_km either way are not compared. Statistics are weighted by the area each vertex
stands for (a third of its faces'), since fused regions are meshed far finer than the base.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pwm.mesh import Mesh
from pwm.raytrace import RayTracer


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


def height_change(old: Mesh, new: Mesh, *, max_distance_km: float = 0.01) -> HeightChange:
    """The signed height change of every vertex of `new` from the `old` surface (see the module
    docstring); max_distance_km must stay well below the body's radius."""
    normals = new.vertex_normals()
    origins = new.vertices + max_distance_km * normals
    hits = RayTracer(old).intersect(origins, -normals)
    change = hits.t - max_distance_km
    change[~hits.hit | (hits.t > 2.0 * max_distance_km)] = np.nan
    return HeightChange(change_m=change * 1e3, area_m2=vertex_areas(new) * 1e6)
