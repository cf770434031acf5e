"""The truth asteroid of the proving ground: a real shape with a synthetic high-resolution site.

The base body is a shape model (e.g. the Bennu radar model) loop-subdivided to a target edge,
with optional global fractal roughness and a fractal albedo. At the site, a height-field patch on
a regular grid of the site's local frame (pwm.frames) carries roughness, craters, boulders and
albedo patches; it is blended into the base over a margin and stitched into the body mesh.
Simulated images are rendered from `Truth.mesh`; models are measured against it. Units: km.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from scipy import ndimage
from trimesh.remesh import subdivide_loop

from pwm.frames import LocalFrame, latlon_to_unit, local_frame
from pwm.io.meshio import read_ply, write_ply
from pwm.mesh import Mesh, grid_faces, split_edges
from pwm.raytrace import RayTracer
from pwm.simulate.landforms import Landform
from pwm.simulate.terrain import (
    LARGE_BOULDER_CLEARANCE_KM,
    Boulder,
    Crater,
    add_large_boulders,
    albedo_patches,
    boulder_relief,
    cobble_relief,
    crater_relief,
    fractal_grid,
    gaussian_sigma_km,
    plane_waves,
    sample_boulders,
    sample_craters,
)

BENNU_ALBEDO = 0.044
"""Normal albedo of Bennu (Lauretta et al. 2019)."""

GLOBAL_ALBEDO_LOG_RMS = 0.15
SITE_ALBEDO_LOG_RMS = 0.10
SITE_ROUGHNESS_KM = 3e-5
"""RMS of the site's fractal roughness (3 cm over wavelengths up to the site size)."""

GLOBAL_WAVELENGTHS_KM = (2e-4, 1.0)
"""Wavelength band of the global roughness and albedo waves; fixed so that a field does not depend
on the base resolution (waves below 4 base edges are filtered out at evaluation)."""

RESOLVED_NODES = 4
"""Shortest wavelength of any fractal detail, in grid spacings or mean base edges."""

_STREAMS = {"roughness": 1, "albedo": 2, "site_roughness": 3, "site_albedo": 4, "craters": 5,
            "boulders": 6, "patches": 7, "cobbles": 8, "start_error": 9, "large_boulders": 10}


def _rng(seed: int, stream: str, site: int = 0) -> np.random.Generator:
    """Independent generator per component (and per site after the first), so adding craters
    leaves the roughness unchanged and a second site leaves the first as it was."""
    return np.random.default_rng([seed, _STREAMS[stream]] + ([site] if site else []))


@dataclass
class Truth:
    """The truth asteroid.

    mesh: body mesh with per-vertex albedo (body-fixed, km): base vertices and faces first
    (n_base_vertices, n_base_faces), then the site patch, one vertex per grid node in row-major
    order and two faces per grid cell.
    site_frame: local frame at the site (origin on the base surface, z regional normal, x east).
    x_km, y_km: patch grid axes in the site frame; height_km: (len(y), len(x)) heights along z.
    eval_radius_km: the evaluation region is the disc of this radius about the site origin,
    inscribed in the site square where the detail has full weight.
    zero_band_km: width of the patch border where the detail is zero (the patch lies on the base);
    the detail then ramps up to full weight at the edge of the site square.
    craters, boulders: the features placed, in site-frame coordinates.
    landforms: the craters and boulders placed over the whole body (pwm.simulate.landforms).
    params: the build_truth arguments other than the base shape, for provenance.
    """

    mesh: Mesh
    site_frame: LocalFrame
    site_size_km: float
    x_km: np.ndarray
    y_km: np.ndarray
    height_km: np.ndarray
    eval_radius_km: float
    zero_band_km: float
    craters: list[Crater]
    boulders: list[Boulder]
    n_base_vertices: int
    n_base_faces: int
    landforms: list[Landform] = field(default_factory=list)
    params: dict = field(default_factory=dict)

    @property
    def resolution_km(self) -> float:
        return float(self.x_km[1] - self.x_km[0])

    @property
    def albedo_grid(self) -> np.ndarray:
        """Patch albedo per grid node, (len(y), len(x)) (a view into the mesh albedo)."""
        return self.mesh.require_albedo()[self.n_base_vertices :].reshape(self.height_km.shape)

    def blend_weight(self) -> np.ndarray:
        """Weight of the detail per grid node: 0 in the zero band, 1 in the site square."""
        return _blend_weight(self.x_km, self.y_km, self.zero_band_km, self.site_size_km)

    def patch(self, x_km: float, y_km: float, half_km: float) -> Mesh:
        """The site's grid within half_km of the site point (x_km, y_km) along each axis, as a
        small mesh (body-fixed, km) to drop rays on (pwm.sampling.drop_rays)."""
        cols = np.flatnonzero(np.abs(self.x_km - x_km) <= half_km)
        rows = np.flatnonzero(np.abs(self.y_km - y_km) <= half_km)
        return Mesh(_grid_vertices(self.site_frame, self.x_km[cols], self.y_km[rows],
                                   self.height_km[np.ix_(rows, cols)]), grid_faces(len(rows), len(cols)))

    def site_point(self, x_km: float, y_km: float) -> np.ndarray:
        """The body-fixed point (km) of the site's surface nearest the grid node at (x_km, y_km)."""
        i, j = int(np.abs(self.y_km - y_km).argmin()), int(np.abs(self.x_km - x_km).argmin())
        return self.site_frame.to_body(np.array([[x_km, y_km, self.height_km[i, j]]]))[0]

    def base_mesh(self) -> Mesh:
        """The base body with the hole under the patch (km, with albedo)."""
        return Mesh(self.mesh.vertices[: self.n_base_vertices], self.mesh.faces[: self.n_base_faces],
                    self.mesh.require_albedo()[: self.n_base_vertices])


def build_base(
    base: Mesh, *, base_edge_km: float, seed: int, global_roughness_km: float = 0.0,
    low_pass_km: float | None = None,
) -> Mesh:
    """The base body: `base` loop-subdivided until its mean edge is at most base_edge_km, displaced
    radially by fractal roughness of RMS global_roughness_km, with a fractal albedo about Bennu's.

    low_pass_km: Gaussian cut-off wavelength applied to the roughness, for a smoothed copy of the
    same body (same seed) to start a global model from.
    """
    # shape files may list vertices no face uses (ryugu_test.obj does): subdivision cannot place them
    used = np.unique(base.faces)
    v, f = base.vertices[used], np.searchsorted(used, base.faces)
    edge = base.mean_edge_length()
    # each level halves the edges; measuring them only once keeps fine bodies cheap
    while edge > base_edge_km:
        levels = max(1, int(np.ceil(np.log2(edge / base_edge_km) - 1e-3)))
        v, f = subdivide_loop(v, f, iterations=levels)
        edge = Mesh(v, f).mean_edge_length()
    lo, hi = GLOBAL_WAVELENGTHS_KM
    resolved = RESOLVED_NODES * edge
    albedo = BENNU_ALBEDO * np.exp(GLOBAL_ALBEDO_LOG_RMS * plane_waves(
        _rng(seed, "albedo"), wavelength_min_km=lo, wavelength_max_km=hi)(v, cutoff_km=resolved))
    if global_roughness_km > 0:
        cutoff = max(resolved, low_pass_km or 0.0)
        h = global_roughness_km * plane_waves(_rng(seed, "roughness"), wavelength_min_km=lo,
                                              wavelength_max_km=hi)(v, cutoff_km=cutoff)
        v = v + h[:, None] * (v / np.linalg.norm(v, axis=1, keepdims=True))
    return Mesh(v, f, albedo)


def _faces_where(mesh: Mesh, vertex_mask: np.ndarray) -> Mesh:
    """The faces with a vertex in vertex_mask, over all the vertices (for a small ray-tracing scene)."""
    return Mesh(mesh.vertices, mesh.faces[vertex_mask[mesh.faces].any(axis=1)], mesh.albedo)


def site_frame(mesh: Mesh, *, lat_deg: float, lon_deg: float, radius_km: float, max_edge_km: float) -> LocalFrame:
    """Local frame at the site: origin where the ray from far outside towards the centre along
    (lat, lon) first meets the surface; z the area-weighted mean normal of the faces with a vertex
    within radius_km of it (or of one facet, if larger); x parallel to the equator.
    max_edge_km: bound on the facet size."""
    u = latlon_to_unit(lat_deg, lon_deg)
    v = mesh.vertices
    # only faces with a vertex within one facet of the ray line can meet it
    along = v @ u
    line = _faces_where(mesh, (along > 0) & (np.linalg.norm(v - along[:, None] * u, axis=1) <= max_edge_km))
    far = 4.0 * float(along.max())
    tracer = RayTracer(line)
    hits = tracer.intersect(far * u[None], -u[None])
    if not hits.hit[0]:
        raise ValueError(f"no surface along latitude {lat_deg}, longitude {lon_deg}")
    # back onto the ray line, which float32 hits miss by micrometres, so the site is exactly at (lat, lon)
    origin = u * (tracer.hit_points(far * u[None], -u[None], hits)[0] @ u)
    t = v[_faces_where(mesh, np.linalg.norm(v - origin, axis=1) <= max(radius_km, max_edge_km)).faces]
    normal = np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]).sum(axis=0)
    return local_frame(origin, normal)


def _refine_near(mesh: Mesh, centre: np.ndarray, radius_km: float, max_edge_km: float) -> Mesh:
    """Refine the faces with a vertex within radius_km of centre (plus a ring of their largest
    edge) until none of them has an edge longer than max_edge_km; the surface is unchanged."""
    while True:
        dist = np.linalg.norm(mesh.vertices - centre, axis=1)[mesh.faces].min(axis=1)
        reach = radius_km + _longest_edges(mesh, dist <= radius_km).max()
        near = dist <= reach
        longest = _longest_edges(mesh, near)
        if longest.max() <= max_edge_km:
            return mesh
        red = np.zeros(len(mesh.faces), dtype=bool)
        red[near] = longest > 0.5 * max_edge_km
        mesh = split_edges(mesh, np.repeat(red[:, None], 3, axis=1))[0]


def _longest_edges(mesh: Mesh, face_mask: np.ndarray) -> np.ndarray:
    """Longest edge (km) of each face in face_mask."""
    tri = mesh.vertices[mesh.faces[face_mask]]
    return np.linalg.norm(tri - np.roll(tri, 1, axis=1), axis=2).max(axis=1)


def _blend_weight(x_km: np.ndarray, y_km: np.ndarray, zero_band_km: float, site_size_km: float) -> np.ndarray:
    """C2 ramp from 0 (within zero_band_km of the patch edge) to 1 (inside the site square)."""
    half = x_km[-1]
    depth = half - np.maximum(np.abs(x_km)[None, :], np.abs(y_km)[:, None])
    t = np.clip((depth - zero_band_km) / (half - site_size_km / 2 - zero_band_km), 0.0, 1.0)
    return t**3 * (10 - 15 * t + 6 * t**2)


def _grid_vertices(frame: LocalFrame, x_km: np.ndarray, y_km: np.ndarray, height_km: np.ndarray) -> np.ndarray:
    """Body-fixed positions (km) of the grid nodes, row-major: `frame.to_body` done axis by axis,
    because a BLAS product with an inner size of 3 is several times slower on millions of nodes."""
    ex, ey, ez = frame.rotation
    body = frame.origin + (x_km[None, :, None] * ex + y_km[:, None, None] * ey)
    body += height_km[..., None] * ez
    return body.reshape(-1, 3)


def _drape(mesh: Mesh, frame: LocalFrame, x_km: np.ndarray, y_km: np.ndarray, *, max_edge_km: float,
           rows_per_chunk: int = 256) -> tuple[np.ndarray, np.ndarray]:
    """Height along the frame's z (km) and interpolated albedo of the surface under each grid
    node: the first hit of a ray cast along -z from above the highest vertex near the patch.
    max_edge_km: bound on the facet size, to keep only the faces that can lie under the grid."""
    half = max(abs(x_km[0]), abs(x_km[-1]), abs(y_km[0]), abs(y_km[-1]))
    local = frame.to_local(mesh.vertices)
    near = np.all(np.abs(local) <= 2 * half + max_edge_km, axis=1)
    top = local[near, 2].max() + half
    tracer = RayTracer(_faces_where(mesh, near))
    height = np.empty((len(y_km), len(x_km)))
    albedo = np.empty_like(height)
    down = np.broadcast_to(-frame.normal, (rows_per_chunk * len(x_km), 3))
    for i0 in range(0, len(y_km), rows_per_chunk):
        ys = y_km[i0 : i0 + rows_per_chunk]
        origins = _grid_vertices(frame, x_km, ys, np.full((len(ys), len(x_km)), top))
        hits = tracer.intersect(origins, down[: len(origins)])
        if not hits.hit.all():
            raise ValueError("the site patch overhangs the edge of the body: choose a smaller site")
        height[i0 : i0 + len(ys)] = (top - hits.t).reshape(len(ys), -1)
        albedo[i0 : i0 + len(ys)] = tracer.interpolate(mesh.require_albedo(), hits).reshape(len(ys), -1)
    return height, albedo


def _cut(base: Mesh, frame: LocalFrame, half_km: float) -> tuple[Mesh, float]:
    """Remove the base faces that lie wholly over the patch square (near side only) and drop the
    vertices left unused. Returns the cut base and a bound on how far (km) the remaining faces
    reach inside the square from its edge."""
    local = frame.to_local(base.vertices)
    depth = half_km - np.maximum(np.abs(local[:, 0]), np.abs(local[:, 1]))
    near_side = np.abs(local[:, 2]) < half_km
    removed = ((depth >= 0) & near_side)[base.faces].all(axis=1)
    kept = ~removed & near_side[base.faces].all(axis=1)
    # depth is 1-Lipschitz, so no point of a face lies deeper than any of its corners plus its longest edge
    reach = float(np.max(depth[base.faces[kept]].min(axis=1) + _longest_edges(base, kept), initial=0.0))
    faces = base.faces[~removed]
    used = np.zeros(len(base.vertices), dtype=bool)
    used[faces] = True
    new_id = np.cumsum(used) - 1
    return Mesh(base.vertices[used], new_id[faces], base.require_albedo()[used]), reach


def _site_detail(seed: int, site: int, axis_km: np.ndarray, site_size_km: float, craters: list[Crater],
                 boulders: list[Boulder], cobble_cover: float) -> tuple[np.ndarray, np.ndarray]:
    """Relief along z (km) and log-albedo of the site on the square grid with this axis."""
    shape = (len(axis_km), len(axis_km))
    spacing = float(axis_km[1] - axis_km[0])
    band: dict[str, Any] = dict(shape=shape, spacing_km=spacing, wavelength_min_km=RESOLVED_NODES * spacing,
                                wavelength_max_km=site_size_km)
    relief, log_albedo = boulder_relief(axis_km, axis_km, boulders)
    relief += crater_relief(axis_km, axis_km, craters)
    if cobble_cover > 0:
        relief += cobble_relief(_rng(seed, "cobbles", site), axis_km, axis_km, cover=cobble_cover,
                                site_size_km=site_size_km, resolution_km=spacing)
    relief += SITE_ROUGHNESS_KM * fractal_grid(_rng(seed, "site_roughness", site), **band)
    log_albedo += SITE_ALBEDO_LOG_RMS * fractal_grid(_rng(seed, "site_albedo", site), **band)
    log_albedo += albedo_patches(_rng(seed, "patches", site), axis_km, axis_km, site_size_km=site_size_km)
    return relief, log_albedo


@dataclass(frozen=True)
class SiteSpec:
    """A site of the truth: the square of side size_km centred at planetocentric (lat, lon),
    sampled every resolution_km over the site plus margin_km per side (default a quarter of the
    site size) where the detail blends into the body. steep_boulders of the n_boulders have side
    slopes above 60 degrees; large_boulders more, 3-5 m across and about 1 m tall, are each the
    largest about it (pwm.simulate.terrain.add_large_boulders); cobble_cover is the fraction of
    the site strewn with sub-metre rocks."""

    lat_deg: float
    lon_deg: float
    size_km: float
    resolution_km: float
    n_craters: int
    n_boulders: int
    steep_boulders: int
    cobble_cover: float = 0.0
    margin_km: float | None = None
    large_boulders: int = 0

    @property
    def margin(self) -> float:
        return 0.25 * self.size_km if self.margin_km is None else self.margin_km

    @property
    def clear_radius_km(self) -> float:
        """The radius of the disc that holds the site's square and its margin."""
        return float(np.sqrt(2.0) * (self.size_km / 2 + self.margin))


@dataclass
class _Patch:
    """A site's grid as stitched into the body: its frame, axis (x and y alike), heights and albedo
    per node, zero band, and the landforms drawn on it."""

    spec: SiteSpec
    frame: LocalFrame
    axis: np.ndarray
    height: np.ndarray
    albedo: np.ndarray
    zero_band: float
    craters: list[Crater]
    boulders: list[Boulder]

    def thinned(self, spacing_km: float) -> _Patch:
        """The same patch on every k-th node, k such that the spacing is at most spacing_km; the
        outermost nodes are kept, so it still covers the same square."""
        step = max(1, int(spacing_km / (self.axis[1] - self.axis[0])))
        keep = np.unique(np.r_[np.arange(0, len(self.axis), step), len(self.axis) - 1])
        return _Patch(spec=self.spec, frame=self.frame, axis=self.axis[keep], height=self.height[np.ix_(keep, keep)],
                      albedo=self.albedo[np.ix_(keep, keep)], zero_band=self.zero_band, craters=self.craters,
                      boulders=self.boulders)


def build_truth(
    *, base: Mesh, site_lat_deg: float, site_lon_deg: float, site_size_km: float, resolution_km: float,
    seed: int, base_edge_km: float, global_roughness_km: float = 0.0, n_craters: int, n_boulders: int,
    steep_boulders: int, cobble_cover: float = 0.0, margin_km: float | None = None, large_boulders: int = 0,
) -> Truth:
    """Build the truth asteroid with one site (see the module docstring and SiteSpec). Lengths
    in km, angles in degrees; deterministic for a given seed."""
    body = build_base(base, base_edge_km=base_edge_km, seed=seed, global_roughness_km=global_roughness_km)
    site = SiteSpec(lat_deg=site_lat_deg, lon_deg=site_lon_deg, size_km=site_size_km, resolution_km=resolution_km,
                    n_craters=n_craters, n_boulders=n_boulders, steep_boulders=steep_boulders,
                    cobble_cover=cobble_cover, margin_km=margin_km, large_boulders=large_boulders)
    extra = dict(base_edge_km=base_edge_km, global_roughness_km=global_roughness_km)
    return stitch_sites(body, [site], seed=seed, params=extra).truth(0)


def site_frames(body: Mesh, sites: list[SiteSpec]) -> list[LocalFrame]:
    """Each site's local frame on the body (`site_frame`)."""
    max_edge = _max_edge(body)
    return [site_frame(body, lat_deg=s.lat_deg, lon_deg=s.lon_deg, radius_km=s.size_km / 2, max_edge_km=max_edge)
            for s in sites]


def _max_edge(mesh: Mesh) -> float:
    return float(_longest_edges(mesh, np.ones(len(mesh.faces), dtype=bool)).max())


def stitch_sites(body: Mesh, sites: list[SiteSpec], *, seed: int, params: dict | None = None,
                 landforms: list[Landform] | None = None) -> Stitched:
    """The body with a site patch stitched in for each of `sites` (far enough apart that their
    squares and margins do not meet), from which each site's Truth is composed on demand.
    landforms: those on the body, recorded. The first site draws what a lone site of the same
    seed draws.
    """
    max_edge = _max_edge(body)
    frames, axes, grounds = site_frames(body, sites), [], []
    for site, frame in zip(sites, frames, strict=True):
        n = int(np.ceil((site.size_km / 2 + site.margin) / site.resolution_km - 1e-9))
        axes.append(np.arange(-n, n + 1) * site.resolution_km)
        grounds.append(_drape(body, frame, axes[-1], axes[-1], max_edge_km=max_edge))

    # The patch replaces the base faces lying wholly over it; base faces crossing its border stay
    # and overlap it by at most their size. The detail is zero over that overlap, so there the
    # patch lies on those faces within the error of sampling their creases (about 1 mm at 5 cm
    # spacing): no gap and no visible seam, at the price of a thin doubly covered band outside the
    # site. Clipping base triangles against the grid would avoid the overlap but not improve any
    # image. Refining the base near the border keeps the band within a third of the margin.
    cut = body
    for site, frame, axis in zip(sites, frames, axes, strict=True):
        cut = _refine_near(cut, frame.origin, np.sqrt(2) * float(axis[-1]), site.margin / 3)
    patches = []
    for k, (site, frame, axis, (ground, ground_albedo)) in enumerate(zip(sites, frames, axes, grounds, strict=True)):
        cut, reach = _cut(cut, frame, float(axis[-1]))
        zero_band = reach + 2 * site.resolution_km
        if zero_band >= site.margin:
            raise ValueError(f"margin {site.margin * 1e3:g} m is too narrow for grid spacing "
                             f"{site.resolution_km * 1e3:g} m")
        weight = _blend_weight(axis, axis, zero_band, site.size_km)
        craters = sample_craters(_rng(seed, "craters", k), n=site.n_craters, site_size_km=site.size_km,
                                 resolution_km=site.resolution_km)
        boulders = sample_boulders(_rng(seed, "boulders", k), n=site.n_boulders, n_steep=site.steep_boulders,
                                   site_size_km=site.size_km, resolution_km=site.resolution_km)
        boulders = add_large_boulders(_rng(seed, "large_boulders", k), boulders, n=site.large_boulders,
                                      site_size_km=site.size_km, clearance_km=LARGE_BOULDER_CLEARANCE_KM,
                                      resolution_km=site.resolution_km)
        detail, log_albedo = _site_detail(seed, k, axis, site.size_km, craters, boulders, site.cobble_cover)
        patches.append(_Patch(spec=site, frame=frame, axis=axis, height=ground + weight * detail,
                              albedo=ground_albedo * np.exp(weight * log_albedo), zero_band=zero_band,
                              craters=craters, boulders=boulders))
    return Stitched(cut=cut, patches=patches, seed=seed, params=params or {}, landforms=landforms or [])


@dataclass
class Stitched:
    """A body cut for its sites' patches, and the patches: each site's Truth is composed from
    them when asked for, as one site's truth of tens of millions of faces is memory enough."""

    cut: Mesh
    patches: list[_Patch]
    seed: int
    params: dict
    landforms: list[Landform]

    def truth(self, site: int, *, thin_to_km: float | None = None) -> Truth:
        """The whole surface with `site`'s patch last (so that each site is evaluated as a lone
        site would be). thin_to_km: every patch sampled at about this spacing instead of its own
        (a global survey's truth, where centimetre nodes would only cost memory)."""
        patches = self.patches if thin_to_km is None else [p.thinned(thin_to_km) for p in self.patches]
        order = [p for j, p in enumerate(patches) if j != site] + [patches[site]]
        return _compose(self.cut, order, seed=self.seed, params=self.params, landforms=self.landforms)


def _compose(cut: Mesh, patches: list[_Patch], *, seed: int, params: dict, landforms: list[Landform]) -> Truth:
    """The Truth of the cut body with the patches stitched in, the last one its site."""
    vertices, faces, albedo = [cut.vertices], [cut.faces], [cut.require_albedo()]
    count = len(cut.vertices)
    for patch in patches:
        vertices.append(_grid_vertices(patch.frame, patch.axis, patch.axis, patch.height))
        faces.append(grid_faces(len(patch.axis), len(patch.axis)) + count)
        albedo.append(patch.albedo.ravel())
        count += len(vertices[-1])
    site = patches[-1]
    spec = site.spec
    params = dict(site_lat_deg=spec.lat_deg, site_lon_deg=spec.lon_deg, site_size_km=spec.size_km,
                  resolution_km=spec.resolution_km, seed=seed, n_craters=spec.n_craters, n_boulders=spec.n_boulders,
                  steep_boulders=spec.steep_boulders, cobble_cover=spec.cobble_cover, margin_km=spec.margin,
                  large_boulders=spec.large_boulders,
                  **params)
    return Truth(mesh=Mesh(np.vstack(vertices), np.vstack(faces), np.concatenate(albedo)), site_frame=site.frame,
                 site_size_km=spec.size_km, x_km=site.axis, y_km=site.axis.copy(), height_km=site.height,
                 eval_radius_km=spec.size_km / 2, zero_band_km=site.zero_band, craters=site.craters,
                 boulders=site.boulders, n_base_vertices=count - len(site.axis) ** 2,
                 n_base_faces=sum(len(f) for f in faces[:-1]), landforms=landforms, params=params)


def low_pass_heights(truth: Truth, *, wavelength_km: float) -> np.ndarray:
    """Patch heights (km) with the detail low-passed by the Gaussian filter whose gain is 1/2 at
    wavelength_km (ISO 16610-21); unchanged in the zero band, so the border still meets the base."""
    sigma = gaussian_sigma_km(wavelength_km) / truth.resolution_km
    smooth = ndimage.gaussian_filter(truth.height_km, sigma, mode="nearest")
    return truth.height_km + truth.blend_weight() * (smooth - truth.height_km)


def undulations(truth: Truth, *, rms_km: float, shortest_km: float, longest_km: float, seed: int) -> np.ndarray:
    """A smooth random height error on the patch grid (km, (len(y), len(x))): a Gaussian field
    whose wavelengths all lie between shortest_km and longest_km, of RMS rms_km over the site
    square, faded out over the border like the detail (zero in the zero band), as an earlier,
    coarser campaign leaves its model wrong at long wavelengths."""
    if not 0 < shortest_km < longest_km:
        raise ValueError(f"need 0 < shortest < longest wavelength, not {shortest_km} and {longest_km} km")
    ny, nx = truth.height_km.shape
    ky = np.fft.fftfreq(ny, truth.resolution_km)[:, None]
    kx = np.fft.rfftfreq(nx, truth.resolution_km)[None, :]
    k = np.hypot(kx, ky)
    band = (k >= 1 / longest_km) & (k <= 1 / shortest_km)
    if not band.any():
        raise ValueError(f"no wavelength between {shortest_km} and {longest_km} km fits the {nx}-node patch")
    spectrum = np.fft.rfft2(_rng(seed, "start_error").normal(size=(ny, nx))) * band
    field = np.fft.irfft2(spectrum, s=(ny, nx))
    weight = truth.blend_weight()
    full = weight >= 1.0
    field *= rms_km / max(float(np.sqrt(np.mean(field[full] ** 2))), 1e-300)
    return field * weight


def low_pass(truth: Truth, *, wavelength_km: float, spacing_km: float | None = None,
             error_km: np.ndarray | None = None) -> Mesh:
    """A starting shape model: the truth low-passed to wavelength_km over the patch, plus
    error_km (heights on the patch grid, e.g. `undulations`), remeshed on a grid of spacing
    about spacing_km (default wavelength_km / 2), and the truth's base elsewhere (km, no albedo).

    Over the border band the coarse patch lies on the base faces only within the error of linear
    interpolation at that spacing (about a centimetre for 1 m): overlapping, never leaving a gap.
    """
    smooth = low_pass_heights(truth, wavelength_km=wavelength_km)
    if error_km is not None:
        smooth = smooth + error_km
    half = float(truth.x_km[-1])
    m = int(np.ceil(2 * half / (spacing_km or wavelength_km / 2))) + 1
    axis = np.linspace(-half, half, m)
    index = (axis - truth.x_km[0]) / truth.resolution_km
    coarse = ndimage.map_coordinates(smooth, np.meshgrid(index, index, indexing="ij"), order=1, mode="nearest")
    return _with_patch(truth, axis, axis, coarse)


def sampled(truth: Truth, *, spacing_km: float, average_km: float) -> Mesh:
    """The truth as a model on a coarser grid could hold it at best: the patch heights and albedo
    averaged over squares of side average_km and sampled every spacing_km (both rounded to whole
    truth nodes), on the truth's base (km, with albedo)."""
    stride = max(1, int(round(spacing_km / truth.resolution_km)))
    box = max(1, int(round(average_km / truth.resolution_km)))
    heights = ndimage.uniform_filter(truth.height_km, box, mode="nearest")[::stride, ::stride]
    albedo = ndimage.uniform_filter(truth.albedo_grid, box, mode="nearest")[::stride, ::stride]
    return _with_patch(truth, truth.x_km[::stride], truth.y_km[::stride], heights, albedo)


def _with_patch(truth: Truth, x_km: np.ndarray, y_km: np.ndarray, height_km: np.ndarray,
                albedo: np.ndarray | None = None) -> Mesh:
    """The truth's base with a patch grid of heights (len(y), len(x)) in the site frame; with
    albedo per node, the base keeps its own."""
    base = truth.base_mesh()
    return Mesh(np.vstack([base.vertices, _grid_vertices(truth.site_frame, x_km, y_km, height_km)]),
                np.vstack([base.faces, grid_faces(len(y_km), len(x_km)) + len(base.vertices)]),
                None if albedo is None else np.concatenate([base.albedo, albedo.ravel()]))


def save(truth: Truth, directory: str | Path) -> None:
    """Write a truth directory: mesh.ply (with albedo), grid.npz (axes, heights), truth.json."""
    d = Path(directory)
    d.mkdir(parents=True, exist_ok=True)
    write_ply(d / "mesh.ply", truth.mesh)
    np.savez(d / "grid.npz", x_km=truth.x_km, y_km=truth.y_km, height_km=truth.height_km)
    meta = dict(origin_km=truth.site_frame.origin.tolist(), rotation=truth.site_frame.rotation.tolist(),
                site_size_km=truth.site_size_km, eval_radius_km=truth.eval_radius_km,
                zero_band_km=truth.zero_band_km, n_base_vertices=truth.n_base_vertices,
                n_base_faces=truth.n_base_faces, craters=[asdict(c) for c in truth.craters],
                boulders=[asdict(b) for b in truth.boulders], params=truth.params,
                landforms=[_landform_json(f) for f in truth.landforms])
    (d / "truth.json").write_text(json.dumps(meta, indent=1))


def load(directory: str | Path) -> Truth:
    """Read a truth directory written by `save`."""
    d = Path(directory)
    meta = json.loads((d / "truth.json").read_text())
    grid = np.load(d / "grid.npz")
    frame = LocalFrame(origin=np.array(meta["origin_km"]), rotation=np.array(meta["rotation"]))
    return Truth(mesh=read_ply(d / "mesh.ply"), site_frame=frame, site_size_km=meta["site_size_km"],
                 x_km=grid["x_km"], y_km=grid["y_km"], height_km=grid["height_km"],
                 eval_radius_km=meta["eval_radius_km"], zero_band_km=meta["zero_band_km"],
                 craters=[Crater(**c) for c in meta["craters"]], boulders=[Boulder(**b) for b in meta["boulders"]],
                 n_base_vertices=meta["n_base_vertices"], n_base_faces=meta["n_base_faces"],
                 landforms=[_landform(f) for f in meta.get("landforms", [])], params=meta["params"])


def _landform_json(form: Landform) -> dict:
    return {"origin_km": list(form.origin_km), "normal": list(form.normal),
            "kind": "crater" if isinstance(form.shape, Crater) else "boulder", **asdict(form.shape)}


def _landform(entry: dict) -> Landform:
    fields = {k: v for k, v in entry.items() if k not in ("origin_km", "normal", "kind")}
    shape = Crater(**fields) if entry["kind"] == "crater" else Boulder(**fields)
    return Landform(origin_km=tuple(entry["origin_km"]), normal=tuple(entry["normal"]), shape=shape)
