"""Photoclinometric refinement and alignment of one maplet on scenes rendered with pwm.render.

The scene: a 60 x 60-node maplet at 5 cm on Bennu's surface with a Gaussian bump (30 cm high,
sigma 25 cm, about 1 m across) and an albedo pattern, drawn on a grid mesh twice as fine as the maplet, seen by a
MapCam-like camera (14729 px focal length, ~5 cm pixels) from nadir and four azimuths at 30 deg
emission (one image frame mirrored), under a Sun 30-60 deg from the zenith at varying azimuths;
per-image brightness scales and 1 % noise. Refinement starts from the flat, bump-free heights.
"""

from __future__ import annotations

import dataclasses
import functools
from dataclasses import dataclass

import numpy as np
import pytest
from scipy.ndimage import gaussian_filter
from scipy.spatial.transform import Rotation

from pwm.alignment import _align_at, _every, align, parallax_height, register, sweep_height, window_rises
from pwm.camera import Camera, Pose, look_at, project
from pwm.config import DEFAULTS, PLACEMENT, RefinementConfig
from pwm.frames import latlon_to_unit, local_frame
from pwm.maplets import NO_SPOTS, MapletGrid, MapletSpots, Spots, grid_heights, spots_over
from pwm.mesh import Mesh, grid_faces
from pwm.photoclinometry import (
    MapletImages,
    Refinement,
    Solver,
    _Geometry,
    _Problem,
    _shading,
    bilinear,
    cubic_gradient,
    extract,
    horizons,
    node_pixels,
    predict,
    refine,
    slopes,
)
from pwm.pipeline import _coarse_first, _reshaped, _settled_on_spots, _swept_again, placed_on_spots
from pwm.raytrace import RayTracer
from pwm.render import render
from pwm.weights import shade

FOCAL_PX = 14729.0
N_NODES = 60
SPACING_KM = 5e-5
BUMP_KM = 3e-4
SIGMA_KM = 2.5e-4
VIEWS = ((0.0, 0.0), (30.0, 0.0), (30.0, 90.0), (30.0, 180.0), (30.0, 270.0))   # emission, azimuth (deg)
HIGH_SUN = ((45.0, 120.0), (30.0, 200.0), (60.0, 300.0), (40.0, 30.0), (50.0, 240.0))  # incidence, azimuth
LOW_SUN = ((65.0, 120.0), (60.0, 200.0), (70.0, 300.0), (60.0, 30.0), (65.0, 240.0))
NOISE = 0.01


@dataclass
class Scene:
    start: MapletGrid          # flat heights, no albedo
    truth: MapletGrid          # the true heights and albedo on the maplet's nodes
    data: MapletImages
    scales: np.ndarray     # true brightness scales, geometric mean 1


def _direction(angle_deg: float, azimuth_deg: float) -> np.ndarray:
    """Local unit vector at `angle_deg` from the zenith, azimuth from north (+y) towards east (+x)."""
    e, a = np.radians(angle_deg), np.radians(azimuth_deg)
    return np.array([np.sin(e) * np.sin(a), np.sin(e) * np.cos(a), np.cos(e)])


def _heights(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    return BUMP_KM * np.exp(-(x**2 + y**2) / (2 * SIGMA_KM**2))


def _albedo(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    return 0.045 * (1 + 0.15 * np.sin(2 * np.pi * x / 8e-4) * np.cos(2 * np.pi * y / 1.1e-3 + 0.3))


def _grid_mesh(maplet: MapletGrid, axis: np.ndarray) -> Mesh:
    """The true surface as a grid mesh on `axis` (km) in the maplet's frame, two faces a cell."""
    x, y = np.meshgrid(axis, axis)
    vertices = maplet.frame.to_body(np.stack([x, y, _heights(x, y)], axis=-1).reshape(-1, 3))
    return Mesh(vertices, grid_faces(len(axis), len(axis)), albedo=_albedo(x, y).ravel())


def _scene(suns: tuple[tuple[float, float], ...], seed: int = 0) -> Scene:
    rng = np.random.default_rng(seed)
    centre = 0.25 * latlon_to_unit(10.0, 30.0)
    frame = local_frame(centre, centre)
    start = MapletGrid(name="bump", frame=frame, spacing_km=SPACING_KM, heights=np.zeros((N_NODES, N_NODES)))
    x, y = np.meshgrid(start.axis_km, start.axis_km)
    truth = dataclasses.replace(start, heights=_heights(x, y), albedo=_albedo(x, y))
    half = start.axis_km[-1] + 1e-3
    tracer = RayTracer(_grid_mesh(start, np.linspace(-half, half, int(round(2 * half / (SPACING_KM / 2))) + 1)))

    size = 96
    camera = Camera(width=size, height=size, fx=FOCAL_PX, fy=FOCAL_PX, cx=(size - 1) / 2, cy=(size - 1) / 2)
    distance = SPACING_KM * FOCAL_PX
    scales = np.exp(rng.normal(0.0, 0.05, len(VIEWS)))
    scales /= np.exp(np.log(scales).mean())
    nodes = truth.nodes_body().reshape(-1, 3)
    lift = 3 * tracer.offset * frame.normal
    images, poses, sun_dirs, visible, lit = [], [], [], [], []
    for k, ((emission, azimuth), (incidence, sun_azimuth)) in enumerate(zip(VIEWS, suns, strict=True)):
        pose = look_at(frame.to_body(distance * _direction(emission, azimuth)[None])[0], centre, frame.rotation[1])
        if k == 1:
            pose = Pose(pose.position, np.diag([-1.0, 1.0, 1.0]) @ pose.rotation)   # a mirrored image frame
        sun = frame.rotation.T @ _direction(incidence, sun_azimuth)
        view = render(tracer, camera=camera, pose=pose, sun_direction=sun)
        image = scales[k] * view.reflectance + NOISE * 0.03 * rng.normal(size=view.reflectance.shape)
        images.append(np.where(view.hit, image, np.nan))
        poses.append(pose)
        sun_dirs.append(sun)
        # Node masks as visibility would draw them on the true surface.
        to_cam = pose.position - nodes
        dist = np.linalg.norm(to_cam, axis=1)
        visible.append(~tracer.occluded(nodes + lift, to_cam / dist[:, None], dist))
        lit.append(~tracer.occluded(nodes + lift, np.broadcast_to(sun, nodes.shape)))
    shape = (len(VIEWS), N_NODES, N_NODES)
    visible = np.reshape(visible, shape)
    lit = np.reshape(lit, shape)
    data = MapletImages(images=images, cameras=[camera] * len(VIEWS), poses=poses, sun_directions=np.array(sun_dirs),
                        visible=visible, lit=lit, weights=(visible & lit).astype(float))
    return Scene(start=start, truth=truth, data=data, scales=scales)


@pytest.fixture(scope="module")
def scene() -> Scene:
    return _scene(HIGH_SUN)


@pytest.fixture(scope="module")
def refined(scene: Scene) -> Refinement:
    return refine(scene.start, scene.data)


def _bump_height(heights: np.ndarray) -> float:
    """Peak height above the median of the maplet's rim (km)."""
    rim = np.concatenate([heights[0], heights[-1], heights[:, 0], heights[:, -1]])
    return float(heights.max() - np.median(rim))


def _shape_error(heights: np.ndarray, truth: np.ndarray) -> float:
    """RMS height error (km) about its mean: the mean height is the starting shape's to keep."""
    return float(np.std(heights - truth))


def test_shading_derivatives_match_finite_differences() -> None:
    rng = np.random.default_rng(4)
    k, n = 3, 50
    sun = np.array([_direction(a, b) for a, b in ((30, 20), (55, 200), (45, 290))])
    view = np.stack([np.broadcast_to(_direction(a, b), (n, 3)) for a, b in ((0, 0), (30, 90), (25, 180))])
    phase = np.arccos(np.einsum("kni,ki->kn", view, sun))
    geo = _Geometry(sun=sun, view=view, phase=phase)
    p, q = rng.uniform(-0.5, 0.5, n), rng.uniform(-0.5, 0.5, n)
    G, gp, gq = _shading(p, q, geo)
    h = 1e-6
    assert G.shape == (k, n) and np.all(G > 0)
    np.testing.assert_allclose(gp, (_shading(p + h, q, geo)[0] - _shading(p - h, q, geo)[0]) / (2 * h), atol=1e-7)
    np.testing.assert_allclose(gq, (_shading(p, q + h, geo)[0] - _shading(p, q - h, geo)[0]) / (2 * h), atol=1e-7)


def test_slopes_follow_numpy_gradient() -> None:
    rng = np.random.default_rng(2)
    h = rng.normal(size=(7, 7)) * 1e-4
    p, q = slopes(h, 5e-5)
    dz_dy, dz_dx = np.gradient(h, 5e-5)
    np.testing.assert_allclose(p, -dz_dx)
    np.testing.assert_allclose(q, -dz_dy)


def test_extract_samples_bilinearly_and_marks_outside(scene: Scene) -> None:
    # On a linear image bilinear sampling is exact; a detector window cuts off part of the maplet.
    camera = scene.data.cameras[0]
    window = camera.subframe(first_sample=30, first_line=10, samples=60, lines=80)
    lines, samples = np.mgrid[0:80, 0:60].astype(float)
    image = 0.02 + 1e-4 * samples + 3e-4 * lines
    data = dataclasses.replace(scene.data, images=[image], cameras=[window], poses=scene.data.poses[:1],
                               sun_directions=scene.data.sun_directions[:1], visible=scene.data.visible[:1],
                               lit=scene.data.lit[:1], weights=scene.data.weights[:1])
    values = extract(scene.truth, data)[0]
    pix = project(scene.truth.nodes_body(), window, data.poses[0])
    inside = (pix[..., 0] >= 0) & (pix[..., 0] <= 59) & (pix[..., 1] >= 0) & (pix[..., 1] <= 79)
    assert 0.2 < inside.mean() < 0.9
    np.testing.assert_allclose(values[inside], 0.02 + 1e-4 * pix[inside][:, 0] + 3e-4 * pix[inside][:, 1], rtol=1e-12)
    assert np.isnan(values[~inside]).all()
    assert np.isnan(bilinear(image, np.array([[-0.01, 5.0], [5.0, 79.01]]))).all()


def test_parts_registered_at_once_are_each_registered_on_its_own(scene: Scene) -> None:
    # window_rises registers a maplet's parts together: each as `align` on its nodes alone
    bad = _mispointed(scene.data, seed=7, angle_rad=3e-5)
    n = scene.truth.n
    band = np.minimum(np.arange(n) * 3 // n, 2)
    parts = band[:, None] * 3 + band[None, :]
    parts[:5, :5] = -1  # nodes in no part
    start = np.zeros((bad.count, 2))
    pixels = node_pixels(scene.truth, bad, offsets=start)
    model = predict(scene.truth, bad, albedo=scene.truth.albedo)
    together = _align_at(bad, pixels, model, start, search_px=3, min_nodes=50, max_iterations=20, parts=parts)
    assert len(together) == 9
    for label, found in enumerate(together):
        alone = align(scene.truth, dataclasses.replace(bad, weights=np.where(parts == label, bad.weights, 0.0)),
                      albedo=scene.truth.albedo, search_px=3)
        np.testing.assert_allclose(found.offsets, alone.offsets, rtol=0, atol=1e-9)
        np.testing.assert_allclose(found.correlation, alone.correlation, rtol=0, atol=1e-9)
        assert np.isfinite(found.correlation).all() and (found.correlation > 0.9).all()


def test_cubic_sampling_is_exact_on_quadratics_and_sharper_than_bilinear() -> None:
    lines, samples = np.mgrid[0:40, 0:50].astype(float)
    image = 0.3 + 0.02 * samples - 0.01 * lines + 1e-3 * samples * lines - 2e-4 * samples**2 + 3e-4 * lines**2
    at = np.random.default_rng(3).uniform(0.0, [49.0, 39.0], (500, 2))
    s, ln = at[:, 0], at[:, 1]
    values, gradient = cubic_gradient(image, at)
    inner = (s >= 1) & (s <= 48) & (ln >= 1) & (ln <= 38)  # the clamped border is not exact
    np.testing.assert_allclose(values[inner],
                               (0.3 + 0.02 * s - 0.01 * ln + 1e-3 * s * ln - 2e-4 * s**2 + 3e-4 * ln**2)[inner],
                               atol=1e-12)
    np.testing.assert_allclose(gradient[inner, 0], (0.02 + 1e-3 * ln - 4e-4 * s)[inner], atol=1e-12)
    np.testing.assert_allclose(gradient[inner, 1], (-0.01 + 1e-3 * s + 6e-4 * ln)[inner], atol=1e-12)
    assert np.isnan(cubic_gradient(image, np.array([[-0.01, 5.0], [5.0, 39.01]]))[0]).all()
    # detail at six pixels a period, between the pixel centres
    wave = np.sin(2 * np.pi * samples / 6.0)
    truth = np.sin(2 * np.pi * s[inner] / 6.0)
    cubic_error = np.sqrt(np.mean((cubic_gradient(wave, at[inner])[0] - truth) ** 2))
    bilinear_error = np.sqrt(np.mean((bilinear(wave, at[inner]) - truth) ** 2))
    assert cubic_error < 0.5 * bilinear_error


def test_refine_recovers_bump_and_scales(scene: Scene, refined: Refinement) -> None:
    result = refined
    truth = scene.truth.heights
    assert result.converged
    assert _bump_height(result.heights) == pytest.approx(BUMP_KM, rel=0.10)
    start_error = _shape_error(scene.start.heights, truth)
    assert _shape_error(result.heights, truth) < 0.15 * start_error
    np.testing.assert_allclose(result.scales, scene.scales, rtol=0.02)
    albedo_error = np.sqrt(np.mean((result.albedo / scene.truth.albedo - 1) ** 2))
    assert albedo_error < 0.03
    # The residuals come down to the noise (interpolating between pixels averages some of it away).
    assert np.all(result.rms < 1.5 * NOISE * 0.03)


def test_nodes_without_data_keep_the_starting_shape(scene: Scene) -> None:
    # The start has a dent (10 cm deep) in the south-west corner that the true surface lacks.
    x, y = np.meshgrid(scene.start.axis_km, scene.start.axis_km)
    dent = -1e-4 * np.exp(-((x + 1e-3) ** 2 + (y + 1e-3) ** 2) / (2 * 1.2e-4**2))
    start = dataclasses.replace(scene.start, heights=scene.start.heights + dent)
    corner = (x < -6e-4) & (y < -6e-4)
    deep = (x < -7.5e-4) & (y < -7.5e-4)   # three nodes or more away from any data
    # With data, the refinement removes the dent; with none there, it keeps it.
    seen = refine(start, scene.data)
    assert np.abs(seen.heights - scene.truth.heights)[deep].max() < 0.2 * np.abs(dent[deep]).max()
    weights = np.where(corner, 0.0, scene.data.weights)
    blind = refine(start, dataclasses.replace(scene.data, weights=weights))
    # (what moves there is the smooth tail of the data region's datum shift, ~1 cm)
    assert np.abs(blind.heights - start.heights)[deep].max() < 0.15 * np.abs(dent[deep]).max()


def test_stopping_on_a_small_decrease_of_the_objective_costs_no_accuracy(scene: Scene, refined: Refinement) -> None:
    # Iterating until the steps themselves vanish (no objective stop, a tolerance of 1e-4
    # spacings) takes more iterations and ends within a fiftieth of a spacing of the default.
    longer = refine(scene.start, scene.data, solver=Solver(cost_tolerance=0.0, tolerance=1e-4))
    assert refined.iterations < longer.iterations
    assert np.sqrt(np.mean((refined.heights - longer.heights) ** 2)) < 0.02 * SPACING_KM


def test_parallax_is_the_change_of_the_samples_as_the_nodes_rise(scene: Scene) -> None:
    problem = _Problem(scene.start, scene.data, weights=scene.data.weights, region=1.0,
                       offsets=np.zeros((scene.data.count, 2)),
                       solve_offsets=True, slope_weight=0.02, slope_scale=0.17, height_weight=1e-3, albedo_weight=1e-3,
                       offset_weight=1e-3, shadow_weight=0.0, spots=NO_SPOTS, lidar_weight=0.0)
    state, ev = problem.start()
    h = 1e-3  # spacings: a uniform rise leaves the slopes, so only the samples change
    risen, values = problem._evaluate(dataclasses.replace(state, u=state.u + h))
    _, before = problem._evaluate(state)
    both = (ev.rows > 0) & (risen.rows > 0)
    assert both.mean() > 0.9 and np.abs(ev.parallax[both]).max() > 1e-3
    np.testing.assert_allclose((values - before)[both] / h, ev.parallax[both], rtol=0.02, atol=1e-4)


def test_a_maplet_too_high_keeps_its_mean_height_and_the_offsets_take_the_parallax(scene: Scene) -> None:
    # The start sits 2 spacings (10 cm) too high: the oblique images see its nodes ~1 px off.
    # Brightness cannot tell, and the data see a common rise only by perspective, apart from
    # offsets: the mean height stays the start's, and the offsets absorb the parallax of what
    # separates it from the true mean (the lift less the bump's mean, which the flat start lacks),
    # up to the maplet's sideways datum, which they keep.
    lift = 2 * SPACING_KM
    start = dataclasses.replace(scene.start, heights=scene.start.heights + lift)
    result = refine(start, scene.data)
    assert float(np.mean(result.heights - start.heights)) == pytest.approx(0.0, abs=1e-6 * SPACING_KM)
    rise = start.frame.rotation[2] * (lift - float(np.mean(scene.truth.heights)))
    centre = scene.truth.nodes_body()[N_NODES // 2, N_NODES // 2]
    parallax = np.array([project(centre, c, p) - project(centre + rise, c, p)
                         for c, p in zip(scene.data.cameras, scene.data.poses, strict=True)])
    assert np.abs(parallax).max() > 0.5
    np.testing.assert_allclose(_datum_free(result.offsets, start, scene.data), _datum_free(parallax, start, scene.data),
                               atol=0.05)
    assert _bump_height(result.heights) == pytest.approx(BUMP_KM, rel=0.10)


def test_the_offsets_parallax_tells_how_far_the_maplet_is_too_high(scene: Scene) -> None:
    # where the poses are known (the images' offsets good to 0.1 px), what the offsets took up
    # of a start 2 spacings too high is a rise of the maplet, as stereo measures it
    lift = 2 * SPACING_KM
    start = dataclasses.replace(scene.start, heights=scene.start.heights + lift)
    result = refine(start, scene.data)
    made = dataclasses.replace(start, heights=result.heights)
    rise, sigma = parallax_height(made, scene.data, result.offsets, sigma_px=np.full(scene.data.count, 0.1))
    truth = float(np.mean(scene.truth.heights)) - lift
    assert 0 < sigma < 0.1 * SPACING_KM and rise == pytest.approx(truth, abs=0.15 * SPACING_KM)
    # an image that says nothing (infinite sigma) changes nothing but the sigma
    loose = np.full(scene.data.count, 0.1)
    loose[0] = np.inf
    rise_without, sigma_without = parallax_height(made, scene.data, result.offsets, sigma_px=loose)
    assert sigma_without >= sigma and rise_without == pytest.approx(truth, abs=0.15 * SPACING_KM)


def test_a_sweep_of_rises_finds_a_start_many_pixels_of_parallax_off(scene: Scene) -> None:
    sweep = functools.partial(sweep_height, reach_px=16.0)
    far = 16 * SPACING_KM
    # 8 spacings too high: the oblique images see the nodes several pixels apart, beyond the
    # joint solution's reach; the images agree again where the maplet is lowered by about that
    lift = 8 * SPACING_KM
    start = dataclasses.replace(scene.start, heights=scene.start.heights + lift)
    zero = np.zeros((scene.data.count, 2))
    rise = sweep(start, scene.data, zero, max_rise_km=far)
    assert rise == pytest.approx(float(np.mean(scene.truth.heights)) - lift, abs=SPACING_KM)
    # a sweep too short to reach it follows the images' agreement on past its end to the same place
    short = functools.partial(sweep_height, start, scene.data, zero, reach_px=2.0, max_rise_km=far)
    assert short(follow=True) == pytest.approx(rise, abs=0.2 * SPACING_KM) and short() == 0.0
    # never further than it is allowed to go: a start 8 spacings off is no find within 4
    assert abs(sweep(start, scene.data, zero, max_rise_km=4 * SPACING_KM)) <= 4 * SPACING_KM
    # at the true height, the images agree best where the maplet is
    assert sweep(scene.truth, scene.data, zero, max_rise_km=far) == pytest.approx(0.0, abs=0.1 * SPACING_KM)
    # nor with a single image
    assert sweep(start, dataclasses.replace(scene.data, images=scene.data.images[:1],
                                    cameras=scene.data.cameras[:1], poses=scene.data.poses[:1],
                                    sun_directions=scene.data.sun_directions[:1],
                                    visible=scene.data.visible[:1], lit=scene.data.lit[:1],
                                    weights=scene.data.weights[:1]), zero[:1], max_rise_km=far) == 0.0


def _tilted(scene: Scene, span: float) -> MapletGrid:
    """The flat start tilted along x by +-span spacings at its edges."""
    x = np.broadcast_to(scene.start.axis_km, scene.start.heights.shape)
    return dataclasses.replace(scene.start, heights=scene.start.heights + span * SPACING_KM * x / x.max())


def _part_means(heights: np.ndarray, windows: int) -> np.ndarray:
    edges = np.linspace(0, heights.shape[0], windows + 1).round().astype(int)
    return np.array([[heights[edges[i]:edges[i + 1], edges[j]:edges[j + 1]].mean() for j in range(windows)]
                     for i in range(windows)])


def test_the_parallax_of_a_maplets_parts_shows_the_tilt_its_start_kept(scene: Scene) -> None:
    # a start tilted by +-8 spacings: photoclinometry leaves about half of the tilt (the
    # brightness scales take up a uniform slope), and the oblique images see its parts pixels
    # apart; each part's own offsets measure most of what it is off
    start = _tilted(scene, 8.0)
    result = refine(start, scene.data)
    needed = _part_means(scene.truth.heights - result.heights, 3) / SPACING_KM
    centres, rises, sigmas = window_rises(dataclasses.replace(start, heights=result.heights), scene.data,
                                          result.offsets, albedo=result.albedo, sigma_px=np.full(scene.data.count, 0.3),
                                          windows=3, search_px=4)
    rises = rises / SPACING_KM
    np.testing.assert_allclose(centres, [9.5, 29.5, 49.5])
    assert np.all(sigmas < 0.5 * SPACING_KM)
    assert np.all(needed[:, 0] > 3) and np.all(needed[:, 2] < -3)  # the tilt is still there
    tilt, measured = needed[:, 0] - needed[:, 2], rises[:, 0] - rises[:, 2]
    assert np.all((measured > 0.5 * tilt) & (measured < 1.1 * tilt))
    np.testing.assert_allclose(rises[:, 1], needed[:, 1], atol=0.3)


def test_a_maplet_bent_by_its_parts_parallax_loses_the_tilt(scene: Scene, refined: Refinement) -> None:
    bend = functools.partial(_reshaped, data=scene.data, sigma_px=np.full(scene.data.count, 0.1),
                             config=RefinementConfig(shape_window_nodes=20), max_rise_km=20 * SPACING_KM)
    start = _tilted(scene, 8.0)
    result = refine(start, scene.data)
    before = np.std(result.heights - scene.truth.heights)
    after = np.std(bend(start, result=result).heights - scene.truth.heights)
    assert before > 2.5 * SPACING_KM and after < 0.35 * before
    # where the parts agree with the whole, nothing moves; nor where the parts are too small
    assert bend(scene.start, result=refined) is refined
    assert bend(start, result=result, config=RefinementConfig(shape_window_nodes=40)) is result
    # nor beyond what the start may be off
    assert bend(start, result=result, max_rise_km=SPACING_KM) is result


def test_region_weight_tightens_to_the_start(scene: Scene, refined: Refinement) -> None:
    tight = refine(scene.start, dataclasses.replace(scene.data, region_weight=0.02))
    assert _bump_height(tight.heights) < 0.7 * _bump_height(refined.heights)


def test_the_slope_tie_holds_relief_the_start_lacks_less_than_noise(scene: Scene) -> None:
    # Held tight to the flat start, a quadratic tie (slope_scale far above any slope) flattens
    # the bump more than the pseudo-Huber tie, which grows only linearly beyond slope_scale.
    tight = dataclasses.replace(scene.data, region_weight=0.02)
    quadratic = refine(scene.start, tight, solver=Solver(slope_scale=1e3))
    robust = refine(scene.start, tight, solver=Solver(slope_scale=0.1))
    assert _bump_height(robust.heights) > 1.15 * _bump_height(quadratic.heights)
    # and the tie's Gauss-Newton matrix is its gradient: finite differences of its cost
    problem = _Problem(scene.start, scene.data, weights=scene.data.weights, region=1.0,
                       offsets=np.zeros((scene.data.count, 2)),
                       solve_offsets=False, slope_weight=0.02, slope_scale=0.1, height_weight=1e-3, albedo_weight=1e-3,
                       offset_weight=1e-3, shadow_weight=0.0, spots=NO_SPOTS, lidar_weight=0.0)
    du = (robust.heights - scene.start.heights).ravel() / SPACING_KM
    step = np.random.default_rng(5).normal(size=du.size)
    h = 1e-6
    numeric = (problem._tie_cost(du + h * step) - problem._tie_cost(du - h * step)) / (2 * h)
    assert numeric == pytest.approx(2 * step @ (problem._tie_matrix(du) @ du), rel=1e-6)


def test_pwm_weights_beat_standard_photoclinometry_in_shadow() -> None:
    low = _scene(LOW_SUN, seed=1)
    assert (~low.data.lit).mean() > 0.01
    errors = {mode: _shape_error(refine(low.start, low.data, mode=mode).heights, low.truth.heights)
              for mode in ("pwm", "standard")}
    assert errors["pwm"] < 0.5 * errors["standard"]
    assert _shape_error(low.start.heights, low.truth.heights) > 5 * errors["pwm"]


def test_a_horizon_is_the_shadow_line_of_the_highest_node_towards_the_sun() -> None:
    n = 21
    u = np.zeros((n, n))
    u[10, 10] = 5.0                     # a pillar 5 spacings high
    elevation = np.radians(30.0)
    east = np.array([[np.cos(elevation), 0.0, np.sin(elevation)], [0.0, 0.0, 1.0]])   # and one overhead
    top, caster = horizons(u, east)
    row = top[0].reshape(n, n)[10]
    # west of the pillar the horizon falls by tan(30 deg) a spacing; the pillar casts it
    assert np.allclose(row[1:10], 5.0 - np.tan(elevation) * np.arange(9, 0, -1))
    assert (caster[0].reshape(n, n)[10, 1:10] == 10 * n + 10).all()
    shaded = u.ravel() < top[0]
    assert shaded.reshape(n, n)[10, 2:10].all() and not shaded.reshape(n, n)[10, 11:].any()
    assert not shaded.reshape(n, n)[9, :].any()    # the next row: no pillar to its east
    assert np.isneginf(top[1]).all() and (caster[1] == -1).all()


def _horizons_node_by_node(u: np.ndarray, sun_local: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """`horizons` as its docstring says, each step's node found for every node on its own."""
    n = u.shape[0]
    i, j = np.divmod(np.arange(n * n), n)
    flat = u.ravel()
    top = np.full((len(sun_local), n * n), -np.inf)
    caster = np.full((len(sun_local), n * n), -1)
    horizontal = np.hypot(sun_local[:, 0], sun_local[:, 1])
    for k, sun in enumerate(sun_local):
        dx, dy, rise = sun[0] / horizontal[k], sun[1] / horizontal[k], sun[2] / horizontal[k]
        for step in range(1, 2 * n + 1):
            ci, cj = np.rint(i + step * dy).astype(int), np.rint(j + step * dx).astype(int)
            inside = (ci >= 0) & (ci < n) & (cj >= 0) & (cj < n)
            h = np.full(n * n, -np.inf)
            h[inside] = flat[ci[inside] * n + cj[inside]] - rise * ((cj - j) * dx + (ci - i) * dy)[inside]
            higher = h > top[k]
            top[k, higher], caster[k, higher] = h[higher], (ci * n + cj)[higher]
    return top, caster


def test_horizons_are_each_nodes_own_along_any_sun() -> None:
    rng = np.random.default_rng(3)
    n = 40
    u = gaussian_filter(rng.normal(size=(n, n)), 2) * 15 + rng.normal(size=(n, n))
    azimuth, elevation = rng.uniform(0, 2 * np.pi, 24), np.radians(rng.uniform(3, 70, 24))
    suns = np.column_stack([np.cos(azimuth) * np.cos(elevation), np.sin(azimuth) * np.cos(elevation),
                            np.sin(elevation)])
    suns = np.vstack([suns, [[1.0, 0.0, 0.1], [0.0, -1.0, 0.2], [0.6, 0.8, 0.05]]])  # along the grid, and 3-4-5
    top, caster = horizons(u, suns)
    expected_top, expected_caster = _horizons_node_by_node(u, suns)
    np.testing.assert_array_equal(top, expected_top)
    np.testing.assert_array_equal(caster, expected_caster)


def test_the_shadows_the_images_show_hold_the_slope_no_image_lights() -> None:
    # The Sun always low in the south: the bump's northern flank is dark in every image, and only
    # the ties to the flat start would shape it without the shadow term.
    south = _scene(((70.0, 160.0), (65.0, 180.0), (75.0, 200.0), (70.0, 170.0), (65.0, 190.0)), seed=1)
    marked = dataclasses.replace(south.data, shade=shade(extract(south.start, south.data), south.data.weights,
                                                         south.data.visible))
    dark = (~south.data.lit & south.data.visible).any(axis=0)
    assert dark.sum() > 50

    def error(weight: float) -> float:
        heights = refine(south.start, marked, solver=Solver(shadow_weight=weight)).heights
        return float(np.sqrt(np.mean((heights - south.truth.heights)[dark] ** 2)))

    assert error(0.05) < 0.9 * error(0.0)


def _mispointed(data: MapletImages, seed: int, angle_rad: float = 1e-4) -> MapletImages:
    """The same images with each pose turned by angle_rad about an axis across the boresight."""
    rng = np.random.default_rng(seed)
    poses = []
    for pose in data.poses:
        turn = rng.uniform(0.0, 2 * np.pi)
        rotation = Rotation.from_rotvec(angle_rad * np.array([np.cos(turn), np.sin(turn), 0.0])).as_matrix()
        poses.append(Pose(pose.position, rotation @ pose.rotation))
    return dataclasses.replace(data, poses=poses)


def _true_offsets(truth: MapletGrid, good: MapletImages, bad: MapletImages) -> np.ndarray:
    """Where the maplet centre really is minus where the mispointed poses put it (px)."""
    centre = truth.nodes_body()[N_NODES // 2, N_NODES // 2]
    return np.array([project(centre, camera, right) - project(centre, camera, wrong)
                     for camera, right, wrong in zip(good.cameras, good.poses, bad.poses, strict=True)])


def test_align_recovers_pointing_errors(scene: Scene) -> None:
    bad = _mispointed(scene.data, seed=5)
    expected = _true_offsets(scene.truth, scene.data, bad)
    assert np.all(np.hypot(*expected.T) > 1.0)   # 1e-4 rad is ~1.5 px at 14729 px
    found = align(scene.truth, bad)
    np.testing.assert_allclose(found.offsets, expected, atol=0.1)
    assert np.all(found.correlation > 0.95)


def test_refine_solves_pointing_up_to_the_maplet_datum(scene: Scene) -> None:
    # From the flat start the pointing errors are solved jointly. A common shift of the maplet is
    # invisible to photometry, so compare the offsets after removing the best-fitting one.
    bad = _mispointed(scene.data, seed=6)
    expected = _true_offsets(scene.truth, scene.data, bad)
    result = refine(scene.start, bad)
    centre = scene.truth.nodes_body()[N_NODES // 2, N_NODES // 2]
    step = SPACING_KM
    shift = np.column_stack([
        np.concatenate([(project(centre + step * axis, c, p) - project(centre - step * axis, c, p)) / (2 * step)
                        for c, p in zip(bad.cameras, bad.poses, strict=True)])
        for axis in scene.start.frame.rotation
    ])
    miss = (result.offsets - expected).ravel()
    common = shift @ np.linalg.lstsq(shift, miss, rcond=None)[0]
    assert np.abs(miss).max() > 0.1   # the datum part is really there
    assert np.abs(miss - common).max() < 0.05
    assert _bump_height(result.heights) == pytest.approx(BUMP_KM, rel=0.10)
    assert np.all(refine(scene.start, bad, solver=Solver(solve_offsets=False)).rms > 2 * result.rms)


def _datum_free(offsets: np.ndarray, maplet: MapletGrid, data: MapletImages) -> np.ndarray:
    """Offsets (K, 2) less the best-fitting common shift of the maplet along its x and y."""
    centre = maplet.nodes_body()[N_NODES // 2, N_NODES // 2]
    shift = np.column_stack([
        np.concatenate([(project(centre + SPACING_KM * axis, c, p) - project(centre - SPACING_KM * axis, c,
                                                                             p)) / (2 * SPACING_KM)
                        for c, p in zip(data.cameras, data.poses, strict=True)])
        for axis in maplet.frame.rotation[:2]
    ])
    flat = offsets.ravel()
    return (flat - shift @ np.linalg.lstsq(shift, flat, rcond=None)[0]).reshape(-1, 2)


def test_register_recovers_offsets_of_many_pixels_without_albedo(scene: Scene) -> None:
    # Knowledge errors of metres put images ~10 px off: beyond the joint solution's reach, and
    # beyond align's, which needs the albedo. register finds them from a low-passed start (the
    # simulator's start models are the truth low-passed), up to the maplet's datum, and the
    # refinement then recovers the bump.
    start = dataclasses.replace(scene.start, heights=gaussian_filter(scene.truth.heights, 4.0))
    bad = _mispointed(scene.data, seed=7, angle_rad=6e-4)
    expected = _true_offsets(scene.truth, scene.data, bad)
    assert np.all(np.hypot(*expected.T) > 8.0)
    found = register(start, bad, levels=((4, 12.0), (4, 12.0), (1, 1.0)))
    assert np.abs(_datum_free(found.offsets - expected, start, bad)).max() < 0.7
    refined = refine(start, bad, offsets=found.offsets)
    assert _bump_height(refined.heights) == pytest.approx(BUMP_KM, rel=0.10)
    unregistered = refine(start, bad)
    assert np.abs(_datum_free(unregistered.offsets - expected, start, bad)).max() > 2.0
    assert (_shape_error(refined.heights, scene.truth.heights)
            < 0.5 * _shape_error(unregistered.heights, scene.truth.heights))


def test_a_swept_maplet_is_swept_again_from_its_refined_relief(scene: Scene) -> None:
    # a maplet refined 5 spacings too high (its first sweep's peak was flat on a coarser
    # start's relief) keeps that height through the joint solution; swept again from the relief
    # it has now, and solved again, it comes down
    lift = 5 * SPACING_KM
    zero = np.zeros((scene.data.count, 2))
    truth = float(np.mean(scene.truth.heights))
    high = refine(dataclasses.replace(scene.truth, heights=scene.truth.heights + lift, albedo=None), scene.data,
                  offsets=zero)
    assert float(np.mean(high.heights)) - truth > 3 * SPACING_KM
    again = functools.partial(_swept_again, scene.start, scene.data, high, offsets=zero, config=RefinementConfig(),
                              follow=False)
    placed, raised = again(raised_km=0.0, max_rise_km=16 * SPACING_KM)
    assert float(np.mean(placed.heights)) == pytest.approx(truth, abs=0.5 * SPACING_KM)
    assert raised == pytest.approx(-lift, abs=0.5 * SPACING_KM)
    # within what is left of the start's face size: a maplet already raised that far stays
    kept, raised = again(raised_km=16 * SPACING_KM, max_rise_km=16 * SPACING_KM)
    assert kept is high and raised == 16 * SPACING_KM


def test_the_sweeps_sparser_grid_keeps_the_shadows_the_images_show(scene: Scene) -> None:
    # refine_maplet marks the shadows before a swept maplet is swept again: every node mask of
    # the sparser grid the sweep scores on must be taken alike
    n = 58    # (n - 1) a multiple of 3: every third node spans the same square
    data = dataclasses.replace(scene.data, visible=scene.data.visible[:, :n, :n], lit=scene.data.lit[:, :n, :n],
                               weights=scene.data.weights[:, :n, :n])
    data.shade = shade(extract(dataclasses.replace(scene.start, heights=scene.start.heights[:n, :n]), data),
                       data.weights, data.visible)
    sparse, sparse_data = _every(dataclasses.replace(scene.start, heights=scene.start.heights[:n, :n]), data)
    assert sparse.n == 20 and sparse_data.shade is not None
    assert np.array_equal(sparse_data.shade, data.shade[:, ::3, ::3])


def test_relief_a_coarser_start_lacks_is_found_on_coarser_grids_first(scene: Scene) -> None:
    # a start 10 spacings low over a patch of 14 spacings (sigma): about 6 px of parallax, beyond
    # the joint solution's linear reach at the maplet's spacing, which keeps a fifth of it; solved
    # on grids 8, 4 and 2 times coarser first, it is gone before the fine solution
    x, y = np.meshgrid(scene.start.axis_km, scene.start.axis_km)
    pit = -10 * SPACING_KM * np.exp(-((x - 5e-4) ** 2 + (y + 4e-4) ** 2) / (2 * (7 * SPACING_KM) ** 2))
    start = dataclasses.replace(scene.truth, heights=scene.truth.heights + pit, albedo=None)
    zero = np.zeros((scene.data.count, 2))
    assert _shape_error(start.heights, scene.truth.heights) > 1.5 * SPACING_KM
    fine = refine(start, scene.data, offsets=zero)
    assert _shape_error(fine.heights, scene.truth.heights) > 0.25 * SPACING_KM
    first = _coarse_first(start, scene.data, offsets=zero, config=RefinementConfig())
    assert _shape_error(first.heights, scene.truth.heights) < 0.15 * SPACING_KM
    assert _shape_error(refine(first, scene.data, offsets=zero).heights, scene.truth.heights) < 0.1 * SPACING_KM


def _profiles(maplet: MapletGrid, rows: tuple[float, ...], *, sigma_km: float, seed: int = 3) -> MapletSpots:
    """Laser altimeter profiles along x at the rows y (shares of the half side), 40 spots each,
    measuring the true heights with noise of sigma_km."""
    rng = np.random.default_rng(seed)
    half = maplet.axis_km[-1]
    xy = np.concatenate([np.column_stack([np.linspace(-half, half, 40), np.full(40, y * half)]) for y in rows])
    z = _heights(xy[:, 0], xy[:, 1]) + rng.normal(0.0, sigma_km, len(xy))
    return MapletSpots(local_km=np.column_stack([xy, z]), sigma_km=np.full(len(xy), sigma_km))


def _images(data: MapletImages, count: int) -> MapletImages:
    return dataclasses.replace(data, images=data.images[:count], cameras=data.cameras[:count],
                               poses=data.poses[:count], sun_directions=data.sun_directions[:count],
                               visible=data.visible[:count], lit=data.lit[:count], weights=data.weights[:count])


def test_lidar_spots_place_a_maplet_its_few_images_cannot(scene: Scene) -> None:
    # A start 2 spacings high and tilted +-8 spacings, seen by three images: brightness cannot
    # see the mean height or a uniform tilt, and the solution keeps them (4.5 spacings RMS off);
    # three profiles of 1 cm spots place the maplet on them, within the bump the start lacks
    # (the middle profile crosses its top: 0.15 spacings high), the solution weighs them, and
    # the spots' mean residual from the refined heights places it again.
    start = _tilted(scene, 8.0)
    start = dataclasses.replace(start, heights=start.heights + 2 * SPACING_KM)
    three = _images(scene.data, 3)
    spots = _profiles(start, (-0.7, 0.0, 0.7), sigma_km=1e-5)
    alone = refine(start, three)
    placed, rise = placed_on_spots(start, spots, placement=PLACEMENT)
    joined = refine(placed, three, spots=spots)
    settled, _ = _settled_on_spots(placed, three, joined, spots=spots, config=DEFAULTS, raised_km=rise)

    def error(heights: np.ndarray) -> np.ndarray:
        return (heights - scene.truth.heights) / SPACING_KM

    assert float(np.sqrt(np.mean(error(alone.heights) ** 2))) > 3.0 and np.isnan(alone.lidar_rms)
    assert rise == pytest.approx(float(np.mean(scene.truth.heights)) - 2 * SPACING_KM, abs=0.3 * SPACING_KM)
    assert abs(float(np.mean(error(joined.heights)))) > 0.1  # the placement's own bias
    assert float(np.sqrt(np.mean(error(settled.heights) ** 2))) < 0.12
    assert _bump_height(settled.heights) == pytest.approx(BUMP_KM, rel=0.1)
    # the spots fit within their noise; weighed, they shape the maplet between the profiles,
    # the more the more they weigh (spots of 1 cm here: 1e-2 is the best of 1e-3 ... 1)
    assert 0.5 < settled.lidar_rms < 1.5
    unweighed = refine(placed, three)
    heavier = refine(placed, three, spots=spots, solver=Solver(lidar_weight=1e-2))
    assert np.std(error(heavier.heights)) < 0.7 * np.std(error(unweighed.heights))
    assert np.std(error(joined.heights)) < 0.9 * np.std(error(unweighed.heights))


def test_a_profile_tilts_a_maplet_along_itself_only(scene: Scene) -> None:
    # one profile along x says nothing of a tilt along y: the start's tilt across it stays
    x, y = np.meshgrid(scene.start.axis_km, scene.start.axis_km)
    tilt = 4 * SPACING_KM * (x + y) / x.max()
    start = dataclasses.replace(scene.start, heights=scene.start.heights + tilt)
    placed, _ = placed_on_spots(start, _profiles(start, (0.0,), sigma_km=1e-5), placement=PLACEMENT)
    change = placed.heights - start.heights
    along, across = np.gradient(change, SPACING_KM, axis=1), np.gradient(change, SPACING_KM, axis=0)
    assert float(np.mean(along)) == pytest.approx(-4 * SPACING_KM / x.max(), rel=0.1)
    assert np.allclose(across, 0.0, atol=1e-9)


def test_spots_over_a_maplet_are_those_over_its_grid_near_its_heights(scene: Scene) -> None:
    maplet = scene.truth
    frame, half = maplet.frame, maplet.axis_km[-1]
    local = np.array([[0.0, 0.0, 0.0], [0.9 * half, -0.9 * half, 0.0], [1.1 * half, 0.0, 0.0],
                      [0.0, 0.0, -0.5], [0.2 * half, 0.1 * half, 0.0]])
    local[:, 2] += grid_heights(maplet, local[:, :2])
    local[3, 2] = -0.5  # half a kilometre below: the body's far side, not this surface
    sigma = np.array([1e-5, 1e-5, 1e-5, 1e-5, np.nan])
    over = spots_over(maplet, Spots(body_km=frame.to_body(local), sigma_km=sigma))
    np.testing.assert_allclose(over.local_km, local[:2], atol=1e-9)
    assert over.count == 2 and spots_over(maplet, Spots(body_km=np.zeros((0, 3)), sigma_km=np.zeros(0))) is NO_SPOTS
    # the grid's heights are bilinear between the nodes: exact on a plane
    x = np.broadcast_to(maplet.axis_km, maplet.heights.shape)
    plane = dataclasses.replace(maplet, heights=0.3 * x + 2e-4)
    at = np.array([[0.37 * half, -0.81 * half], [-half, half]])
    np.testing.assert_allclose(grid_heights(plane, at), 0.3 * at[:, 0] + 2e-4, atol=1e-12)
