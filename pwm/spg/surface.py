"""A watertight surface through sparse stereo points, at the resolution the points support:
over a previous model, its vertices moved along their normals towards the points near them (where
there are no points the model stays); over a figure (the PCK ellipsoid of a body with no model
yet), the points' offsets interpolated over the whole surface by the smoothest field."""

from __future__ import annotations

import numpy as np
from scipy import sparse
from scipy.sparse.linalg import spsolve
from scipy.spatial import cKDTree

from pwm.decimate import decimate
from pwm.evaluate.distance import ClosestPoint
from pwm.mesh import Mesh

FIGURE_SMOOTHING = 3.0
"""fit_figure bends over this many mean point spacings (the surface's area per point): the
figure's error is a body's shape, kilometre-long, and a cluster of points should move the
surface between the clusters, not leave a dimple under each."""
_FIGURE_ROUNDS = 3


def point_spacing(points: np.ndarray) -> float:
    """Median distance (km) from each point to its nearest neighbour."""
    d, _ = cKDTree(points).query(points, k=2)
    return float(np.median(d[:, 1]))


def at_resolution(model: Mesh, edge_km: float, points: np.ndarray, *, max_faces: int = 4_000_000) -> Mesh:
    """`model` with edges of about `edge_km` where the `points` lie: decimated where it is much
    finer, split 1-to-4 (everywhere, which keeps it watertight) while it is much coarser there."""
    if model.mean_edge_length() < 0.5 * edge_km:
        area = float(model.face_areas().sum())
        target = int(area / (np.sqrt(3) / 4 * edge_km**2))
        return decimate(model, max(target, 4)) if target < len(model.faces) else model
    while _local_edge(model, points) > 2.0 * edge_km and 4 * len(model.faces) <= max_faces:
        model = subdivide(model)
    return model


def _local_edge(model: Mesh, points: np.ndarray) -> float:
    """Mean edge length (km) of the faces nearest the points."""
    centroids = model.vertices[model.faces].mean(axis=1)
    _, near = cKDTree(centroids).query(points)
    v = model.vertices[model.faces[np.unique(near)]]
    return float(np.linalg.norm(v - np.roll(v, 1, axis=1), axis=2).mean())


def subdivide(mesh: Mesh) -> Mesh:
    """Midpoint 1-to-4 split of every face (km, same frame; the albedo is dropped)."""
    f = mesh.faces
    edges = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
    unique, inverse = np.unique(edges, axis=0, return_inverse=True)
    mid = len(mesh.vertices) + inverse.reshape(3, -1)
    vertices = np.concatenate([mesh.vertices, mesh.vertices[unique].mean(axis=1)])
    a, b, c = f[:, 0], f[:, 1], f[:, 2]
    ab, bc, ca = mid
    faces = np.concatenate([np.column_stack(t) for t in ((a, ab, ca), (ab, b, bc), (ca, bc, c), (ab, bc, ca))])
    return Mesh(vertices, faces)


def _neighbour_mean(mesh: Mesh) -> sparse.csr_matrix:
    """Row-normalised vertex adjacency: (A @ f)[v] is the mean of f over v's neighbours."""
    f = mesh.faces
    i = np.concatenate([f[:, 0], f[:, 1], f[:, 2], f[:, 1], f[:, 2], f[:, 0]])
    j = np.concatenate([f[:, 1], f[:, 2], f[:, 0], f[:, 0], f[:, 1], f[:, 2]])
    a = sparse.csr_matrix((np.ones(len(i)), (i, j)), shape=(len(mesh.vertices),) * 2)
    a.data[:] = 1.0
    return sparse.diags(1.0 / np.maximum(np.asarray(a.sum(axis=1)).ravel(), 1.0)) @ a


def fit_surface(model: Mesh, points: np.ndarray, *, radius_km: float, neighbours: int = 16, prior_weight: float = 0.5,
                smoothing: int = 2) -> Mesh:
    """Move each vertex of `model` along its normal by a robust, distance-weighted mean of the
    normal offsets of the `neighbours` nearest points within `radius_km` (km, body-fixed).

    The offsets are first shrunk towards zero by `prior_weight` (in units of one nearby point's
    weight), so the previous model takes over smoothly where points thin out; outliers beyond
    three robust sigmas of the neighbourhood median are ignored; then `smoothing` passes of
    neighbour averaging take out the point noise. The topology is the model's, so a watertight
    model stays watertight.
    """
    normals = model.vertex_normals()
    dist, idx = cKDTree(points).query(model.vertices, k=neighbours, distance_upper_bound=radius_km)
    found = np.isfinite(dist)
    idx = np.where(found, idx, 0)
    offset = np.einsum("vkj,vj->vk", points[idx] - model.vertices[:, None, :], normals)
    lateral2 = np.maximum(dist**2 - offset**2, 0.0)
    weight = np.where(found, np.exp(-0.5 * lateral2 / (0.5 * radius_km) ** 2), 0.0)
    median, mad = np.zeros(len(offset)), np.zeros(len(offset))
    some = found.any(axis=1)
    masked = np.where(found[some], offset[some], np.nan)
    median[some] = np.nanmedian(masked, axis=1)
    mad[some] = np.nanmedian(np.abs(masked - median[some, None]), axis=1)
    inlier = found & (np.abs(offset - median[:, None]) <= 3.0 * 1.4826 * mad[:, None] + 1e-12)
    weight = np.where(inlier, weight, 0.0)
    total = weight.sum(axis=1)
    height = np.einsum("vk,vk->v", weight, np.where(found, offset, 0.0)) / (total + prior_weight)
    mean = _neighbour_mean(model)
    for _ in range(smoothing):
        height = 0.5 * height + 0.5 * (mean @ height)
    return Mesh(model.vertices + height[:, None] * normals, model.faces)


def fit_figure(figure: Mesh, points: np.ndarray, *, smoothing: float = FIGURE_SMOOTHING) -> Mesh:
    """Move the vertices of `figure` (a body's reference figure, its PCK ellipsoid, at the
    resolution the points support) along their normals by the smoothest field of offsets that
    meets the `points` (km, body-fixed): least squares over the points' normal offsets (at their
    closest points, interpolated from the face's vertices) plus the bending of the field (the
    umbrella Laplacian, a thin plate) weighted so that it bends over `smoothing` mean point
    spacings, whatever the mesh's edge length. Unlike fit_surface, places far from any point
    move too: a figure is wrong everywhere, and smoothly. Fitted FIGURE_ROUNDS times, each
    leaving out the points beyond three robust sigmas of the last fit (mismatches)."""
    keep = np.ones(len(points), dtype=bool)
    spacing = float(np.sqrt(figure.face_areas().sum() / max(len(points), 1)))
    bending = smoothing * spacing / figure.mean_edge_length()
    n = len(figure.vertices)
    laplacian = sparse.identity(n) - _neighbour_mean(figure)
    regular = bending**2 * (laplacian.T @ laplacian) + 1e-9 * sparse.identity(n)
    _, closest, face = ClosestPoint(figure).query(points)
    offset = np.einsum("ij,ij->i", points - closest, figure.face_normals()[face])
    corners = figure.faces[face]
    design = sparse.csr_matrix((_barycentric(figure.vertices[corners], closest).ravel(),
                                (np.repeat(np.arange(len(points)), 3), corners.ravel())), shape=(len(points), n))
    for _ in range(_FIGURE_ROUNDS):
        used = sparse.diags(keep.astype(float)) @ design
        height = spsolve((used.T @ used + regular).tocsc(), used.T @ offset)
        residual = np.abs(design @ height - offset)
        keep = residual <= 3.0 * 1.4826 * np.median(residual[keep]) + 1e-12
    return Mesh(figure.vertices + height[:, None] * figure.vertex_normals(), figure.faces)


def _barycentric(triangles: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(N, 3) barycentric coordinates of points on (N, 3, 3) triangles (clipped to the face)."""
    a = triangles[:, 0]
    u, v, w = triangles[:, 1] - a, triangles[:, 2] - a, points - a
    uu, uv, vv = (u * u).sum(1), (u * v).sum(1), (v * v).sum(1)
    wu, wv = (w * u).sum(1), (w * v).sum(1)
    det = np.maximum(uu * vv - uv**2, 1e-300)
    b1, b2 = (vv * wu - uv * wv) / det, (uu * wv - uv * wu) / det
    return np.clip(np.column_stack([1.0 - b1 - b2, b1, b2]), 0.0, 1.0)
