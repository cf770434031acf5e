"""Stereo photogrammetry: tracks, bundle adjustment with pose priors, the surface, and `pwm spg`
end to end on the tiny simulation."""

from __future__ import annotations

import ast
import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
import typer
from scipy.spatial.transform import Rotation
from typer.testing import CliRunner

import pwm.spg as pwm_spg
import service.cli.spg as service_cli_spg
import service.spg as service_spg
from pwm.camera import Camera, Pose, corrected_pose, look_at, project
from pwm.io.downlink import read_downlink
from pwm.knowledge import NavigationErrors
from pwm.mesh import Mesh
from pwm.simulate.knowledge import Knowledge, perturb
from pwm.spg import PoseCorrection
from pwm.spg.adjustment import bundle_adjust
from pwm.spg.config import SPG_DEFAULTS, SpgConfig
from pwm.spg.features import fundamental
from pwm.spg.photogrammetry import adjust_poses, anchor_shift
from pwm.spg.pose_models import navigation_poses
from pwm.spg.surface import fit_figure, fit_surface, point_spacing, subdivide
from pwm.spg.ties import MeasuredSurface, surface_ties
from pwm.spg.triangulation import Tracks, build_tracks, triangulate
from pwm.spg.uncertainty import DETERMINED, determined, image_sigmas, pose_uncertainty
from pwm.trajectory import track_frames
from pwm.views import View
from service.cli import app
from service.cli.spg import spg_config

CAMERA = Camera(width=1024, height=1024, fx=14729.4, fy=14729.4, cx=511.5, cy=511.5)


def _sphere(levels: int) -> Mesh:
    octahedron = Mesh(np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], float),
                      np.array([[0, 2, 4], [2, 1, 4], [1, 3, 4], [3, 0, 4],
                                [2, 0, 5], [1, 2, 5], [3, 1, 5], [0, 3, 5]]))
    for _ in range(levels):
        octahedron = subdivide(octahedron)
    return Mesh(octahedron.vertices / np.linalg.norm(octahedron.vertices, axis=1, keepdims=True), octahedron.faces)


def _edge_uses(mesh: Mesh) -> np.ndarray:
    f = mesh.faces
    edges = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
    return np.unique(edges, axis=0, return_counts=True)[1]


def _scene(rng: np.random.Generator) -> tuple[np.ndarray, list]:
    """Points on a rough 50 m patch 1.5 km from eight cameras looking at it from a ring."""
    xy = rng.uniform(-0.025, 0.025, (400, 2))
    points = np.column_stack([xy, 0.002 * rng.standard_normal(400)])
    poses = [look_at(np.array([1.47 * np.sin(e) * np.cos(a), 1.47 * np.sin(e) * np.sin(a), 1.47 * np.cos(e)]),
                     np.zeros(3), np.array([0, 1.0, 0]))
             for e, a in [(0.05, 0.0)] + [(np.radians(30), k * np.pi / 3.5) for k in range(7)]]
    return points, poses


def test_subdivision_keeps_a_closed_surface_closed():
    sphere = _sphere(2)
    finer = subdivide(sphere)
    assert len(finer.faces) == 4 * len(sphere.faces)
    assert set(_edge_uses(sphere)) == set(_edge_uses(finer)) == {2}
    assert np.isclose(finer.face_areas().sum(), sphere.face_areas().sum())


def test_fundamental_matrix_holds_for_projected_points():
    points, poses = _scene(np.random.default_rng(1))
    a, b = poses[0], poses[3]
    xa = np.column_stack([project(points, CAMERA, a) + 0.5, np.ones(len(points))])
    xb = np.column_stack([project(points, CAMERA, b) + 0.5, np.ones(len(points))])
    f = fundamental(CAMERA, a, CAMERA, b)
    line = xa @ f.T
    distance = np.abs(np.einsum("ij,ij->i", xb, line)) / np.hypot(line[:, 0], line[:, 1])
    assert distance.max() < 1e-6
    wrong = np.abs(np.einsum("ij,ij->i", xb[::-1], line)) / np.hypot(line[:, 0], line[:, 1])
    assert np.median(wrong) > 1.0


def test_tracks_join_matches_and_drop_conflicts():
    keypoints = [np.arange(8.0).reshape(4, 2) + 10 * i for i in range(3)]
    matches = {(0, 1): np.array([[0, 0], [1, 1], [2, 2]]), (1, 2): np.array([[0, 3], [2, 1]]),
               (0, 2): np.array([[2, 2]])}
    tracks = build_tracks(matches, keypoints)
    # point 0 spans three images; keypoint 2 of image 0 reaches keypoints 1 and 2 of image 2: dropped
    assert tracks.n_points == 2
    sizes = sorted(np.bincount(tracks.point))
    assert sizes == [2, 3]
    assert all(len(np.unique(tracks.image[tracks.point == p])) == n
               for p, n in zip(range(2), np.bincount(tracks.point), strict=True))


def _observed(rng: np.random.Generator) -> tuple[Tracks, list]:
    """Every point of `_scene` seen by every camera with 0.2 px of noise, and the true poses."""
    points, truth = _scene(rng)
    image = np.repeat(np.arange(len(truth)), len(points))
    point = np.tile(np.arange(len(points)), len(truth))
    xy = np.concatenate([project(points, CAMERA, p) for p in truth]) + 0.2 * rng.standard_normal((len(image), 2))
    return Tracks(point=point, image=image, xy=xy), truth


def test_bundle_adjustment_removes_line_of_sight_errors():
    rng = np.random.default_rng(2)
    tracks, truth = _observed(rng)
    noisy = [corrected_pose(p, rng.normal(0, 1e-3, 3), rng.normal(0, 1e-4, 3)) for p in truth]
    cameras = [CAMERA] * len(truth)
    start, _ = triangulate(tracks, cameras, noisy)
    result = bundle_adjust(start, tracks, cameras, noisy, sigma_position_km=1e-3, sigma_pointing_rad=1e-4)
    fixed = [corrected_pose(p, result.position_corrections[i],
                            result.rotation_corrections[i]) for i, p in enumerate(noisy)]

    def los_px(poses):
        # a shift common to all images moves the whole block: only the priors see it
        d = np.array([project(np.zeros(3), CAMERA, p) - project(np.zeros(3), CAMERA, t)
                      for p, t in zip(poses, truth, strict=True)])
        return np.sqrt(np.mean(np.sum((d - d.mean(axis=0)) ** 2, axis=1)))

    def position_m(poses):
        return np.sqrt(np.mean([np.sum((p.position - t.position) ** 2)
                                for p, t in zip(poses, truth, strict=True)])) * 1e3

    assert np.sqrt(np.mean(result.residuals_px**2)) < 0.4
    assert los_px(noisy) > 3.0
    assert los_px(fixed) < 0.5 * los_px(noisy)
    assert position_m(fixed) < 0.6 * position_m(noisy)


def test_narrow_field_fixes_the_line_of_sight_not_the_pointing():
    tracks, truth = _observed(np.random.default_rng(3))
    cameras = [CAMERA] * len(truth)
    result = bundle_adjust(triangulate(tracks, cameras, truth)[0], tracks, cameras, truth, sigma_position_km=1e-3,
                           sigma_pointing_rad=1e-4)
    u = pose_uncertainty(result, cameras, truth, np.full(len(truth), 1.47), noise_px=0.2)
    assert np.isclose(u["pointing_urad_prior"], np.sqrt(2) * 100) and np.isclose(u["lateral_m_prior"], np.sqrt(2))
    # the images pin an image's line of sight to a fraction of a pixel ...
    assert u["los_one_image_px"] < 0.05 * u["los_px_prior"]
    # ... but even with every other camera known, a 1 m prior on position leaves an image's
    # pointing near its prior: lateral position and pointing are all but perfectly correlated
    assert u["pointing_one_image_urad"] > 0.8 * u["pointing_urad_prior"]
    assert u["lateral_pointing_correlation"] > 0.99
    # with its position known too, the same image would fix its pointing
    assert u["pointing_alone_urad"] < 0.1 * u["pointing_urad_prior"]
    # each image's own figures: what the images determined is its line of sight, not the split
    priors, posteriors = image_sigmas(result, cameras, truth, np.full(len(truth), 1.47), noise_px=0.2)
    assert np.median([p.los_px for p in posteriors]) == pytest.approx(u["los_px_posterior"])
    for prior, posterior in zip(priors, posteriors, strict=True):
        assert posterior.los_px < DETERMINED * prior.los_px
        assert posterior.pointing_urad > DETERMINED * prior.pointing_urad
        assert "los_px" in determined(prior, posterior) and "pointing_urad" not in determined(prior, posterior)


def test_surface_follows_points_and_keeps_the_model_elsewhere():
    sphere = _sphere(4)
    cap = sphere.vertices[:, 2] > 0.8
    points = 1.01 * sphere.vertices[cap]
    surface = fit_surface(sphere, points, radius_km=0.03, prior_weight=0.01, smoothing=0)
    radius = np.linalg.norm(surface.vertices, axis=1)
    assert np.array_equal(surface.faces, sphere.faces)
    assert np.abs(radius[sphere.vertices[:, 2] > 0.9] - 1.01).max() < 1e-3
    assert np.abs(radius[sphere.vertices[:, 2] < 0.5] - 1.0).max() < 1e-12


def test_a_figure_bends_to_points_in_a_few_clusters_everywhere():
    # a body whose shape differs from its reference figure at long wavelengths (a ridge and a
    # squashing, 5% of the radius), seen by stereo points in 8 clusters only, with noise and a
    # few mismatches: the whole surface follows, not only the places under the points
    def body(u: np.ndarray) -> np.ndarray:
        return 1.0 + 0.05 * (1.5 * u[:, 2] ** 2 - 0.5) * -1 + 0.03 * u[:, 0] * u[:, 1]

    rng = np.random.default_rng(1)
    figure = _sphere(4)
    centres = rng.normal(size=(16, 3))
    u = np.repeat(centres / np.linalg.norm(centres, axis=1, keepdims=True), 20, axis=0) + rng.normal(0, 0.08, (320, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    points = u * (body(u) + rng.normal(0, 0.003, len(u)))[:, None]
    points[:8] *= 1.3  # mismatches

    def error(mesh: Mesh) -> float:
        radius = np.linalg.norm(mesh.vertices, axis=1)
        return float(np.sqrt(np.mean((radius - body(mesh.vertices / radius[:, None])) ** 2)))

    fitted = fit_figure(figure, points)
    local = fit_surface(figure, points, radius_km=2.0 * point_spacing(points))
    assert np.array_equal(fitted.faces, figure.faces)
    assert error(fitted) < 0.4 * error(figure) and error(fitted) < 0.5 * error(local)


def test_spg_command_on_the_tiny_downlink(tiny_sim, tmp_path):
    downlink = tiny_sim / "downlink"
    out = tmp_path / "spg"
    result = CliRunner().invoke(app,
                                ["spg", str(downlink), "--start", str(downlink / "start_model.obj"), "--out", str(out)])
    assert result.exit_code == 0, result.output
    stats = json.loads((out / "spg.json").read_text())
    assert stats["points"] >= 30 and stats["residual_rms_px"] < 1.5
    written = json.loads((out / "corrections.json").read_text())["images"]
    corrections = {k: PoseCorrection(**v) for k, v in written.items()}
    plain = read_downlink(downlink).views
    assert set(corrections) == {v.name for v in plain}
    moved = read_downlink(downlink, corrections=corrections).views
    for a, b in zip(plain, moved, strict=True):
        c = corrections[a.name]
        assert np.allclose(b.pose.position, a.pose.position + np.array(c.position_km))
        assert np.allclose(b.pose.rotation, corrected_pose(a.pose, np.zeros(3), np.array(c.rotation_rad)).rotation)
    for name in ("spg.ply", "spg.obj"):
        assert (out / name).stat().st_size > 0


def _orbit_passes(rng: np.random.Generator) -> tuple[np.ndarray, list, np.ndarray]:
    """Twenty views of a 50 m site from two passes of an orbit 1.5 km above it, four days apart
    (two navigation arcs), and points on the site."""
    site = np.array([0.0, 0.0, 0.25])
    points = np.column_stack([rng.uniform(-0.025, 0.025, (300, 2)), 0.25 + 0.002 * rng.standard_normal(300)])
    times, poses = [], []
    for tilt, start in [(0.3, 0.0), (-0.5, 4 * 86400.0)]:
        for phase in np.linspace(-0.6, 0.6, 10):
            position = Rotation.from_rotvec([tilt, 0, 0]).apply([1.75 * np.sin(phase), 0, 1.75 * np.cos(phase)])
            times.append(6e8 + start + (phase + 0.6) / (2 * np.pi) * 86400)
            poses.append(look_at(position, site + rng.normal(0, 0.003, 3), np.array([0, 1.0, 0])))
    return np.array(times), poses, points


NAVIGATION = NavigationErrors(along_m=3, cross_m=1, misalign_urad=50, drift_urad=20)


def _navigated(times: np.ndarray, truth: list, rng: np.random.Generator) -> tuple[NavigationErrors, Knowledge, list]:
    """Navigation-like knowledge errors of the true poses: the errors, what was drawn, the kernels' poses."""
    drawn = perturb(NAVIGATION, times=times, positions_km=np.array([p.position for p in truth]),
                    rotations=np.array([p.rotation for p in truth]), rng=rng)
    return NAVIGATION, drawn, [Pose(position=drawn.positions_km[i], rotation=drawn.rotations[i])
                               for i in range(len(truth))]


def test_navigation_pose_model_recovers_what_the_images_determine():
    rng = np.random.default_rng(0)
    times, truth, points = _orbit_passes(rng)
    errors, drawn, kernels = _navigated(times, truth, rng)
    n = len(truth)
    tracks = Tracks(point=np.tile(np.arange(len(points)), n), image=np.repeat(np.arange(n), len(points)),
                    xy=np.concatenate([project(points, CAMERA, p) for p in truth])
                    + 0.2 * rng.standard_normal((n * len(points), 2)))
    cameras = [CAMERA] * n
    model = navigation_poses(times, kernels, errors)
    assert len(model.names) == 2 * 12 + 6  # two arcs of 3 axes x 4 terms, misalignment, drift
    # the errors drawn are what the model can express (both take the track frames of the kernels'
    # trajectory): within 1 mm and 1e-3 microradian
    target = np.concatenate([np.r_[-drawn.position_error_m[i] * 1e-3, drawn.pointing_error_body_rad[i]]
                             for i in range(n)])
    true_theta = np.linalg.lstsq(model.design.toarray(), target, rcond=None)[0]
    misfit = np.abs(model.design @ true_theta - target).reshape(n, 6)
    assert misfit[:, :3].max() < 1e-6 and misfit[:, 3:].max() < 1e-9

    result = bundle_adjust(triangulate(tracks, cameras, kernels)[0], tracks, cameras, kernels, model=model)
    fixed = [corrected_pose(p, result.position_corrections[i], result.rotation_corrections[i])
             for i, p in enumerate(kernels)]

    def los_px(poses):
        d = [project(np.array([0, 0, 0.25]), CAMERA, p) - project(np.array([0, 0, 0.25]), CAMERA, t)
             for p, t in zip(poses, truth, strict=True)]
        return float(np.sqrt(np.mean(np.sum(np.square(d), axis=1))))

    assert los_px(fixed) < 0.3 * los_px(kernels)
    # the unknowns the posterior says the images determined come out within half their truth
    posterior = np.sqrt(np.diag(result.parameter_covariance(0.2)))
    determined = posterior < DETERMINED
    assert 0 < determined.sum() < len(determined)  # some are left to the priors
    error = result.parameters[determined] - true_theta[determined]
    assert np.sqrt(np.mean(error**2)) < 0.5 * np.sqrt(np.mean(true_theta[determined] ** 2))
    # and each arc's position error shrinks in every track axis
    frames = track_frames(times, np.array([p.position for p in truth]))
    for arc in drawn.arcs:
        after = np.einsum("kij,kj->ki", frames[arc], np.array([fixed[i].position - truth[i].position for i in arc]))
        assert (np.sqrt(np.mean(after**2, axis=0)) * 1e3 < 0.5 * np.array([3.0, 1.0, 0.5])).all()


def test_the_block_is_anchored_to_the_model_by_its_relief():
    sphere = _sphere(5)
    model = Mesh(sphere.vertices * 0.25, sphere.faces)
    rng = np.random.default_rng(5)
    on = model.vertices[rng.choice(len(model.vertices), 400, replace=False)]
    on = on + rng.normal(0, 1e-5, on.shape)  # 1 cm of noise
    off = np.array([1.0, -2.0, 0.5]) * 1e-3
    shift, covariance = anchor_shift(on + off, model)
    np.testing.assert_allclose(shift, -off, atol=2e-5)
    edge = 0.25 * np.pi / 2 / 32  # the sphere's edges: a quarter circle in 32
    assert np.all(np.sqrt(np.diag(covariance)) < edge) and np.all(np.sqrt(np.diag(covariance)) > 0.4 * edge)
    # a plane constrains only the shift across it: the sliding is left at zero
    corners = np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], float) * 0.1
    plane = Mesh(corners, np.array([[0, 1, 2], [0, 2, 3]]))
    flat = np.column_stack([rng.uniform(-0.05, 0.05, (100, 2)), np.zeros(100)])
    shift, covariance = anchor_shift(flat + off, plane)
    np.testing.assert_allclose(shift, [0, 0, -off[2]], atol=1e-9)
    # across it, half the model's edge (0.2 and 0.28 km here): a model places nothing more finely
    assert covariance[0, 0] > 1e3 and covariance[1, 1] > 1e3 and 0.1**2 <= covariance[2, 2] <= 0.15**2  # km^2


def test_landmarks_adjust_views_that_no_feature_joins():
    """Blank images give no feature: the maplets' landmarks (a point per maplet, where each image
    saw it once registered, pwm.pipeline.landmark_pixels) are then what the adjustment has, and
    enough to take out most of the line-of-sight error."""
    rng = np.random.default_rng(7)
    times, truth, points = _orbit_passes(rng)
    errors, drawn, kernels = _navigated(times, truth, rng)
    sphere = _sphere(5)
    model = Mesh(sphere.vertices * 0.25, sphere.faces)
    grid = np.stack(np.meshgrid(np.linspace(-0.02, 0.02, 5), np.linspace(-0.02, 0.02, 5)), axis=-1).reshape(-1, 2)
    landmarks = np.column_stack([grid, np.sqrt(0.25**2 - np.sum(grid**2, axis=1))])  # 25 maplet centres
    n = len(truth)
    observed = Tracks(point=np.tile(np.arange(len(landmarks)), n), image=np.repeat(np.arange(n), len(landmarks)),
                      xy=np.concatenate([project(landmarks, CAMERA, p) for p in truth])
                      + 0.1 * rng.standard_normal((n * len(landmarks), 2)))
    views = [View(name=f"img{i}", image=np.zeros((CAMERA.height, CAMERA.width)), camera=CAMERA, pose=p,
                  sun=np.array([0.0, 0.0, 1.0]), et=t) for i, (p, t) in enumerate(zip(kernels, times, strict=True))]
    pose_model = navigation_poses(times, kernels, errors)
    with pytest.raises(ValueError):
        adjust_poses(views, model, pose_model=pose_model)
    result = adjust_poses(views, model, pose_model=pose_model, landmarks=observed)
    assert result.stats["feature_tracks"] == 0 and result.stats["landmarks"] == len(landmarks)
    fixed = [result.corrections[v.name].apply(v.pose) for v in views]

    def los_px(poses):
        centre = np.array([0, 0, 0.25])
        d = [project(centre, CAMERA, p) - project(centre, CAMERA, t) for p, t in zip(poses, truth, strict=True)]
        return float(np.sqrt(np.mean(np.sum(np.square(d), axis=1))))

    assert los_px(kernels) > 20.0
    assert los_px(fixed) < 0.3 * los_px(kernels)



WIDE = Camera(width=1024, height=1024, fx=2000.0, fy=2000.0, cx=511.5, cy=511.5)


def _cap(n: int, rng: np.random.Generator) -> np.ndarray:
    """n points uniform on the cap of a 250 m sphere above z = 0.1 km."""
    z = rng.uniform(0.1, 0.25, n)
    phi = rng.uniform(0, 2 * np.pi, n)
    rho = np.sqrt(0.25**2 - z**2)
    return np.column_stack([rho * np.cos(phi), rho * np.sin(phi), z])


def test_ties_to_a_measured_surface_place_the_block_and_the_posterior_says_what_is_left():
    """A shift or turn of the whole block of cameras and points is, to the images, no change: the
    adjustment leaves it to the priors. Points tied to spots on the surface (pwm.spg.ties)
    cannot move with the block: the images' line of sight against the true frame and the points'
    places come out several times better, and what the ties cannot split (here the camera's
    misalignment from the arcs' smooth position errors, which move the images alike) is left
    where its posterior sigma says."""
    rng = np.random.default_rng(11)
    times, truth, _ = _orbit_passes(rng)
    errors, drawn, kernels = _navigated(times, truth, rng)
    points = _cap(400, rng)
    n = len(truth)
    cameras = [WIDE] * n
    seen = [(i, k) for i, p in enumerate(truth) for k in np.flatnonzero(
        np.einsum("ij,ij->i", p.position - points, points) > 0)]  # in front of the sphere
    image, point = (np.array(v, np.int64) for v in zip(*seen, strict=True))
    xy = np.concatenate([project(points[point[image == i]], WIDE, truth[i]) for i in range(n)])
    assert np.all(np.abs(xy - 511.5) < 512)
    tracks = Tracks(point=point, image=image, xy=xy + 0.2 * rng.standard_normal(xy.shape))
    model = navigation_poses(times, kernels, errors)
    target = np.concatenate([np.r_[-drawn.position_error_m[i] * 1e-3, drawn.pointing_error_body_rad[i]]
                             for i in range(n)])
    true_theta = np.linalg.lstsq(model.design.toarray(), target, rcond=None)[0]
    start = triangulate(tracks, cameras, kernels)[0]
    ties = surface_ties(start, MeasuredSurface(_cap(30000, rng)))
    assert len(ties) > 0.9 * len(points)
    assert ties.sigma_km.max() < 5e-5  # a 250 m sphere is within centimetres of a plane at the spots' scale

    def los_px(adjusted):
        fixed = [corrected_pose(p, adjusted.position_corrections[i], adjusted.rotation_corrections[i])
                 for i, p in enumerate(kernels)]
        d = np.concatenate([project(points, WIDE, p) - project(points, WIDE, t)
                            for p, t in zip(fixed, truth, strict=True)])
        return float(np.sqrt(np.mean(np.sum(d**2, axis=1))))

    def placed_m(adjusted):
        return float(np.sqrt(np.mean(np.sum((adjusted.points - points) ** 2, axis=1)))) * 1e3

    alone = bundle_adjust(start, tracks, cameras, kernels, model=model)
    tied = bundle_adjust(start, tracks, cameras, kernels, model=model, ties=ties)
    assert los_px(tied) < 0.2 * los_px(alone)
    assert placed_m(tied) < 0.3 * placed_m(alone)
    assert np.sqrt(np.mean(tied.tie_distances_km**2)) < 2e-5  # the points on the surface, within 2 cm
    z = (tied.parameters - true_theta) / np.sqrt(np.diag(tied.parameter_covariance(0.2)))
    assert np.sqrt(np.mean(z**2)) < 1.5 and np.abs(z).max() < 4.0  # 30 unknowns: the largest near 3
    # the posterior knows what the ties fixed: the block's place, no longer the priors'
    assert np.trace(tied.parameter_covariance(0.2)) < np.trace(alone.parameter_covariance(0.2))

    # spots placed half a metre and 2 mrad off (their instrument's own trajectory and attitude
    # errors): taken as exact, they drag the block with them and the posterior claims what is
    # false; with their frame's motion as unknowns under its prior (1 m, 4 mrad), it stays honest
    moved = Rotation.from_rotvec([0.0, 0.002, 0.0]).apply(_cap(30000, rng)) + np.array([5e-4, 0.0, 5e-4])

    def z_scores(frame_km: float, frame_rad: float) -> np.ndarray:
        adjusted = bundle_adjust(start, tracks, cameras, kernels, model=model, ties=surface_ties(
            start, MeasuredSurface(moved, frame_km=frame_km, frame_rad=frame_rad)))
        assert len(adjusted.frame) == (6 if frame_km else 0)
        return (adjusted.parameters - true_theta) / np.sqrt(np.diag(adjusted.parameter_covariance(0.2)))

    assert np.abs(z_scores(0.0, 0.0)).max() > 6.0
    z = z_scores(1e-3, 4e-3)
    assert np.sqrt(np.mean(z**2)) < 1.5 and np.abs(z).max() < 4.0

SPG_SOURCES = sorted(Path(pwm_spg.__file__).parent.glob("*.py")) + [
    Path(service_spg.__file__), Path(service_cli_spg.__file__)]


def _spg_default_values() -> set:
    """SpgConfig's defaults that no other number is likely to equal by chance: neither None, a
    bool, nor a small whole number (0 to 3)."""
    values: set = set()
    for f in dataclasses.fields(SpgConfig):
        for v in f.default if isinstance(f.default, tuple) else (f.default,):
            if v is not None and not isinstance(v, bool) and v not in {0, 1, 2, 3}:
                values.add(v)
    return values


def test_photogrammetry_defaults_are_written_once():
    """Every photogrammetry default lives in pwm.spg.config alone: no function under pwm/spg, in
    service/spg.py or service/cli/spg.py has a literal keyword default for a setting of SpgConfig
    (by its name; None, deferring to the configuration, aside) or equal to one of its defaults
    (by value), and the commands' options read
    their defaults from SPG_DEFAULTS, so that a default repeated elsewhere cannot come back."""
    names = {f.name for f in dataclasses.fields(SpgConfig)}
    values = _spg_default_values()
    assert {8192, 6, 1e-4, 1e-3, 25.0} <= values
    found = []
    for path in SPG_SOURCES:
        if path.name == "config.py":
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
                args = node.args.posonlyargs + node.args.args
                pairs = list(zip(args[len(args) - len(node.args.defaults):], node.args.defaults, strict=True))
                pairs += [(a, d) for a, d in zip(node.args.kwonlyargs, node.args.kw_defaults, strict=True)
                          if d is not None]
                for arg, default in pairs:
                    try:
                        value = ast.literal_eval(default)
                    except ValueError:
                        continue  # an expression: SPG_DEFAULTS, a typer option, another module's constant
                    flat = value if isinstance(value, tuple) else (value,)
                    if (arg.arg in names and value is not None) or any(v in values for v in flat
                                                                       if not isinstance(v, bool | str)):
                        found.append(f"{path.name}:{node.lineno} {node.name}({arg.arg}={value!r})")
            elif (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and node.func.attr == "Option"
                  and node.args and isinstance(node.args[0], ast.Constant)):
                value = node.args[0].value
                if isinstance(value, int | float) and not isinstance(value, bool):
                    found.append(f"{path.name}:{node.lineno} typer.Option({value!r})")
    assert not found, "photogrammetry defaults outside pwm.spg.config: " + ", ".join(found)


def test_spg_commands_default_to_spg_config():
    """`pwm spg` and `pwm spg-catalog` with no options run with SPG_DEFAULTS."""
    commands = typer.main.get_command(app).commands
    for name in ("spg", "spg-catalog"):
        given = {p.name: p.default for p in commands[name].params}
        config = spg_config(sigma_position_m=given["sigma_position"], sigma_pointing_rad=given["sigma_pointing"],
                            max_features=given["max_features"], first_octave=given["first_octave"],
                            per_image=given["per_image"], threads=given["threads"],
                            max_sun_deg=given["max_sun_deg"])
        assert config == SPG_DEFAULTS, name
