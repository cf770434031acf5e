"""Stereo photogrammetry (SPG) on arrays: pairs by geometry, SIFT features matched under the
navigation poses, tracks triangulated with those poses, a bundle adjustment with pose priors,
and a surface through the points filled from the previous model.

No files here: `pwm spg` (service/cli/spg.py) reads a downlink into views.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field

import numpy as np
import trimesh

from pwm.camera import PoseCorrection, corrected_pose
from pwm.evaluate.distance import ClosestPoint
from pwm.mesh import Mesh
from pwm.raytrace import RayTracer
from pwm.spg.adjustment import bundle_adjust
from pwm.spg.config import SPG_DEFAULTS, SpgConfig
from pwm.spg.features import Features, extract, match_guided
from pwm.spg.hull import Hull, clip_to, visual_hull
from pwm.spg.pairs import Pair, choose_pairs, footprints
from pwm.spg.pose_models import PoseModel, free_poses
from pwm.spg.surface import at_resolution, fit_figure, fit_surface, point_spacing
from pwm.spg.ties import NO_TIES, MeasuredSurface, surface_ties
from pwm.spg.triangulation import Tracks, build_tracks, rays, reprojection_errors, triangulate
from pwm.spg.uncertainty import PoseSigma, image_sigmas, pose_uncertainty, prior_sigmas
from pwm.views import View

log = logging.getLogger(__name__)


@dataclass
class SpgResult:
    """The photogrammetric model (km, body-fixed), per-image-name pose corrections and their prior
    and posterior 1-sigma figures, the adjusted points (km) and figures of the run (counts,
    residuals, seconds)."""

    mesh: Mesh
    corrections: dict[str, PoseCorrection]
    points: np.ndarray
    pairs: list[Pair]
    stats: dict = field(default_factory=dict)
    sigmas: dict[str, tuple[PoseSigma, PoseSigma]] = field(default_factory=dict)


@dataclass
class Matching:
    """Pairs chosen, features per view, matches per pair {(first, second): (k, 2) keypoint
    indices}, each view's range to the model along its boresight (km) and its band (px: three
    sigma of the image motion its pose knowledge allows, plus one), and seconds spent."""

    pairs: list[Pair]
    features: list[Features]
    matches: dict[tuple[int, int], np.ndarray]
    ranges: np.ndarray
    bands: np.ndarray
    extract_s: float
    match_s: float


def match_views(views: list[View], tracer: RayTracer, *, ranges: np.ndarray | None = None,
                los_sigma_px: np.ndarray | None = None, config: SpgConfig = SPG_DEFAULTS) -> Matching:
    """Choose pairs on the model (`tracer`), extract SIFT features where each view sees the model
    and match them along the epipolar band the pose knowledge allows (los_sigma_px: each view's
    1-sigma line of sight per axis, px; default: from `config`'s sigmas).

    config.first_octave None: -1 (images doubled) for views where the model fills less than
    `config.double_below` of the frame, so that a small target yields features at its finest
    scale for little cost, else 0.
    """
    clock = time.perf_counter()
    prints = footprints(views, tracer, config=config)
    pairs = choose_pairs(views, prints, config=config)
    if not pairs:
        raise ValueError("no image pair overlaps with a usable stereo angle and illumination")
    ranges = _ranges(views, tracer) if ranges is None else ranges
    bands = _bands(views, ranges, config, los_sigma_px)
    windows = [p.window(v.camera, margin_px=max(v.camera.width, v.camera.height) / (config.footprint_grid - 1))
               for p, v in zip(prints, views, strict=True)]
    if config.first_octave is None:
        octaves = [-1 if (w[0].stop - w[0].start) * (w[1].stop - w[1].start)
                   < config.double_below * v.camera.width * v.camera.height else 0
                   for w, v in zip(windows, views, strict=True)]
    else:
        octaves = [config.first_octave] * len(views)
    features = extract([v.image for v in views], first_octave=octaves, windows=windows, config=config)
    extract_s = time.perf_counter() - clock
    matches = {}
    for p in pairs:
        a, b = views[p.first], views[p.second]
        band = bands[p.first] + bands[p.second]
        matches[(p.first, p.second)] = match_guided(features[p.first], features[p.second], camera_a=a.camera,
                                                    pose_a=a.pose, camera_b=b.camera, pose_b=b.pose,
                                                    max_error_px=band, config=config)
    return Matching(pairs=pairs, features=features, matches=matches, ranges=ranges, bands=bands,
                    extract_s=extract_s, match_s=time.perf_counter() - clock - extract_s)


@dataclass
class PoseAdjustment:
    """A bundle adjustment of views on a model: per-image-name pose corrections, their prior and
    posterior 1-sigma figures, the adjusted points (km) with their triangulation angles (rad),
    the pairs matched and figures of the run (counts, residuals, seconds, the pose model's
    unknowns with their prior and posterior sigmas)."""

    corrections: dict[str, PoseCorrection]
    sigmas: dict[str, tuple[PoseSigma, PoseSigma]]
    points: np.ndarray
    angles: np.ndarray
    pairs: list[Pair]
    stats: dict


def adjust_poses(views: list[View], model: Mesh, *, pose_model: PoseModel | None = None, anchor: bool = False,
                 landmarks: Tracks | None = None, surface: MeasuredSurface | None = None,
                 config: SpgConfig = SPG_DEFAULTS) -> PoseAdjustment:
    """Match `views` on `model` and adjust their poses (pwm.spg.adjustment.bundle_adjust).

    pose_model: what the adjustment may change (pwm.spg.pose_models; default: every image free,
    with priors config.sigma_position_km and config.sigma_pointing_rad per axis); its prior line
    of sight sizes each view's matching band. config.model_tolerance_px: how far (in pixels of
    the image) a triangulated point may lie from `model` along its line of sight before it
    counts as a mismatch; observations whose residual exceeds config.max_residual_px are left
    out and the adjustment made again. The matching's settings: see `match_views`.

    anchor: tie the block to `model`. A shift of every camera and point together leaves the
    images as they are, so only the priors place the block; when `model` is a shape to keep (not
    a first guess), the adjusted points are shifted onto it (point to plane, `anchor_shift`) and
    the cameras with them, as far as the shift's covariance against the block's (from the
    adjustment) says: fully where the model's relief places the block better than the priors
    do, hardly at all on a coarse model. The shift alone: a turn of the block would move the
    split between the cameras' positions and pointings that the images leave to the priors.

    landmarks: observations of points no feature needs to find, such as the maplets' landmarks
    (pwm.pipeline.landmark_pixels; image indices into `views`), adjusted with the feature tracks;
    with landmarks, views that no feature pair joins are still adjusted.

    surface: the spots of the surface another instrument measured (the lidar's): the points
    among them are tied to their planes (pwm.spg.ties), which places the block, as well as that
    instrument's own frame is placed, where the images alone leave it to the priors; tied again
    where the first adjustment put them (the kernels' poses can put a point metres off its ground).
    """
    clock = time.perf_counter()
    if pose_model is None:
        pose_model = free_poses(len(views), sigma_position_km=config.sigma_position_km,
                                sigma_pointing_rad=config.sigma_pointing_rad)
    tracer = RayTracer(model)
    cameras, poses = [v.camera for v in views], [v.pose for v in views]
    ranges = _ranges(views, tracer)
    prior_los = np.array([s.los_px for s in prior_sigmas(pose_model, cameras, poses, ranges)]) / np.sqrt(2)  # per axis
    stats: dict = {}
    try:
        m = match_views(views, tracer, ranges=ranges, los_sigma_px=prior_los, config=config)
    except ValueError:
        if landmarks is None or landmarks.n_points == 0:
            raise
        pairs, tracks = [], _NO_TRACKS
    else:
        pairs = m.pairs
        stats.update(extract_s=m.extract_s, match_s=m.match_s, features=int(sum(len(f.xy) for f in m.features)),
                     matches=int(sum(len(x) for x in m.matches.values())))
        log.info("%d pairs, %d features, %d matches (%.1f s)", len(pairs), stats["features"], stats["matches"],
                 time.perf_counter() - clock)
        tracks = build_tracks(m.matches, [f.xy for f in m.features])
        if tracks.n_points:
            tracks = _consistent(tracks, cameras, poses, tracer, ranges, m.bands, config.model_tolerance_px)
    stats["feature_tracks"] = tracks.n_points
    if landmarks is not None:
        stats["landmarks"] = landmarks.n_points
        tracks = tracks.joined(landmarks)
    if tracks.n_points == 0:
        raise ValueError("no feature track is consistent with the model and the pose knowledge")
    points, _ = triangulate(tracks, cameras, poses)
    ties = NO_TIES if surface is None else surface_ties(points, surface, config=config)
    adjusted = bundle_adjust(points, tracks, cameras, poses, model=pose_model, ties=ties, config=config)
    keep = adjusted.residuals_px <= config.max_residual_px
    if not keep.all() or surface is not None:
        # once more without the mismatches, which the Huber weights only damped
        tracks = tracks.subset(keep)
        if surface is not None:
            first = [corrected_pose(p, adjusted.position_corrections[i], adjusted.rotation_corrections[i])
                     for i, p in enumerate(poses)]
            ties = surface_ties(triangulate(tracks, cameras, first)[0], surface, config=config)
        points, _ = triangulate(tracks, cameras, poses)
        adjusted = bundle_adjust(points, tracks, cameras, poses, model=pose_model, ties=ties, config=config)
    if surface is not None:
        stats.update(ties=len(ties), tie_rms_m=float(np.sqrt(np.mean(adjusted.tie_distances_km**2))) * 1e3
                     if len(ties) else None)
        if len(adjusted.frame) == 6:  # how far the images moved the ties' frame (the frame_motion's order)
            stats.update(tie_frame_shift_m=[float(v) * ties.frame_km * 1e3 for v in adjusted.frame[:3]],
                         tie_frame_turn_urad=[float(v) * ties.frame_rad * 1e6 for v in adjusted.frame[3:]])
    positions, rotations = adjusted.position_corrections, adjusted.rotation_corrections
    final = [corrected_pose(p, positions[i], rotations[i]) for i, p in enumerate(poses)]
    points, angles = triangulate(tracks, cameras, final)
    if anchor:
        anchoring = angles >= np.radians(config.anchor_min_angle_deg) / 2
        measured, measured_covariance = anchor_shift(points[anchoring], model, config=config)
        # weighed against what the adjustment knows of the block's place: the covariance of the
        # images' mean position correction
        noise = max(float(np.sqrt(np.mean(adjusted.residuals_px**2))), 0.1) / np.sqrt(2)
        position = adjusted.covariance(noise).reshape(len(poses), 6, len(poses), 6)[:, :3, :, :3]
        block = position.mean(axis=(0, 2))
        shift = block @ np.linalg.solve(block + measured_covariance, measured)
        stats["anchor_shift_m"] = [float(v) * 1e3 for v in shift]
        stats["anchor_measured_m"] = [float(v) * 1e3 for v in measured]
        positions = positions + shift
        final = [corrected_pose(p, positions[i], rotations[i]) for i, p in enumerate(poses)]
        points = points + shift
    residual = reprojection_errors(points, tracks, cameras, final)
    stats.update(pairs=len(pairs), tracks=tracks.n_points, observations=len(tracks.image),
                 residual_rms_px=float(np.sqrt(np.mean(residual**2))), iterations=adjusted.iterations)
    noise_px = max(stats["residual_rms_px"], 0.1) / np.sqrt(2)
    stats["uncertainty"] = pose_uncertainty(adjusted, cameras, poses, ranges, noise_px=noise_px)
    if len(pose_model.names) < 6 * len(views):  # a model of shared unknowns: what each was found to be
        sigma = np.sqrt(np.diag(adjusted.parameter_covariance(noise_px)))
        stats["unknowns"] = [{"name": name, "value": float(v * scale), "prior_sigma": float(scale),
                              "posterior_sigma": float(s * scale)} for name, v, scale, s in
                             zip(pose_model.names, adjusted.parameters, pose_model.scale, sigma, strict=True)]
    priors, posteriors = image_sigmas(adjusted, cameras, poses, ranges, noise_px=noise_px)
    corrections = {v.name: PoseCorrection(_triple(positions[i]), _triple(rotations[i])) for i, v in enumerate(views)}
    sigmas = {v.name: (priors[i], posteriors[i]) for i, v in enumerate(views)}
    stats["seconds"] = time.perf_counter() - clock
    return PoseAdjustment(corrections=corrections, sigmas=sigmas, points=points, angles=angles, pairs=pairs,
                          stats=stats)


def stereo_photogrammetry(views: list[View], previous: Mesh, *, pose_model: PoseModel | None = None,
                          from_figure: bool = False, config: SpgConfig = SPG_DEFAULTS) -> SpgResult:
    """The photogrammetric model and pose corrections from `views`, starting from `previous`:
    `adjust_poses` (pose_model: what it may change, by default every image free with
    config.sigma_position_km and config.sigma_pointing_rad, the 1-sigma navigation knowledge per
    axis), then a surface through the points seen at a stereo angle of at least
    config.min_angle_deg: `previous` moved towards the points near them (fit_surface).

    from_figure: `previous` is only the body's reference figure (its PCK ellipsoid), no model
    yet: the points are interpolated over the whole of a figure (fit_figure). Where the views'
    visual hull can be made (pwm.spg.hull, carved in config.hull.bound_radii of the figure's
    largest radius: closed, and no larger than config.hull.max_figure_volumes figures), the
    matching runs on the hull; the figure interpolated is the hull where the points lie
    config.hull.preference times closer to it than to the reference figure (RMS; a hull carved by
    few views is loose between the points, bumps the smooth interpolation cannot take out, so
    it must be clearly the better figure: a contact binary's ellipsoid bridging the neck and
    missing the lobes' ends), else the reference figure; and the surface is clipped to the
    hull, which holds the body.
    """
    clock = time.perf_counter()
    stats: dict = {}
    hull = _hull(views, previous, config=config) if from_figure else None
    if hull is not None:
        stats.update(hull_cell_km=hull.cell_km, hull_volume_km3=hull.volume_km3, hull_views=hull.carving_views)
    adjusted = adjust_poses(views, previous if hull is None else hull.mesh, pose_model=pose_model, config=config)
    stats.update(adjusted.stats)
    good_point = adjusted.angles >= np.radians(config.min_angle_deg) / 2
    points = adjusted.points[good_point]
    stats["points"] = int(good_point.sum())
    spacing = point_spacing(points)
    if hull is not None:
        misfit = {name: float(np.sqrt(np.mean(ClosestPoint(shape).query(points)[0] ** 2)))
                  for name, shape in (("visual hull", hull.mesh), ("reference figure", previous))}
        stats["figure_misfit_m"] = {name: value * 1e3 for name, value in misfit.items()}
        closer = misfit["visual hull"] * config.hull.preference < misfit["reference figure"]
        stats["figure"] = "visual hull" if closer else "reference figure"
        if closer:
            previous = hull.mesh
    resampled = at_resolution(previous, 2.0 * spacing, points)
    surface = (fit_figure(resampled, points) if from_figure
               else fit_surface(resampled, points, radius_km=2.0 * spacing))
    if hull is not None:
        surface = clip_to(surface, hull.mesh)
    stats.update(point_spacing_km=spacing, surface_vertices=len(surface.vertices), seconds=time.perf_counter() - clock)
    log.info("SPG: %d points at %.2f m spacing, residual %.2f px RMS, %d vertices (%.1f s)", len(points), spacing * 1e3,
             stats["residual_rms_px"], len(surface.vertices), stats["seconds"])
    return SpgResult(mesh=surface, corrections=adjusted.corrections, points=points, pairs=adjusted.pairs, stats=stats,
                     sigmas=adjusted.sigmas)


def _volume(mesh: Mesh) -> float:
    return float(trimesh.Trimesh(mesh.vertices, mesh.faces, process=False).volume)


def _hull(views: list[View], figure: Mesh, *, config: SpgConfig) -> Hull | None:
    """The views' visual hull in place of the reference `figure`, or None where it failed: not
    closed, or larger than config.hull.max_figure_volumes figures (what no outline carved)."""
    radius = float(np.linalg.norm(figure.vertices, axis=1).max())
    hull = visual_hull(views, bound_km=config.hull.bound_radii * radius, config=config.hull)
    if hull is None:
        log.info("no visual hull: no view carved anything; starting from the reference figure")
        return None
    figure_volume = _volume(figure)
    if not hull.closed or hull.volume_km3 > config.hull.max_figure_volumes * figure_volume:
        log.info("visual hull of %.4g km^3 against a figure of %.4g km^3 (closed: %s): the outlines do not hold "
                 "the body; starting from the reference figure", hull.volume_km3, figure_volume, hull.closed)
        return None
    return hull


MIN_SCATTER_KM = 1e-6  # the anchor's pairs are never taken to fit better than a millimetre
UNCONSTRAINED_KM2 = 1e6  # the variance of a shift no normal constrains


def anchor_shift(points: np.ndarray, model: Mesh, *,
                 config: SpgConfig = SPG_DEFAULTS) -> tuple[np.ndarray, np.ndarray]:
    """The shift (km) that moves `points` onto `model` (point to plane, the shift alone),
    leaving out the worst fifth of the pairs (mismatches, and relief the model lacks), and its
    covariance (km^2): the pairs' scatter through the normals they constrain (a direction no
    normal constrains, a plane's sliding, keeps a zero shift of vast variance) plus half the
    model's local edge length in every direction, since a model places nothing more finely
    than it is sampled. At most config.anchor_iterations steps."""
    shift = np.zeros(3)
    if len(points) < 6:
        return shift, np.eye(3)
    surface = ClosestPoint(model)
    for _ in range(config.anchor_iterations):
        distance, closest, face = surface.query(points + shift)
        keep = distance <= 2.0 * np.quantile(distance, 0.8)
        normals = surface.face_normals[face[keep]]
        gap = np.einsum("ij,ij->i", normals, closest[keep] - points[keep] - shift)
        step = np.linalg.lstsq(normals.T @ normals, normals.T @ gap, rcond=1e-6)[0]
        shift = shift + step
        if np.linalg.norm(step) < 1e-9:
            break
    scatter = max(float(np.mean((gap - normals @ step) ** 2)), MIN_SCATTER_KM**2)
    values, vectors = np.linalg.eigh(normals.T @ normals)
    variances = np.where(values > 1e-9 * values.max(), scatter / np.maximum(values, 1e-300), UNCONSTRAINED_KM2)
    faces = model.vertices[model.faces[face[keep]]]
    edge = float(np.median(np.linalg.norm(faces[:, 1] - faces[:, 0], axis=1)))
    return shift, (vectors * variances) @ vectors.T + (0.5 * edge) ** 2 * np.eye(3)


_NO_TRACKS = Tracks(point=np.zeros(0, np.int64), image=np.zeros(0, np.int64), xy=np.zeros((0, 2)))


def _triple(values: np.ndarray) -> tuple[float, float, float]:
    x, y, z = (float(v) for v in values)
    return x, y, z


def _ranges(views: list[View], tracer: RayTracer) -> np.ndarray:
    """Distance (km) along each boresight to the model, or to the body centre where it misses."""
    origins = np.array([v.pose.position for v in views])
    bores = np.array([v.pose.boresight for v in views])
    hits = tracer.intersect(origins, bores)
    return np.where(hits.hit, hits.t, np.linalg.norm(origins, axis=1))


def _bands(views: list[View], ranges: np.ndarray, config: SpgConfig, los_sigma_px: np.ndarray | None) -> np.ndarray:
    """Per view, three sigma of the image displacement its pose knowledge allows (px), plus one:
    from los_sigma_px, else from config's sigmas."""
    if los_sigma_px is None:
        los_sigma_px = np.array([v.camera.fx * float(np.hypot(config.sigma_position_km / r, config.sigma_pointing_rad))
                                 for v, r in zip(views, ranges, strict=True)])
    return 1.0 + 3.0 * np.asarray(los_sigma_px, float)


def _consistent(tracks: Tracks, cameras, poses, tracer: RayTracer, ranges: np.ndarray, band: np.ndarray,
                model_tolerance_px: float) -> Tracks:
    """Tracks whose rays meet within the navigation band and whose points lie near the previous
    model along the first observation's line of sight."""
    points, _ = triangulate(tracks, cameras, poses)
    tracks = tracks.subset(reprojection_errors(points, tracks, cameras, poses) <= band[tracks.image])
    points, _ = triangulate(tracks, cameras, poses)
    origins, dirs = rays(tracks, cameras, poses)
    first = np.unique(tracks.point, return_index=True)[1]
    hits = tracer.intersect(origins[first], dirs[first])
    along = np.einsum("ij,ij->i", points - origins[first], dirs[first])
    pixel_km = ranges[tracks.image[first]] / np.array([cameras[i].fx for i in tracks.image[first]])
    near = hits.hit & (np.abs(along - hits.t) <= model_tolerance_px * pixel_km)
    return tracks.subset(near[tracks.point])
