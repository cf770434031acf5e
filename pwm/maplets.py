"""Maplets: square height grids in local surface frames, the unit of refinement.

A maplet's nodes sit on a regular x-y grid of its local frame (pwm.frames.LocalFrame): node (i, j)
at x = (j - c) * spacing, y = (i - c) * spacing with c = (n - 1) / 2, and its surface point at
height h[i, j] along the frame's z. Heights and spacing in km; albedo is the normal albedo.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from pwm.frames import LocalFrame


@dataclass
class MapletGrid:
    """One maplet. heights, albedo: (n, n) arrays indexed [i (y), j (x)]; weight: region weight
    w_PWM of the latest refinement (1 before any)."""

    name: str
    frame: LocalFrame
    spacing_km: float
    heights: np.ndarray
    albedo: np.ndarray | None = None
    weight: float = 1.0
    meta: dict = field(default_factory=dict)

    @property
    def n(self) -> int:
        return self.heights.shape[0]

    @property
    def axis_km(self) -> np.ndarray:
        """Node coordinates along the local x (and y) axis, km."""
        return (np.arange(self.n) - (self.n - 1) / 2) * self.spacing_km

    def nodes_local(self, heights: np.ndarray | None = None) -> np.ndarray:
        """(n, n, 3) local coordinates of the nodes (km)."""
        h = self.heights if heights is None else heights
        x, y = np.meshgrid(self.axis_km, self.axis_km)
        return np.stack([x, y, h], axis=-1)

    def normals_body(self, heights: np.ndarray | None = None) -> np.ndarray:
        """(n, n, 3) unit surface normals at the nodes, body-fixed, from central differences."""
        h = self.heights if heights is None else heights
        dz_dy, dz_dx = np.gradient(h, self.spacing_km)
        local = np.stack([-dz_dx, -dz_dy, np.ones_like(h)], axis=-1)
        local /= np.linalg.norm(local, axis=-1, keepdims=True)
        return local @ self.frame.rotation

    def nodes_body(self, heights: np.ndarray | None = None) -> np.ndarray:
        """(n, n, 3) body-fixed coordinates of the nodes (km)."""
        return self.frame.to_body(self.nodes_local(heights).reshape(-1, 3)).reshape(self.n, self.n, 3)


def flat_grid(name: str, frame: LocalFrame, *, size_km: float, nodes: int) -> MapletGrid:
    """A maplet of nodes x nodes over the square of side size_km of `frame`, its heights zero
    (to be sampled from a shape, pwm.tiling.sample_surface): a catalogued maplet's grid."""
    return MapletGrid(name=name, frame=frame, spacing_km=size_km / (nodes - 1), heights=np.zeros((nodes, nodes)))
