"""Image, pixel and region weights of a pixel-weighted maplet (PWM paper section 3.3.3; METHOD.md 4).

The rules, all thresholds in `Rules`:

- Image weight: the product of an incidence weight (1 from 30 to 75 deg, lower towards the zenith:
  "too low: no contrast on slopes"), an emission weight (1 up to 30 deg, falling beyond), the
  visible fraction of the maplet (not occluded, in frame), the lit fraction of what is visible,
  and a resolution weight min(1, maplet spacing / image pixel scale). The paper's best range
  stops at 60 deg for the other reason it gives, "too high: long shadows"; here the shadows are
  weighed node by node instead (the pixel weights), and what a low Sun leaves lit shows slopes
  with the most contrast.
- Operational SPC drops an image from a maplet (`select_images`) when under 20% of the maplet is
  visible in it, over 20% of what is visible is in shadow, the emission exceeds about 40 deg, or
  its pixels are more than twice as coarse as the maplet's spacing. Here the shadow limit is 60%:
  SPC's photoclinometry reads shadows as dark terrain, the pixel weights here leave them out. An
  image whose pixels are over five times finer than the spacing is dropped too: it belongs to the
  finer maplets tiled where it looks (two levels down or more), so that a site's close images
  leave the coarser levels over the site as they were; and sampled at the nodes without a
  low-pass its pixels alias (a 10 cm image over 2 m nodes reads cobbles as slopes).
- Pixel weights: occluded or out-of-frame nodes get 0; shadowed nodes 0, except that where the
  terrain needs them (steep relief, a maplet whose slope-angle spread exceeds a threshold) shadowed
  nodes next to lit ones keep a small weight; lit nodes next to a shadow edge are down-weighted,
  as excluding pixels next to shadows stabilised SPC in testing.
- Image set: at least five images, a nadir one (the lowest phase and least occlusion among those
  closest to the regional normal) and views from the east, west, north and south (camera azimuth
  in the maplet frame); the Sun's azimuth should vary by at least 90 deg across the set.
- Region weight w_PWM in (0, 1]: lower when the set falls short of those needs (missing views,
  narrow Sun azimuth spread, too few images, poor images); it tightens the photoclinometric
  solution to the starting shape (the 1 / w_PWM term of the paper's equation 7).

Angles in degrees; azimuths from local north (+y) towards east (+x) in the maplet frame.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage

from pwm.camera import project
from pwm.frames import LocalFrame, local_sun
from pwm.maplets import MapletGrid
from pwm.raytrace import RayTracer
from pwm.views import View
from pwm.visibility import Visibility, node_visibility

DIRECTIONS = {"east": 90.0, "west": 270.0, "north": 0.0, "south": 180.0}
"""Camera azimuths of the four side views."""


@dataclass(frozen=True)
class Rules:
    """Every threshold of the weighting."""

    incidence_best_deg: tuple[float, float] = (30.0, 75.0)
    """Incidence range with full weight. Liu & Wu 2021 (cited by the PWM paper) found 30-60 deg
    best, beyond which shadows hide the terrain; with the shadowed nodes excluded one by one, the
    lit rest of a 60-75 deg image is the best slope data there is (bench/RESULTS.md)."""
    incidence_floor: float = 0.3
    """Incidence weight at 0 deg: albedo is still measured, slopes barely."""
    incidence_zero_deg: float = 90.0
    """Incidence at which the weight has fallen to 0 (the Sun on the horizon)."""
    emission_full_deg: float = 30.0
    emission_zero_deg: float = 70.0
    """Emission weight: 1 up to emission_full_deg, falling to 0 at emission_zero_deg."""
    min_visible_fraction: float = 0.2
    max_shadow_fraction: float = 0.6
    max_emission_deg: float = 40.0
    max_resolution_ratio: float = 2.0
    min_resolution_ratio: float = 0.2
    """The SPC drop rules: visible fraction, shadowed fraction, emission, pixel scale / spacing
    (at most max_resolution_ratio, at least min_resolution_ratio: see the module docstring).
    SPC drops an image over 20% in shadow; with shadowed nodes weighed out one by one, an image's
    lit nodes are worth keeping well beyond that. The rule only bites once the shape casts the
    shadows the images show (a smooth start casts few; bench/RESULTS.md)."""
    shadow_keep_weight: float = 0.1
    """Weight of a shadowed node next to a lit one, in steep terrain."""
    steep_slope_std_deg: float = 15.0
    """Spread (standard deviation) of a maplet's slope angles above which its terrain is steep."""
    shadow_edge_factor: float = 0.5
    """Factor on lit nodes next to a node that the current shape shadows, whose shadow's edge may
    lie a node off. Not on those next to a node the images themselves show dark (`dark_nodes`):
    they are lit in the same pixels, and on a boulder a few nodes across they are the flank
    towards its shadow, the steepest slope it shows (bench/RESULTS.md: the survey's boulders)."""
    dark_fraction: float = 0.05
    """A node darker in an image than this fraction of the image's median over the maplet lies in
    a shadow, cast by relief the current shape may not have yet (boulders missing from the start).
    Low enough to keep the dim faces of steep boulders, which carry their slopes; without it,
    the shadows of a low Sun are read as dark terrain (bench/RESULTS.md)."""
    lit_fraction: float = 0.25
    """A node brighter in an image than this fraction of the image's median over the maplet is
    plainly lit: no relief stands between it and the Sun (`shade`)."""
    nadir_tolerance_deg: float = 10.0
    """Nadir candidates: within this of the lowest emission; the lowest phase angle among them wins."""
    side_min_emission_deg: float = 10.0
    """Below this emission a view has no meaningful azimuth and cannot be a side view."""
    side_half_width_deg: float = 45.0
    """A side view's camera azimuth lies within this of east, west, north or south."""
    sun_spread_deg: float = 90.0
    """Sun azimuth spread wanted across the image set."""
    min_images: int = 5
    sun_floor: float = 0.5
    """Region-weight factor of an image set whose Sun azimuth never varies."""
    min_region_weight: float = 0.05
    """w_PWM of a maplet without usable images."""


RULES = Rules()

_SAME_IMAGE = np.zeros((3, 3, 3), dtype=bool)
_SAME_IMAGE[1] = True
"""Dilation structure on (K, n, n) node arrays: the 8 neighbours within one image, none across images."""


@dataclass
class MapletGeometry:
    """Geometry of K images over one maplet, each (K,). Angles in degrees at the maplet origin in
    its frame. resolution_ratio: image pixel scale at the maplet / maplet spacing.
    visible_fraction: nodes in frame and visible; shadow_fraction: unlit among those (1 if none)."""

    incidence_deg: np.ndarray
    emission_deg: np.ndarray
    phase_deg: np.ndarray
    camera_azimuth_deg: np.ndarray
    sun_azimuth_deg: np.ndarray
    resolution_ratio: np.ndarray
    visible_fraction: np.ndarray
    shadow_fraction: np.ndarray


@dataclass
class FiveViews:
    """Indices of the images chosen for each role, None where no image fits."""

    nadir: int | None = None
    east: int | None = None
    west: int | None = None
    north: int | None = None
    south: int | None = None

    def found(self) -> list[int]:
        return [v for v in (self.nadir, self.east, self.west, self.north, self.south) if v is not None]


@dataclass
class ImageWeights:
    """Weights of K images for one maplet, from their geometry alone. image: (K,) image weights
    (0 where dropped); keep: (K,) images kept by the SPC rules, reasons: why each was dropped;
    views: the five-view selection; sun_spread_deg: Sun azimuth spread of the kept images; region:
    w_PWM, and factors: its factors (see `region_weight`)."""

    image: np.ndarray
    keep: np.ndarray
    reasons: list[list[str]]
    views: FiveViews
    sun_spread_deg: float
    region: float
    factors: dict = field(default_factory=dict)


@dataclass(kw_only=True)
class MapletWeights(ImageWeights):
    """ImageWeights with pixel: (K, n, n) per-node weights (image weight times node factor)."""

    pixel: np.ndarray


def maplet_geometry(
    frame: LocalFrame, vis: Visibility, *, camera_positions: np.ndarray, sun_directions: np.ndarray,
    pixel_scale_km: np.ndarray, spacing_km: float, in_frame: np.ndarray | None = None,
) -> MapletGeometry:
    """Geometry of K images over the maplet with this frame. vis: visibility of its nodes (K, N);
    camera_positions (K, 3) km and sun_directions (K, 3), body-fixed; pixel_scale_km (K,): image
    pixel footprint at the maplet (range / focal length in pixels); in_frame (K, N): nodes inside
    each image (all if None)."""
    to_cam = np.asarray(camera_positions, float) - frame.origin
    to_cam /= np.linalg.norm(to_cam, axis=1, keepdims=True)
    sun = np.asarray(sun_directions, float)
    sun = sun / np.linalg.norm(sun, axis=1, keepdims=True)
    emission, cam_az = local_sun(to_cam, frame)
    incidence, sun_az = local_sun(sun, frame)
    seen = vis.visible if in_frame is None else vis.visible & in_frame
    n_seen = seen.sum(axis=1)
    dark = (seen & ~vis.lit).sum(axis=1)
    return MapletGeometry(
        incidence_deg=incidence, emission_deg=emission,
        phase_deg=np.degrees(np.arccos(np.clip(np.einsum("ki,ki->k", to_cam, sun), -1.0, 1.0))),
        camera_azimuth_deg=cam_az, sun_azimuth_deg=sun_az,
        resolution_ratio=np.asarray(pixel_scale_km, float) / spacing_km,
        visible_fraction=n_seen / seen.shape[1],
        shadow_fraction=np.where(n_seen > 0, dark / np.maximum(n_seen, 1), 1.0),
    )


def views_over_maplet(maplet: MapletGrid, views: list[View], tracer: RayTracer, *,
                      spacing_km: float | None = None) -> tuple[Visibility, np.ndarray, MapletGeometry]:
    """Visibility of the maplet's nodes in `views` against the tracer's shape, which nodes fall
    in each image's frame (K, n*n), and the images' geometry over the maplet. Only the views'
    camera, pose and Sun are used. spacing_km: the spacing the resolution is judged against
    (default the maplet's; a subsampled copy of a maplet gives its parent's)."""
    points = maplet.nodes_body().reshape(-1, 3)
    normals = maplet.normals_body().reshape(-1, 3)
    cams = np.array([v.pose.position for v in views])
    suns = np.array([v.sun for v in views])
    vis = node_visibility(tracer, points, normals, camera_positions=cams, sun_directions=suns)
    in_frame = np.array([_in_frame(points, v) for v in views])
    ranges = np.linalg.norm(cams - maplet.frame.origin, axis=1)
    scale = ranges / np.array([0.5 * (v.camera.fx + v.camera.fy) for v in views])
    geom = maplet_geometry(maplet.frame, vis, camera_positions=cams, sun_directions=suns, pixel_scale_km=scale,
                          spacing_km=maplet.spacing_km if spacing_km is None else spacing_km, in_frame=in_frame)
    return vis, in_frame, geom


def _in_frame(points: np.ndarray, view: View) -> np.ndarray:
    """Points that project inside the image (half a pixel in from the edges, for interpolation)."""
    px = project(points, view.camera, view.pose)
    in_front = view.pose.to_camera(points)[:, 2] > 0
    return (in_front & (px[:, 0] >= 0) & (px[:, 0] <= view.camera.width - 1)
            & (px[:, 1] >= 0) & (px[:, 1] <= view.camera.height - 1))


def raised_cosine(t: np.ndarray) -> np.ndarray:
    """Smooth step: 0 for t <= 0, 1 for t >= 1, 0.5 - 0.5 cos(pi t) between."""
    return 0.5 - 0.5 * np.cos(np.pi * np.clip(t, 0.0, 1.0))


def image_weights(geom: MapletGeometry, rules: Rules = RULES) -> np.ndarray:
    """Image weights (K,) in [0, 1] (before the drop rules)."""
    lo, hi = rules.incidence_best_deg
    i = geom.incidence_deg
    w_inc = np.where(i < lo, rules.incidence_floor + (1 - rules.incidence_floor) * raised_cosine(i / lo),
                     raised_cosine((rules.incidence_zero_deg - i) / (rules.incidence_zero_deg - hi)))
    e_full, e_zero = rules.emission_full_deg, rules.emission_zero_deg
    w_em = raised_cosine((e_zero - geom.emission_deg) / (e_zero - e_full))
    w_res = np.minimum(1.0, 1.0 / geom.resolution_ratio)
    return w_inc * w_em * w_res * geom.visible_fraction * (1.0 - geom.shadow_fraction)


def select_images(geom: MapletGeometry, rules: Rules = RULES) -> tuple[np.ndarray, list[list[str]]]:
    """The SPC drop rules: (keep (K,) bool, for each image the reasons it was dropped)."""
    tests = [
        (geom.visible_fraction < rules.min_visible_fraction,
         lambda k: f"visible {geom.visible_fraction[k]:.0%} < {rules.min_visible_fraction:.0%}"),
        (geom.shadow_fraction > rules.max_shadow_fraction,
         lambda k: f"shadowed {geom.shadow_fraction[k]:.0%} > {rules.max_shadow_fraction:.0%}"),
        (geom.emission_deg > rules.max_emission_deg,
         lambda k: f"emission {geom.emission_deg[k]:.1f} > {rules.max_emission_deg:g} deg"),
        (geom.resolution_ratio > rules.max_resolution_ratio,
         lambda k: f"pixel scale {geom.resolution_ratio[k]:.2f} x spacing > {rules.max_resolution_ratio:g}"),
        (geom.resolution_ratio < rules.min_resolution_ratio,
         lambda k: f"pixel scale {geom.resolution_ratio[k]:.2f} x spacing < {rules.min_resolution_ratio:g}: "
                   "the finer levels' image"),
    ]
    reasons = [[text(k) for failed, text in tests if failed[k]] for k in range(len(geom.emission_deg))]
    return np.array([not r for r in reasons], dtype=bool), reasons


def slope_spread_deg(heights: np.ndarray, spacing_km: float) -> float:
    """Standard deviation (deg) of the slope angles of a height grid (km)."""
    gy, gx = np.gradient(heights, spacing_km)
    return float(np.degrees(np.arctan(np.hypot(gx, gy))).std())


def node_factors(vis: Visibility, heights: np.ndarray, spacing_km: float, *, in_frame: np.ndarray | None = None,
                 rules: Rules = RULES) -> np.ndarray:
    """Per image and node (K, n, n), the factor on the image weight: 0 where occluded or out of
    frame; lit nodes 1, or shadow_edge_factor next to a shadowed node (8-neighbours); shadowed
    nodes 0, or shadow_keep_weight next to a lit node in steep terrain."""
    n = heights.shape[0]
    seen = (vis.visible if in_frame is None else vis.visible & in_frame).reshape(-1, n, n)
    lit = vis.lit.reshape(-1, n, n)
    near_dark = ndimage.binary_dilation(~lit, structure=_SAME_IMAGE)
    near_lit = ndimage.binary_dilation(lit, structure=_SAME_IMAGE)
    keep_dark = rules.shadow_keep_weight if slope_spread_deg(heights, spacing_km) > rules.steep_slope_std_deg else 0.0
    factor = np.where(lit, np.where(near_dark, rules.shadow_edge_factor, 1.0), np.where(near_lit, keep_dark, 0.0))
    return np.where(seen, factor, 0.0)


def dark_nodes(values: np.ndarray, weights: np.ndarray, rules: Rules = RULES) -> np.ndarray:
    """(K, n, n) nodes in shadow by the images themselves: darker than rules.dark_fraction of their
    image's median over the nodes it weighs. values: image values at the nodes (K, n, n), NaN where
    missing; weights: the pixel weights (K, n, n). The refinement weighs them out altogether: kept
    at shadow_keep_weight beside lit ones, they cost a long-shadowed site its held-out NCC
    (bench/RESULTS.md)."""
    used = np.isfinite(values) & (weights > 0)
    with np.errstate(invalid="ignore"):
        return used & (values < rules.dark_fraction * _typical(values, used))


def shade(values: np.ndarray, weights: np.ndarray, visible: np.ndarray, rules: Rules = RULES) -> np.ndarray:
    """(K, n, n) int8: -1 where an image shows a visible node in a shadow (darker than
    rules.dark_fraction of the image's median over the nodes it weighs), +1 where it shows it
    plainly lit (brighter than rules.lit_fraction of it), 0 elsewhere and one node either side of
    a shadow's edge, which a pixel's blur and a node's parallax leave uncertain. The refinement's
    shadow term (pwm.photoclinometry) holds the shape to these: what casts the shadows that the
    start lacks."""
    seen = np.isfinite(values) & visible
    typical = _typical(values, seen & (weights > 0))
    with np.errstate(invalid="ignore"):
        dark = seen & (values < rules.dark_fraction * typical)
        lit = seen & (values > rules.lit_fraction * typical)
    dark &= ~ndimage.binary_dilation(~dark & seen, structure=_SAME_IMAGE)
    lit &= ~ndimage.binary_dilation(~lit & seen, structure=_SAME_IMAGE)
    return lit.astype(np.int8) - dark.astype(np.int8)


def _typical(values: np.ndarray, used: np.ndarray) -> np.ndarray:
    """(K, 1, 1) each image's median value over the used nodes (NaN where none is)."""
    return np.array([np.median(v[u]) if u.any() else np.nan for v, u in zip(values, used, strict=True)])[:, None, None]


def five_views(geom: MapletGeometry, image_weight: np.ndarray, keep: np.ndarray, rules: Rules = RULES) -> FiveViews:
    """Nadir view (lowest phase, then most visible, among the kept images within
    nadir_tolerance_deg of the lowest emission) and the best-weighted kept view from each side."""
    views = FiveViews()
    if not keep.any():
        return views
    e = geom.emission_deg
    near = keep & (e <= e[keep].min() + rules.nadir_tolerance_deg)
    cand = np.flatnonzero(near)
    views.nadir = int(cand[np.lexsort((-geom.visible_fraction[cand], geom.phase_deg[cand]))[0]])
    side = keep & (e >= rules.side_min_emission_deg)
    side[views.nadir] = False
    for name, az in DIRECTIONS.items():
        off = np.abs((geom.camera_azimuth_deg - az + 180.0) % 360.0 - 180.0)
        cand = np.flatnonzero(side & (off <= rules.side_half_width_deg))
        if len(cand):
            setattr(views, name, int(cand[np.argmax(image_weight[cand])]))
    return views


def azimuth_spread_deg(azimuth_deg: np.ndarray) -> float:
    """Smallest arc (deg) holding all the azimuths: 360 minus the largest gap between them."""
    a = np.sort(np.asarray(azimuth_deg, float) % 360.0)
    if len(a) < 2:
        return 0.0
    gaps = np.diff(np.append(a, a[0] + 360.0))
    return float(360.0 - gaps.max())


def region_weight(geom: MapletGeometry, image_weight: np.ndarray, keep: np.ndarray, views: FiveViews,
                  rules: Rules = RULES) -> tuple[float, dict]:
    """w_PWM in (0, 1] and its factors: the fraction of the five views found, the Sun azimuth
    spread (sun_floor with none, 1 at sun_spread_deg), the image count (1 at min_images) and the
    mean weight of the chosen views; never below min_region_weight."""
    found = views.found()
    if not found:
        return rules.min_region_weight, {}
    spread = azimuth_spread_deg(geom.sun_azimuth_deg[keep])
    factors = {
        "views": len(found) / 5.0,
        "sun": rules.sun_floor + (1.0 - rules.sun_floor) * min(1.0, spread / rules.sun_spread_deg),
        "count": min(1.0, keep.sum() / rules.min_images),
        "quality": float(image_weight[found].mean()),
    }
    return max(rules.min_region_weight, float(np.prod(list(factors.values())))), factors


def weigh_images(geom: MapletGeometry, rules: Rules = RULES) -> ImageWeights:
    """The weights of K images over one maplet that need only their geometry: what the catalog
    keeps of each image and maplet (service.coverage)."""
    keep, reasons = select_images(geom, rules)
    image = np.where(keep, image_weights(geom, rules), 0.0)
    views = five_views(geom, image, keep, rules)
    region, factors = region_weight(geom, image, keep, views, rules)
    return ImageWeights(image=image, keep=keep, reasons=reasons, views=views,
                        sun_spread_deg=azimuth_spread_deg(geom.sun_azimuth_deg[keep]), region=region, factors=factors)


def weigh_maplet(maplet: MapletGrid, vis: Visibility, geom: MapletGeometry, *, in_frame: np.ndarray | None = None,
                 rules: Rules = RULES) -> MapletWeights:
    """All the weights of one maplet seen in K images. vis: visibility of its nodes in row-major
    order (maplet.nodes_body().reshape(-1, 3)); geom: from `maplet_geometry`; in_frame (K, n*n)."""
    weights = weigh_images(geom, rules)
    pixel = weights.image[:, None, None] * node_factors(vis, maplet.heights, maplet.spacing_km, in_frame=in_frame,
                                                        rules=rules)
    return MapletWeights(**vars(weights), pixel=pixel)
