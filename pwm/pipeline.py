"""The refinement chain on arrays: tile the start model, weigh and refine each maplet against
the images that see it, fuse the maplets back into one model; again from that model, pass after
pass.

No files and no catalog here: `pwm refine` (service/cli/science.py) reads a downlink into views, and the
Celery workers build the same views from the catalog.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy import ndimage
from scipy.interpolate import RegularGridInterpolator
from scipy.spatial import cKDTree

from pwm.alignment import parallax_height, register, rise_motion, sweep_height, window_rises
from pwm.camera import project
from pwm.config import DEFAULTS, Placement, RefinementConfig
from pwm.levels import LevelGrids
from pwm.maplets import NO_SPOTS, MapletGrid, MapletSpots, Spots, grid_heights, solution_change, spots_over
from pwm.mesh import Mesh
from pwm.parallel import Progress, map_processes
from pwm.photoclinometry import MapletImages, Refinement, coarsened, extract, refine
from pwm.raytrace import RayTracer
from pwm.tiling import tile
from pwm.uncertainty import node_sigma, vertex_sigma
from pwm.views import View
from pwm.weights import (
    RULES,
    MapletWeights,
    Rules,
    dark_nodes,
    shade,
    views_over_maplet,
    weigh_maplet,
)

log = logging.getLogger(__name__)


@dataclass
class MapletResult:
    """A refined maplet and how it was made: the images used (names), weights, solver outcome,
    where each image that weighed into it sees its landmark (`landmark_pixels`), how far (km) the
    images' parallax or the lidar's spots raised it from its start, how many spots it was refined
    with and their height residuals' RMS in their sigmas (NaN without)."""

    maplet: MapletGrid
    images: list[str]
    region_weight: float
    five_views: dict
    dropped: dict
    iterations: int
    converged: bool
    residual_rms: list[float]
    seconds: float
    registrations: dict[str, tuple[float, float]]
    raised_km: float
    lidar_spots: int = 0
    lidar_rms: float = float("nan")


def maplet_images(maplet: MapletGrid, views: list[View], tracer: RayTracer, *,
                  rules: Rules = RULES) -> tuple[MapletImages, MapletWeights, list[int]]:
    """The images of `views` that the weighting rules keep for `maplet`, with visibility against
    the tracer's shape, per-node weights and the region weight; and their indices in `views`."""
    vis, in_frame, geom = views_over_maplet(maplet, views, tracer)
    weights = weigh_maplet(maplet, vis, geom, in_frame=in_frame, rules=rules)
    suns = np.array([v.sun for v in views])
    keep = np.flatnonzero(weights.keep)
    n = maplet.n
    data = MapletImages(
        images=[views[k].image for k in keep], cameras=[views[k].camera for k in keep],
        poses=[views[k].pose for k in keep], sun_directions=suns[keep],
        visible=(vis.visible & in_frame)[keep].reshape(-1, n, n), lit=vis.lit[keep].reshape(-1, n, n),
        weights=weights.pixel[keep], region_weight=weights.region,
    )
    return data, weights, keep.tolist()


def refine_maplet(maplet: MapletGrid, views: list[View], tracer: RayTracer, *,
                  config: RefinementConfig = DEFAULTS, spots: MapletSpots = NO_SPOTS) -> MapletResult:
    """Weigh and refine one maplet; with fewer than config.min_images usable images it keeps its
    start's shape, placed on its lidar spots where it has enough (`placed_on_spots`).

    spots: the laser altimeter's over the maplet (pwm.maplets.spots_over). Every solution weighs
    them (pwm.photoclinometry.refine), and config.placement.lidar_spots of them or more place the
    maplet (`placed_on_spots`) instead of its images' parallax: the sweeps and parallax rises
    below are for maplets without.

    config.search_px: how far (px) the images may be off the maplet, from the pose knowledge (about
    3 sigma of position error / range plus pointing error, times the focal length), or three of
    its images' los_sigma_px where that is more: beyond a pixel, the images are registered
    (`pwm.alignment.register`) within it before the joint solution; within it, the joint solution
    holds the start's mean height, which a coarser start gets wrong by pixels of parallax, so the
    maplet is raised after the solution by what its offsets took up of the parallax (`_settled`),
    and first, where the start is much coarser (config.placement.sweep_start, or sweep_start_many
    under many images), to where its images agree best (`pwm.alignment.sweep_height`, over
    config.height_sweep_px of parallax), then solved on coarser grids (`_coarse_first`), and last,
    swept again from its refined relief (`_swept_again`). Within a pixel, with or without spots,
    the maplet is bent last by the parallax of its parts (`_reshaped`)."""
    clock = time.perf_counter()
    mode = config.mode
    data, weights, keep = maplet_images(maplet, views, tracer, rules=config.rules)
    search_px = max([config.search_px] + [config.knowledge_sigmas * views[k].los_sigma_px for k in keep])
    views_found = {role: views[i].name for role, i in vars(weights.views).items() if i is not None}
    dropped = {views[k].name: reasons for k, reasons in enumerate(weights.reasons) if reasons}
    refined = MapletGrid(name=maplet.name, frame=maplet.frame, spacing_km=maplet.spacing_km,
                         heights=maplet.heights.copy(),
                         albedo=None if maplet.albedo is None else maplet.albedo.copy(),
                         weight=weights.region if mode == "pwm" else 1.0, meta=dict(maplet.meta))
    iterations, converged, rms, raised, lidar_rms = 0, False, [], 0.0, float("nan")
    registrations: dict[str, tuple[float, float]] = {}
    on_spots = spots.count >= config.placement.lidar_spots
    if on_spots:
        # placed even where too few images see it to refine it
        maplet, raised = placed_on_spots(maplet, spots, placement=config.placement)
        refined.heights = maplet.heights.copy()
    if data.count >= config.min_images:
        # navigation knowledge errors move images by many pixels: register them before the joint
        # solution, which only corrects offsets within its linear reach (about a pixel); within
        # that, registering against the start's shading, itself off by its height errors, only
        # moves the joint solution's starting point away from the poses
        offsets = (register(maplet, data, levels=search_levels(search_px), registration=config.registration).offsets
                   if search_px > 1.0 else np.zeros((data.count, 2)))
        # A start can be off by pixels of parallax, and the joint solution holds its mean height;
        # where the poses are known within a pixel, their parallax places the maplet instead,
        # within the start's face size: a model's heights are not off by more than its faces are
        # long, and a rise beyond that (small parallax between the images, a repeating texture)
        # is a misplacement.
        start_edge_km = _start_edge_km(maplet, tracer)
        known = search_px <= 1.0
        placed = known and not on_spots
        coarse = start_edge_km / maplet.spacing_km
        placement = config.placement
        many = data.count >= placement.sweep_many_images
        swept = placed and config.height_sweep_px > 0 and (
            coarse >= placement.sweep_start or (coarse >= placement.sweep_start_many and many))
        if swept:
            raised = sweep_height(maplet, data, offsets, reach_px=config.height_sweep_px, max_rise_km=start_edge_km,
                                  follow=many)
            maplet = _coarse_first(_raised(maplet, raised), data, offsets=offsets, config=config)
        if mode == "pwm":
            # the start lacks the relief that casts most shadows: the images show them
            values = extract(maplet, data, offsets=offsets)
            data.shade = shade(values, data.weights, data.visible, config.rules)
            data.weights = np.where(dark_nodes(values, data.weights, config.rules), 0.0, data.weights)
        result = refine(maplet, data, mode=mode, offsets=offsets, solver=config.solver, spots=spots)
        if on_spots:
            result, raised = _settled_on_spots(maplet, data, result, spots=spots, config=config, raised_km=raised)
        if known:
            # an image that no node weighed kept its start offset: it says nothing
            sigma = np.where(np.isfinite(result.rms),
                             np.hypot([views[k].los_sigma_px for k in keep], placement.registration_px), np.inf)
            if placed:
                result, raised = _settled(maplet, data, result, sigma_px=sigma, config=config, raised_km=raised,
                                          max_rise_km=start_edge_km)
            result = _reshaped(maplet, data, result, sigma_px=sigma, config=config, max_rise_km=start_edge_km,
                               spots=spots)
        if swept:
            result, raised = _swept_again(maplet, data, result, offsets=offsets, config=config, raised_km=raised,
                                          max_rise_km=start_edge_km, follow=many)
        refined.heights, refined.albedo = result.heights, result.albedo
        refined.sigma = node_sigma(weights=result.weights, misfit=result.misfit,
                                   slope_gradients=result.slope_gradients, spacing_km=maplet.spacing_km,
                                   uncertainty=config.uncertainty)
        iterations, converged, rms = result.iterations, result.converged, [float(r) for r in result.rms]
        lidar_rms = result.lidar_rms
        seen = np.isfinite(result.rms)  # an image no node weighed kept its start: it observed nothing
        registrations = {views[k].name: (float(s), float(line)) for k, (s, line), ok in
                         zip(keep, landmark_pixels(refined, data, result.offsets), seen, strict=True) if ok}
    return MapletResult(maplet=refined, images=[views[k].name for k in keep], region_weight=weights.region,
                        five_views=views_found, dropped=dropped, iterations=iterations, converged=converged,
                        residual_rms=rms, seconds=time.perf_counter() - clock, registrations=registrations,
                        raised_km=raised, lidar_spots=spots.count, lidar_rms=lidar_rms)


def _coarse_first(maplet: MapletGrid, data: MapletImages, *, offsets: np.ndarray,
                  config: RefinementConfig) -> MapletGrid:
    """The maplet with the heights its images give on grids config.placement.coarse_factors times
    coarser, coarsest first (`pwm.photoclinometry.coarsened`, at least
    config.registration.min_coarse_nodes a side): each grid's change interpolated onto the nodes.
    A coarser model lacks relief metres high and a few metres across (on the campaign's site B
    under its 2 m survey, blobs of +-2 m): pixels of parallax over a few spacings, beyond a joint
    solution's linear reach at the maplet's spacing, which keeps most of such an error, but within
    a coarser grid's."""
    n = maplet.n
    for factor in config.placement.coarse_factors:
        if (n - 1) // factor + 1 < config.registration.min_coarse_nodes:
            continue
        coarse, coarse_data = coarsened(maplet, data, factor)
        result = refine(coarse, coarse_data, mode=config.mode, offsets=offsets, solver=config.solver)
        at = np.arange(n) * (coarse.n - 1) / (n - 1)
        change = ndimage.map_coordinates(result.heights - coarse.heights, np.meshgrid(at, at, indexing="ij"),
                                         order=1, mode="nearest")
        maplet = dataclasses.replace(maplet, heights=maplet.heights + change)
    return maplet


def _swept_again(maplet: MapletGrid, data: MapletImages, result: Refinement, *, offsets: np.ndarray,
                 config: RefinementConfig, raised_km: float, max_rise_km: float,
                 follow: bool) -> tuple[Refinement, float]:
    """The swept maplet's refinement swept again over config.placement.resweep_px of parallax from
    its refined heights and, where it moves, solved again from there: the start it was first
    swept with, a coarser model's relief, blurs where its images agree (a peak +-0.3 m wide on a
    start 0.5 m RMS off), and the refined relief sharpens it. The solution and the whole rise
    (km) from the start, within max_rise_km."""
    room = max_rise_km - abs(raised_km)
    if room <= 0:
        return result, raised_km
    refined = dataclasses.replace(maplet, heights=result.heights)  # the start's albedo stays the prior
    rise = sweep_height(refined, data, offsets, reach_px=config.placement.resweep_px, max_rise_km=room,
                        follow=follow)
    if rise == 0.0:
        return result, raised_km
    again = refine(_raised(refined, rise), data, mode=config.mode, offsets=offsets, solver=config.solver)
    return again, raised_km + rise


def _settled(maplet: MapletGrid, data: MapletImages, result: Refinement, *, sigma_px: np.ndarray,
             config: RefinementConfig, raised_km: float, max_rise_km: float) -> tuple[Refinement, float]:
    """The refinement solved again from a maplet raised by what its offsets took up of a height
    the start got wrong (`pwm.alignment.parallax_height`), while that is more than three sigma
    and the maplet stays within max_rise_km of its start, at most config.placement.parallax_rounds
    times; and the whole rise (km) from the start, of which raised_km was done before. All of them
    are undone where a rise leaves config.placement.runaway of itself in the solution after it."""
    raised, start, last = raised_km, (result, raised_km), None
    for _ in range(config.placement.parallax_rounds):
        rise, sigma = parallax_height(dataclasses.replace(maplet, heights=result.heights), data, result.offsets,
                                      sigma_px=sigma_px)
        if last is not None and abs(rise) > config.placement.runaway * abs(last):
            # the rise did not take up the parallax it was measured from: what the offsets show
            # is not the start's height (a common pointing error, a misregistered image), and
            # following it runs the maplet off by tens of metres
            return start
        if not (abs(rise) > 3 * sigma and abs(raised + rise) <= max_rise_km):
            break
        maplet, raised, last = _raised(maplet, rise), raised + rise, rise
        result = refine(maplet, data, mode=config.mode, offsets=result.offsets - rise * rise_motion(maplet, data),
                        solver=config.solver)
    return result, raised


def _reshaped(maplet: MapletGrid, data: MapletImages, result: Refinement, *, sigma_px: np.ndarray,
              config: RefinementConfig, max_rise_km: float, spots: MapletSpots = NO_SPOTS) -> Refinement:
    """The refinement solved again from its heights bent by the rises that the parallax of its
    images' offsets shows in square parts of about config.shape_window_nodes a side
    (`pwm.alignment.window_rises`; those beyond three sigma, interpolated linearly between the
    parts' centres, less their mean), unless the bend reaches beyond max_rise_km. A survey's
    start from photogrammetry is bent or tilted across a maplet where its points are sparse (a
    polar cap), and photoclinometry keeps that (`pwm.alignment.window_rises`)."""
    windows = maplet.n // config.shape_window_nodes if config.shape_window_nodes else 0
    if windows < 2:
        return result
    # a part's offsets rest on a windows-th of the nodes a side: the registration's error grows so
    part_sigma_px = np.hypot(sigma_px, config.placement.registration_px * windows)
    centres, rises, sigmas = window_rises(dataclasses.replace(maplet, heights=result.heights), data, result.offsets,
                                          albedo=result.albedo, sigma_px=part_sigma_px, windows=windows,
                                          search_px=config.placement.window_search_px,
                                          registration=config.registration)
    rises = np.where(np.abs(rises) > 3 * sigmas, rises, 0.0)
    if not rises.any():
        return result
    nodes = np.stack(np.meshgrid(np.arange(maplet.n), np.arange(maplet.n), indexing="ij"), axis=-1)
    bend = RegularGridInterpolator((centres, centres), rises, bounds_error=False, fill_value=None)(nodes)
    bend -= bend.mean()  # the maplet's mean height is the whole maplet's parallax to place (_settled)
    if np.max(np.abs(bend)) > max_rise_km:
        return result
    return refine(dataclasses.replace(maplet, heights=result.heights + bend), data, mode=config.mode,
                  solver=config.solver, offsets=result.offsets, spots=spots)


def _settled_on_spots(maplet: MapletGrid, data: MapletImages, result: Refinement, *, spots: MapletSpots,
                      config: RefinementConfig, raised_km: float) -> tuple[Refinement, float]:
    """The refinement solved again from the maplet raised by the spots' mean residual from its
    refined heights, where that is more than three of its sigmas; and the whole rise (km). The
    placement measured the spots against a start without the relief they fall on (a profile over
    a boulder's top lifts it), and the solution holds the mean height it was given."""
    xy = spots.local_km[:, :2]
    weight = spots.sigma_km ** -2.0
    rise = float(weight @ (spots.local_km[:, 2] - grid_heights(maplet, xy, result.heights)) / weight.sum())
    if abs(rise) <= 3 / np.sqrt(weight.sum()):
        return result, raised_km
    again = refine(_raised(maplet, rise), data, mode=config.mode, solver=config.solver, spots=spots,
                   offsets=result.offsets - rise * rise_motion(maplet, data))
    return again, raised_km + rise


def placed_on_spots(maplet: MapletGrid, spots: MapletSpots, *, placement: Placement) -> tuple[MapletGrid, float]:
    """The maplet moved by the plane through its spots' height residuals, weighed by their sigmas
    and tilted only along the directions in which the spots spread over placement.lidar_spread of
    its half side or more (a profile's spots say nothing across it); and the mean rise (km). The
    lidar places a start that is metres off as its images' parallax could, without their sweeps'
    false optima, and photoclinometry's ties then hold it there. No spot is left out as an
    outlier: those far above the rest are mostly on boulders the start lacks, which belong in the
    maplet's mean height (a track placed wrong is flagged by pwm.lidar.model.disagreement)."""
    xy = spots.local_km[:, :2]
    half = (maplet.n - 1) / 2 * maplet.spacing_km
    plane = _plane(xy, spots.local_km[:, 2] - grid_heights(maplet, xy), spots.sigma_km ** -2.0,
                   min_spread_km=placement.lidar_spread * half)
    nodes = maplet.nodes_local()[..., :2].reshape(-1, 2)
    rise = plane(nodes).reshape(maplet.n, maplet.n)
    return dataclasses.replace(maplet, heights=maplet.heights + rise), float(rise.mean())


def _plane(xy: np.ndarray, values: np.ndarray, weight: np.ndarray, *, min_spread_km: float
           ) -> Callable[[np.ndarray], np.ndarray]:
    """The weighted least-squares plane through values at points xy (M, 2), as a function of
    points, about the points' weighted centre and tilted only along the principal directions in
    which they spread (RMS) over min_spread_km."""
    w = weight / weight.sum()
    centre = w @ xy
    spread, axes = np.linalg.eigh(((xy - centre) * w[:, None]).T @ (xy - centre))
    along = axes[:, np.sqrt(np.maximum(spread, 0.0)) >= min_spread_km]
    design = np.column_stack([np.ones(len(xy)), (xy - centre) @ along])
    root = np.sqrt(w)
    coefficients = np.linalg.lstsq(design * root[:, None], values * root, rcond=None)[0]
    return lambda points: coefficients[0] + ((points - centre) @ along) @ coefficients[1:]


def landmark_pixels(maplet: MapletGrid, data: MapletImages, offsets: np.ndarray) -> np.ndarray:
    """Where each image sees the maplet's landmark, its centre node (K, 2; sample, line, px): the
    node projected with the image's pose, plus the offset that registered the image to the
    maplet. These are observations of the images' poses in the pixels of the images themselves,
    whatever poses they were registered with: a bundle adjustment takes them as a track of one
    point (SPC's landmarks)."""
    centre = maplet.node_body(maplet.n // 2, maplet.n // 2)
    return np.array([project(centre[None], camera, pose)[0] for camera, pose in
                     zip(data.cameras, data.poses, strict=True)]).reshape(-1, 2) + np.asarray(offsets, float)


def _start_edge_km(maplet: MapletGrid, tracer: RayTracer) -> float:
    """Median edge (km) of the start model's faces under the maplet (at 5 x 5 of its nodes)."""
    pick = np.linspace(0, maplet.n - 1, 5).round().astype(int)
    nodes = maplet.nodes_body()[np.ix_(pick, pick)].reshape(-1, 3)
    up = maplet.frame.rotation[2]
    hits = tracer.intersect(nodes + maplet.n * maplet.spacing_km * up, np.broadcast_to(-up, nodes.shape).copy())
    corners = tracer.mesh.vertices[tracer.mesh.faces[hits.face[hits.hit]]]
    return float(np.median(np.linalg.norm(corners[:, 1] - corners[:, 0], axis=1))) if len(corners) else 0.0


def _raised(maplet: MapletGrid, rise_km: float) -> MapletGrid:
    return dataclasses.replace(maplet, heights=maplet.heights + rise_km)


def search_levels(search_px: float) -> tuple[tuple[int, float], ...]:
    """Registration levels (factor, search px) for images up to search_px (> 1) off: full
    resolution only for a pixel or two (coarse levels could lock onto chance peaks that a close
    start never needs), coarse to fine beyond."""
    if search_px <= 2.0:
        return ((1, search_px),)
    return ((8, search_px), (4, min(search_px, 24.0)), (1, 1.0))


_WORKER: dict = {}


def _init_worker(start: Mesh, views: list[View], config: RefinementConfig, spots: Spots | None) -> None:
    # An Embree scene cannot cross processes: each process builds its own from the start model.
    _WORKER.update(tracer=RayTracer(start), views=views, config=config, spots=spots,
                   spot_tree=None if spots is None else cKDTree(spots.body_km))


def _refine_in_worker(maplet: MapletGrid) -> MapletResult:
    return refine_maplet(maplet, _WORKER["views"], _WORKER["tracer"], config=_WORKER["config"],
                         spots=_spots_near(maplet, _WORKER["spots"], _WORKER["spot_tree"]))


def _spots_near(maplet: MapletGrid, spots: Spots | None, tree: cKDTree | None) -> MapletSpots:
    """The spots over the maplet (pwm.maplets.spots_over), looked for within one and a half of its
    sides of its origin: its corners and a side above or below them."""
    if spots is None or tree is None:
        return NO_SPOTS
    near = tree.query_ball_point(maplet.frame.origin, 1.5 * (maplet.n - 1) * maplet.spacing_km)
    return spots_over(maplet, Spots(body_km=spots.body_km[near], sigma_km=spots.sigma_km[near]))


def refine_maplets(maplets: list[MapletGrid], views: list[View], start: Mesh, *, config: RefinementConfig = DEFAULTS,
                   workers: int = 1, progress: Progress | None = None, stage: str = "refine",
                   spots: Spots | None = None) -> list[MapletResult]:
    """Refine every maplet against `start` (in `workers` processes, pwm.parallel.map_processes),
    each with the lidar's spots over it (none without `spots`), telling `progress` (as `stage`)
    after each and logging each at DEBUG; results in input order."""
    results: list[MapletResult] = []
    clock = time.perf_counter()
    if progress is not None:
        progress(stage, 0, len(maplets))
    for k, result in enumerate(map_processes(_refine_in_worker, maplets, workers=workers, initializer=_init_worker,
                                             initargs=(start, views, config, spots)), 1):
        results.append(result)
        log.debug("maplet %d/%d %s: %d images, w_PWM %.2f, %d iterations (%.1f s; %.0f s elapsed)", k, len(maplets),
                  result.maplet.name, len(result.images), result.region_weight, result.iterations, result.seconds,
                  time.perf_counter() - clock)
        if progress is not None:
            progress(stage, k, len(maplets))
    return results


@dataclass(frozen=True)
class Region:
    """Where to refine: a disc of radius_km about a planetocentric lat/lon (degrees), and the
    maplet grid spacing (km) that the images there support."""

    lat_deg: float
    lon_deg: float
    radius_km: float
    spacing_km: float


def imaged_region(views: list[View], start: Mesh, *, radius_fraction: float = 0.35) -> Region:
    """The region the images look at: the mean of their boresight intercepts on the start model,
    a radius of `radius_fraction` of the median footprint width, and the median pixel scale."""
    from pwm.frames import unit_to_latlon

    tracer = RayTracer(start)
    origins = np.array([v.pose.position for v in views])
    bores = np.array([v.pose.boresight for v in views])
    hits = tracer.intersect(origins, bores)
    if not hits.hit.any():
        raise ValueError("no image's boresight meets the start model")
    centre = tracer.hit_points(origins, bores, hits)[hits.hit].mean(axis=0)
    lat, lon = unit_to_latlon(centre)
    pixel = hits.t[hits.hit] / np.array([views[k].camera.fx for k in np.flatnonzero(hits.hit)])
    width = np.array([views[k].camera.width for k in np.flatnonzero(hits.hit)]) * pixel
    return Region(lat_deg=float(lat), lon_deg=float(lon), radius_km=float(radius_fraction * np.median(width)),
                  spacing_km=float(np.median(pixel)))


def refine_region(start: Mesh, views: list[View], region: Region, *, config: RefinementConfig = DEFAULTS,
                  workers: int = 1, progress: Progress | None = None,
                  spots: Spots | None = None) -> tuple[Mesh, list[MapletResult]]:
    """Tile `region` of `start`, refine its maplets and fuse them, pass after pass: each later
    pass tiles the previous one's fused model afresh, so that a maplet starts from what its
    neighbours made of its edges, and its visibility and shadows come from a shape that has the
    relief (the start's lacks most of what casts shadows). Every maplet gets config.passes passes,
    and more while it has not settled (RefinementConfig.another_pass): a settled maplet keeps its
    last result. Each pass takes the shape only: the albedo comes from the images. Returns the
    last fused model and each maplet's last result. progress: told how far each pass's
    refinement has come (stage "refine pass P/N", N the most passes). spots: the lidar's, which
    every pass's maplets are refined with (`refine_maplets`)."""
    model = start
    settled: list[MapletResult] = []  # the maplets that settled, by their last results
    latest: list[MapletResult] = []  # the last pass's results of the rest
    for done in range(1, config.most_passes + 1):
        shape = Mesh(model.vertices, model.faces)
        maplets = tile(shape, spacing_km=region.spacing_km, nodes=config.nodes, overlap=config.overlap,
                       centre_lat_deg=region.lat_deg, centre_lon_deg=region.lon_deg, radius_km=region.radius_km)
        # a place is the same from pass to pass, not its name: its origin moves with the surface
        maplets = [m for m, kept in zip(maplets, _same_places(maplets, settled), strict=True) if kept is None]
        if not maplets:
            break
        log.info("pass %d/%d: %d maplets of %d nodes at %.3f m", done, config.most_passes, len(maplets), config.nodes,
                 region.spacing_km * 1e3)
        results = refine_maplets(maplets, views, shape, config=config, workers=workers, progress=progress,
                                 stage=f"refine pass {done}/{config.most_passes}", spots=spots)
        before, latest = latest, []
        for result, earlier in zip(results, _same_places([r.maplet for r in results], before), strict=True):
            changed = None if earlier is None else solution_change(earlier.maplet, result.maplet)
            (latest if config.another_pass(done=done, changed_spacings=changed) else settled).append(result)
        model, _ = fuse([r.maplet for r in settled + latest], shape, overlap=config.overlap)
    return model, settled + latest


def _same_places(maplets: list[MapletGrid], results: list[MapletResult]) -> list[MapletResult | None]:
    """For each maplet, the result of `results` whose maplet lies where it does (origins within an
    eighth of its side; neighbours lie at least a quarter of a side apart, at the most overlap), or
    None."""
    if not maplets or not results:
        return [None] * len(maplets)
    distance, nearest = cKDTree([r.maplet.frame.origin for r in results]).query([m.frame.origin for m in maplets])
    return [results[k] if d < 0.25 * m.axis_km[-1] else None
            for m, d, k in zip(maplets, distance, nearest, strict=True)]


def fuse(maplets: list[MapletGrid], base: Mesh, *, overlap: float) -> tuple[Mesh, LevelGrids]:
    """Fuse refined maplets, of any levels, with `base` (pwm.levels); the mesh carries each
    vertex's 1-sigma height from the maplets' (pwm.uncertainty.vertex_sigma)."""
    fusion = LevelGrids(taper_fraction=overlap)
    fusion.add_all(maplets, base=base)
    mesh = fusion.mesh(base)
    return dataclasses.replace(mesh, sigma=vertex_sigma(mesh.vertices, maplets, taper_fraction=overlap)), fusion
