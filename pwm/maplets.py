"""Maplets: square height grids in local surface frames, the unit of refinement.

A maplet's nodes sit on a regular x-y grid of its local frame (pwm.frames.LocalFrame): node (i, j)
at x = (j - c) * spacing, y = (i - c) * spacing with c = (n - 1) / 2, and its surface point at
height h[i, j] along the frame's z. Heights and spacing in km; albedo is the normal albedo.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp

from pwm.frames import LocalFrame


@dataclass
class MapletGrid:
    """One maplet. heights, albedo: (n, n) arrays indexed [i (y), j (x)]; weight: region weight
    w_PWM of the latest refinement (1 before any); sigma: (n, n) each node's 1-sigma height (km,
    pwm.uncertainty; NaN where no image weighed it), None before any refinement."""

    name: str
    frame: LocalFrame
    spacing_km: float
    heights: np.ndarray
    albedo: np.ndarray | None = None
    weight: float = 1.0
    sigma: np.ndarray | None = None
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

    def node_body(self, row: int, col: int) -> np.ndarray:
        """(3,) body-fixed coordinates (km) of the node at [row, col]: one of `nodes_body`."""
        axis = self.axis_km
        return self.frame.to_body(np.array([[axis[col], axis[row], self.heights[row, col]]]))[0]


def flat_grid(name: str, frame: LocalFrame, *, size_km: float, nodes: int) -> MapletGrid:
    """A maplet of nodes x nodes over the square of side size_km of `frame`, its heights zero
    (to be sampled from a shape, pwm.tiling.sample_surface): a catalogued maplet's grid."""
    return MapletGrid(name=name, frame=frame, spacing_km=size_km / (nodes - 1), heights=np.zeros((nodes, nodes)))


@dataclass(frozen=True)
class MapletSpots:
    """Laser altimeter spots over one maplet, in its local frame: (M, 3) km, x and y where each
    spot lies and z the height it measured; sigma_km (M,): each height's 1 sigma."""

    local_km: np.ndarray
    sigma_km: np.ndarray

    @property
    def count(self) -> int:
        return len(self.sigma_km)


NO_SPOTS = MapletSpots(local_km=np.zeros((0, 3)), sigma_km=np.zeros(0))


@dataclass(frozen=True)
class Spots:
    """Laser altimeter spots anywhere: body-fixed (N, 3) km, and each height's 1 sigma (N,) km."""

    body_km: np.ndarray
    sigma_km: np.ndarray


def spots_over(maplet: MapletGrid, spots: Spots) -> MapletSpots:
    """The spots that lie over the maplet's node grid within its side of its heights: farther
    off along its z they measured another surface (the body's far side, a wall facing it), not a
    start a side's length wrong. Spots with no finite positive sigma are left out."""
    body = np.asarray(spots.body_km, float).reshape(-1, 3)
    sigma = np.asarray(spots.sigma_km, float).reshape(-1)
    if not len(body):
        return NO_SPOTS
    local = maplet.frame.to_local(body)
    half = (maplet.n - 1) / 2 * maplet.spacing_km
    over = (np.abs(local[:, 0]) <= half) & (np.abs(local[:, 1]) <= half) & np.isfinite(local).all(axis=1)
    over &= np.isfinite(sigma) & (sigma > 0)
    near = np.abs(local[over, 2] - grid_heights(maplet, local[over, :2])) <= 2 * half
    keep = np.flatnonzero(over)[near]
    return MapletSpots(local_km=local[keep], sigma_km=sigma[keep])


def grid_heights(maplet: MapletGrid, xy_km: np.ndarray, heights: np.ndarray | None = None) -> np.ndarray:
    """(M,) the maplet's heights (km) at local points (M, 2) over its grid, bilinear between nodes."""
    return (interpolation_matrix(maplet, xy_km) @ (maplet.heights if heights is None else heights).ravel())


def solution_change(previous: MapletGrid, refined: MapletGrid) -> float:
    """How far a maplet's refined surface lies from an earlier solution of the same place: the
    RMS over its nodes of their heights above the earlier surface (along the earlier frame's z,
    bilinear between its nodes), in node spacings of `refined`; nodes beyond the earlier grid are
    left out (inf where none is within it). Frames that coincide, as a catalogued maplet's do
    from pass to pass, give the RMS of the height differences node by node."""
    local = previous.frame.to_local(refined.nodes_body().reshape(-1, 3))
    within = np.all(np.abs(local[:, :2]) <= previous.axis_km[-1] * (1 + 1e-9), axis=1)
    if not within.any():
        return float("inf")
    above = local[within, 2] - grid_heights(previous, local[within, :2])
    return float(np.sqrt(np.mean(above**2)) / refined.spacing_km)


def interpolation_matrix(maplet: MapletGrid, xy_km: np.ndarray) -> sp.csr_matrix:
    """(M, n*n) sparse bilinear interpolation from the row-major node grid to local points (M, 2)
    over it (clamped onto the grid's border)."""
    n = maplet.n
    at = np.clip(np.asarray(xy_km, float).reshape(-1, 2) / maplet.spacing_km + (n - 1) / 2, 0.0, n - 1)
    j0 = np.minimum(np.floor(at[:, 0]).astype(np.intp), n - 2)
    i0 = np.minimum(np.floor(at[:, 1]).astype(np.intp), n - 2)
    fj, fi = at[:, 0] - j0, at[:, 1] - i0
    rows = np.repeat(np.arange(len(at)), 4)
    cols = np.stack([i0 * n + j0, i0 * n + j0 + 1, (i0 + 1) * n + j0, (i0 + 1) * n + j0 + 1], axis=1).ravel()
    values = np.stack([(1 - fi) * (1 - fj), (1 - fi) * fj, fi * (1 - fj), fi * fj], axis=1).ravel()
    return sp.csr_matrix((values, (rows, cols)), shape=(len(at), n * n))
