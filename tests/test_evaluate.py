"""Model evaluation: exact closest points, ICP, image similarity, boulder relief, figures."""

from pathlib import Path

import matplotlib.image
import numpy as np
import pytest
import trimesh
from scipy.ndimage import gaussian_filter
from scipy.spatial import ConvexHull
from scipy.spatial.transform import Rotation

import pwm
from pwm.evaluate import plots
from pwm.evaluate.completeness import completeness
from pwm.evaluate.distance import ClosestPoint
from pwm.evaluate.icp import register
from pwm.evaluate.images import ncc, ssim
from pwm.evaluate.profiles import boulder_height_ratio
from pwm.io.meshio import read_mesh
from pwm.mesh import Mesh

BENNU = Path(pwm.__file__).parent / "data" / "shapes" / "bennu_radar_nolan2013_sbgat.obj"


def _segment_distance(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    ab = b - a
    t = np.clip(np.sum((p - a) * ab, axis=-1) / np.sum(ab * ab, axis=-1), 0.0, 1.0)
    return np.linalg.norm(p - (a + t[:, None] * ab), axis=-1)


def _triangle_distance(p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Point-triangle distances by a different route than the code under test: the foot of the
    perpendicular if it falls inside the triangle, else the nearest of the three edges."""
    n = np.cross(b - a, c - a)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    h = np.sum((p - a) * n, axis=-1)
    foot = p - h[:, None] * n
    inside = np.ones(len(h), bool)
    for x, y in ((a, b), (b, c), (c, a)):
        inside &= np.sum(np.cross(y - x, foot - x) * n, axis=-1) >= 0
    edges = np.minimum(_segment_distance(p, a, b), _segment_distance(p, b, c))
    return np.where(inside, np.abs(h), np.minimum(edges, _segment_distance(p, c, a)))


def _brute_force_distance(points: np.ndarray, mesh: Mesh) -> np.ndarray:
    v = mesh.vertices[mesh.faces]
    return np.array([_triangle_distance(p[None], v[:, 0], v[:, 1], v[:, 2]).min() for p in points])


def _inside(points: np.ndarray, mesh: Mesh, rng: np.random.Generator) -> np.ndarray:
    """Inside a closed mesh by the parity of crossings of a random ray (Moller-Trumbore)."""
    v = mesh.vertices[mesh.faces]
    a, e1, e2 = v[:, 0], v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]
    out = np.empty(len(points), bool)
    for i, p in enumerate(points):
        d = rng.normal(size=3)
        h = np.cross(d, e2)
        det = np.sum(e1 * h, axis=1)
        s = p - a
        u = np.sum(s * h, axis=1) / det
        q = np.cross(s, e1)
        w = (q @ d) / det
        t = np.sum(e2 * q, axis=1) / det
        out[i] = np.count_nonzero((u >= 0) & (w >= 0) & (u + w <= 1) & (t > 0)) % 2 == 1
    return out


def _height_field(x_km: np.ndarray, y_km: np.ndarray, z_km: np.ndarray) -> Mesh:
    """Two triangles per grid cell, outward normal +z; z_km is (len(y), len(x))."""
    ny, nx = z_km.shape
    xx, yy = np.meshgrid(x_km, y_km)
    i = np.arange(nx * ny).reshape(ny, nx)
    a, b, c, d = i[:-1, :-1].ravel(), i[:-1, 1:].ravel(), i[1:, 1:].ravel(), i[1:, :-1].ravel()
    faces = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    return Mesh(np.stack([xx, yy, z_km], axis=-1).reshape(-1, 3), faces)


def _rough_surface(rng: np.random.Generator, n: int = 201, size_km: float = 1.0) -> Mesh:
    """A 1 km height field with relief on 30-300 m wavelengths (about 10 m rms), 5 m spacing."""
    x = np.linspace(-size_km / 2, size_km / 2, n)
    xx, yy = np.meshgrid(x, x)
    z = np.zeros_like(xx)
    for _ in range(30):
        k = rng.normal(size=2) * 2 * np.pi / rng.uniform(0.03, 0.3)
        phase = rng.uniform(0, 2 * np.pi)
        z += rng.uniform(0.002, 0.01) * np.cos(k[0] * xx + k[1] * yy + phase)
    return _height_field(x, x, z)


@pytest.fixture(scope="module")
def bennu() -> Mesh:
    return read_mesh(BENNU)


@pytest.fixture(scope="module")
def spiky() -> Mesh:
    """A closed star-shaped mesh with sharp convex and concave vertices and edges."""
    rng = np.random.default_rng(3)
    u = rng.normal(size=(400, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    faces = ConvexHull(u).simplices
    a, b, c = u[faces[:, 0]], u[faces[:, 1]], u[faces[:, 2]]
    inward = np.sum(np.cross(b - a, c - a) * a, axis=1) < 0
    faces[inward] = faces[inward][:, ::-1]
    return Mesh(u * rng.uniform(0.6, 1.4, (400, 1)), faces)


# --- distances ---------------------------------------------------------------------------


def test_distance_matches_brute_force(bennu):
    rng = np.random.default_rng(1)
    edge = bennu.mean_edge_length()
    points = np.concatenate([
        rng.uniform(-0.4, 0.4, (300, 3)),  # inside and outside, near and far
        bennu.vertices[rng.integers(0, len(bennu.vertices), 300)] + rng.normal(0, edge, (300, 3)),
        rng.normal(0, 5.0, (30, 3)),  # kilometres away
    ])
    expected = _brute_force_distance(points, bennu)
    for k in (1, 8):  # k=1 relies on fetching more neighbours where the first ones fall short
        distance, closest, face = ClosestPoint(bennu, k=k).query(points)
        assert np.abs(distance - expected).max() < 1e-12
        assert np.abs(np.linalg.norm(points - closest, axis=1) - distance).max() < 1e-13
        corners = bennu.vertices[bennu.faces[face]]
        on_face = _triangle_distance(closest, corners[:, 0], corners[:, 1], corners[:, 2])
        assert on_face.max() < 1e-12


def test_distance_of_mesh_vertices_is_zero(bennu):
    distance, closest, _ = ClosestPoint(bennu).query(bennu.vertices)
    assert distance.max() < 1e-15
    assert np.abs(closest - bennu.vertices).max() < 1e-15


def test_distance_exact_where_large_faces_pass_between_small_ones():
    """A fine grid plus two big triangles a little above it: points under the middle of the big
    triangles have only fine-grid vertices nearby, yet the closest face is a big one."""
    x = np.linspace(0.0, 1.0, 41)
    fine = _height_field(x, x, np.zeros((41, 41)))
    big = np.array([[-1.0, -1.0, 0.05], [2.0, -1.0, 0.05], [2.0, 2.0, 0.05], [-1.0, 2.0, 0.05]])
    mesh = Mesh(np.vstack([fine.vertices, big]),
                np.vstack([fine.faces, len(fine.vertices) + np.array([[0, 1, 2], [0, 2, 3]])]))
    rng = np.random.default_rng(4)
    points = np.column_stack([rng.uniform(0, 1, (400, 2)), rng.uniform(0.026, 0.2, 400)])
    distance, _, face = ClosestPoint(mesh).query(points)
    assert np.abs(distance - _brute_force_distance(points, mesh)).max() < 1e-12
    assert np.any(face >= len(fine.faces))


def test_signed_distance_sign_is_inside_outside(spiky):
    rng = np.random.default_rng(5)
    edge = spiky.mean_edge_length()
    normals = spiky.vertex_normals()
    idx = rng.integers(0, len(spiky.vertices), 3000)
    # Close to vertices, so that many closest points fall on vertices and edges, where a face
    # normal can give the wrong side.
    points = spiky.vertices[idx] + rng.uniform(-0.3, 0.3, (3000, 1)) * edge * (
        normals[idx] + rng.normal(0, 0.3, (3000, 3)))
    surface = ClosestPoint(spiky)
    signed = surface.signed_distance(points)
    distance, closest, face = surface.query(points)
    assert np.array_equal(np.abs(signed), distance)
    assert np.array_equal(signed < 0, _inside(points, spiky, rng))
    naive = np.einsum("ij,ij->i", points - closest, surface.face_normals[face]) < 0
    assert np.any(naive != (signed < 0))  # the case the pseudonormals are there for


# --- ICP ---------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def rough() -> ClosestPoint:
    return ClosestPoint(_rough_surface(np.random.default_rng(6)))


def _displaced(rough: ClosestPoint, translation_km: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Every 4th vertex of the inner 350 m, displaced, and the rotation that, with
    translation_km, maps them back onto the surface."""
    rotation = Rotation.from_rotvec(1e-3 * np.array([0.6, -0.48, 0.64])).as_matrix()
    vertices = rough.mesh.vertices
    inner = vertices[np.hypot(vertices[:, 0], vertices[:, 1]) < 0.35][::4]
    return (inner - translation_km) @ rotation, rotation


@pytest.mark.parametrize("translation_m", [[3.0, -2.0, 1.5], [10.0, -8.0, 4.0]])
def test_icp_recovers_known_transform(rough, translation_m):
    """1e-3 rad and up to 2.6 grid spacings (5 m) of offset, recovered to 1e-6 of 1 km."""
    translation = np.array(translation_m) * 1e-3
    source, rotation = _displaced(rough, translation)
    fit = register(source, rough.mesh)
    assert np.abs(fit.rotation - rotation).max() < 1e-6
    assert np.abs(fit.translation - translation).max() < 1e-6
    assert rough.query(fit.apply(source))[0].max() < 1e-6


def test_icp_max_distance_rejects_outliers(rough):
    translation = np.array([3.0, -2.0, 1.5]) * 1e-3
    source, rotation = _displaced(rough, translation)
    outliers = source[::10] + np.array([0.0, 0.0, 0.2])  # 200 m off the surface
    source = np.vstack([source, outliers])
    fit = register(source, rough, max_distance_km=0.02)
    assert np.abs(fit.rotation - rotation).max() < 1e-6
    assert np.abs(fit.translation - translation).max() < 1e-6
    biased = register(source, rough, max_iterations=5)
    assert np.abs(biased.translation - translation).max() > 1e-3


# --- images ------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def scene() -> tuple[np.ndarray, np.ndarray]:
    """A textured 256 x 300 image (speckle on smooth shading) and a mask with a dark corner
    (shadow) and a border (sky) left out."""
    rng = np.random.default_rng(8)
    image = 0.3 + 0.05 * gaussian_filter(rng.normal(size=(256, 300)), 6) * 6
    image += 0.02 * rng.normal(size=image.shape)
    mask = np.ones(image.shape, bool)
    mask[:, :20] = False
    mask[180:, 220:] = False
    return image, mask


def test_identical_images_score_one(scene):
    image, mask = scene
    assert ncc(image, image, mask) == pytest.approx(1.0, abs=1e-12)
    assert ssim(image, image, mask) == pytest.approx(1.0, abs=1e-12)
    assert ncc(image, 2.5 * image + 0.1, mask) == pytest.approx(1.0, abs=1e-12)


def test_inverted_image_has_ncc_minus_one(scene):
    image, mask = scene
    assert ncc(image, 1.0 - image, mask) == pytest.approx(-1.0, abs=1e-12)


@pytest.mark.parametrize("noise", [0.01, 0.03, 0.1])
def test_ncc_under_additive_noise_matches_expectation(scene, noise):
    image, mask = scene
    noisy = image + np.random.default_rng(9).normal(0, noise, image.shape)
    signal = image[mask].std()
    assert ncc(image, noisy, mask) == pytest.approx(signal / np.hypot(signal, noise), abs=0.01)


def test_ssim_falls_with_noise(scene):
    image, mask = scene
    rng = np.random.default_rng(10)
    scores = [ssim(image, image + rng.normal(0, n, image.shape), mask) for n in (0.005, 0.02, 0.08)]
    assert 1.0 > scores[0] > scores[1] > scores[2] > 0.0


def test_pixels_outside_the_mask_are_ignored(scene):
    image, mask = scene
    model = image + np.random.default_rng(11).normal(0, 0.02, image.shape)
    spoiled = model.copy()
    spoiled[:, :14] = 50.0  # 6 px or more from the nearest masked pixel: beyond the SSIM window
    spoiled[200:, 240:] = -3.0
    assert ncc(image, spoiled, mask) == ncc(image, model, mask)
    assert ssim(image, spoiled, mask) == pytest.approx(ssim(image, model, mask), abs=1e-12)
    assert ssim(image, spoiled, np.ones_like(mask)) < ssim(image, model, np.ones_like(mask))


# --- boulders ----------------------------------------------------------------------------


def test_boulder_height_ratio_of_scaled_bumps():
    x = np.arange(-0.02, 0.02, 0.0002)  # 40 m at 20 cm
    y = np.arange(-0.015, 0.015, 0.0002)
    xx, yy = np.meshgrid(x, y)
    rng = np.random.default_rng(12)
    ground = 0.05 * xx - 0.03 * yy + 5e-5 * gaussian_filter(rng.normal(size=xx.shape), 3)
    centres = np.array([[-0.01, -0.006], [0.0, 0.0], [0.01, 0.005], [-0.008, 0.008]])
    diameters = np.array([0.004, 0.003, 0.006, 0.002])
    heights = np.array([0.002, 0.0015, 0.003, 0.001])
    recovered = np.array([0.7, 1.0, 0.5, 0.7])
    truth, model = ground.copy(), ground.copy()
    for (cx, cy), d, h, f in zip(centres, diameters, heights, recovered, strict=True):
        r2 = ((xx - cx) ** 2 + (yy - cy) ** 2) / (0.5 * d) ** 2
        bump = h * np.sqrt(np.clip(1 - r2, 0, None))  # a half-ellipsoid
        truth += bump
        model += f * bump
    ratios = boulder_height_ratio(x, y, truth, model, centres_km=np.vstack([centres, [0.5, 0.5]]),
                                  diameters_km=np.append(diameters, 0.002))
    assert np.allclose(ratios[:-1], recovered, atol=0.02)
    assert np.isnan(ratios[-1])  # off the grid


def test_a_boulder_is_measured_from_its_ground_not_its_neighbours():
    # a boulder among taller neighbours over most of its ring; the model has it exactly and them
    # 30% low, which moves the ring's median unless they are left out of it
    x = y = np.linspace(-0.012, 0.012, 241)
    xx, yy = np.meshgrid(x, y)
    around = [(0.0055 * np.cos(a), 0.0055 * np.sin(a)) for a in np.arange(4) * np.pi / 2]

    def cap(cx: float, cy: float, d: float, h: float) -> np.ndarray:
        return h * np.sqrt(np.clip(1 - ((xx - cx) ** 2 + (yy - cy) ** 2) / (0.5 * d) ** 2, 0, None))

    boulder, neighbours = cap(0.0, 0.0, 0.004, 0.001), sum(cap(cx, cy, 0.005, 0.0016) for cx, cy in around)
    truth, model = boulder + neighbours, boulder + 0.7 * neighbours
    centre, diameter = np.zeros((1, 2)), np.array([0.004])
    plain = boulder_height_ratio(x, y, truth, model, centres_km=centre, diameters_km=diameter)[0]
    ground = neighbours == 0
    apart = boulder_height_ratio(x, y, truth, model, centres_km=centre, diameters_km=diameter, ground=ground)[0]
    assert apart == pytest.approx(1.0, abs=1e-12)
    assert abs(plain - 1.0) > 0.05
    with pytest.raises(ValueError, match="ground"):
        boulder_height_ratio(x, y, truth, model, centres_km=centre, diameters_km=diameter, ground=ground[1:])


# --- figures -----------------------------------------------------------------------------


def _assert_png(path: Path) -> None:
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    pixels = matplotlib.image.imread(path)
    assert pixels.ndim == 3 and min(pixels.shape[:2]) > 100


def test_figures_are_written(tmp_path, scene):
    x = np.linspace(-0.01, 0.01, 50)
    y = np.linspace(-0.008, 0.008, 40)
    error = np.random.default_rng(13).normal(0, 0.3, (40, 50))
    error[:5, :5] = np.nan
    plots.height_error_map(tmp_path / "error.png", x, y, error, title="height error")
    d = np.linspace(0, 6, 60)
    plots.profiles(tmp_path / "profiles.png",
                   [(d, np.exp(-(d - 3) ** 2), 0.6 * np.exp(-(d - 3) ** 2), f"boulder {i}")
                    for i in range(4)])
    image, _ = scene
    plots.image_comparison(tmp_path / "images.png", image, image * 0.9, title="image 1")
    for name in ("error.png", "profiles.png", "images.png"):
        _assert_png(tmp_path / name)


def test_an_image_comparison_draws_a_small_site_large_on_its_own_scales(tmp_path):
    # a site of 40 x 40 px in a 1000 px frame, as a held-out view of a site cut shows it: the
    # differences must show, not be drowned by the frame's zeros
    rng = np.random.default_rng(5)
    truth, model = np.zeros((1000, 1000)), np.zeros((1000, 1000))
    mask = np.zeros(truth.shape, bool)
    mask[500:540, 600:640] = True
    truth[mask] = rng.uniform(0.01, 0.02, mask.sum())
    model[mask] = truth[mask] * rng.normal(1.0, 0.05, mask.sum())
    plots.image_comparison(tmp_path / "site.png", truth, model, mask=mask, title="site")
    image = matplotlib.image.imread(tmp_path / "site.png")[..., :3]
    difference_panel = image[:, 2 * image.shape[1] // 3 :]
    assert (np.ptp(difference_panel, axis=-1) > 0.1).mean() > 0.25  # 0.02 drawn whole-frame


def test_a_coverage_map_shows_the_few_gaps_among_many_covered_points(tmp_path):
    directions = np.random.default_rng(3).normal(size=(20000, 3))
    points = 0.25 * directions / np.linalg.norm(directions, axis=1)[:, None]
    top = np.array(matplotlib.colormaps["viridis"](1.0)[:3])  # the colour of a gap

    def gap_pixels(gap_m):
        plots.coverage_map(tmp_path / "coverage.png", points, gap_m, tolerance_m=4.0)
        image = matplotlib.image.imread(tmp_path / "coverage.png")[..., :3]
        the_map = image[:, : int(0.75 * image.shape[1])]  # not the colour bar, on the right
        return (np.abs(the_map - top).max(axis=-1) < 0.05).sum()

    assert gap_pixels(np.full(len(points), 0.5)) == 0  # all covered: no point in a gap's colour
    assert gap_pixels(np.where(np.arange(len(points)) % 200 == 0, 5.0, 0.5)) > 20  # 0.5% not covered


def test_completeness_sees_a_hole_that_distances_cannot():
    sphere = trimesh.creation.icosphere(subdivisions=5, radius=0.25)
    whole = Mesh(np.asarray(sphere.vertices), np.asarray(sphere.faces))
    # the model lacks the cap above z = 0.8 R: a tenth of the sphere's area, (1 - cos) / 2
    centroids = whole.vertices[whole.faces].mean(axis=1)
    holed = Mesh(whole.vertices, whole.faces[centroids[:, 2] <= 0.8 * 0.25])
    assert completeness(whole, whole, tolerance_km=1e-3) == 1.0
    # what is modelled is exact: every model point lies on the truth, so distances see nothing
    assert ClosestPoint(whole).query(holed.vertices)[0].max() < 1e-12
    missing = 1.0 - completeness(whole, holed, tolerance_km=1e-3)
    cap = (1.0 - 0.8) / 2.0
    assert missing == pytest.approx(cap, abs=0.01)
    with pytest.raises(ValueError, match="tolerance"):
        completeness(whole, holed, tolerance_km=0.0)


def test_boulder_size_classes_take_each_boulders_disc_and_apron():
    from pwm.evaluate.classes import boulder_size_masks
    from pwm.simulate.terrain import Boulder

    axis = np.arange(-100, 101) * 1e-4  # a 20 m square every 10 cm, km
    small = Boulder(x_km=-0.005, y_km=0.0, diameter_km=0.8e-3, height_km=0.3e-3, steep=False, albedo_factor=1.0)
    large = Boulder(x_km=0.00405, y_km=0.00205, diameter_km=4e-3, height_km=1e-3, steep=False, albedo_factor=1.0)
    masks = boulder_size_masks(axis, axis, [small, large])
    assert list(masks) == ["boulders <1 m", "boulders 1-2 m", "boulders 2-3 m", "boulders >=3 m"]
    assert not masks["boulders 1-2 m"].any() and not masks["boulders 2-3 m"].any()
    gx, gy = np.meshgrid(axis, axis)
    # 0.75 diameters: the disc and an apron half a radius wide, and nothing else
    assert masks["boulders >=3 m"].sum() == np.sum(np.hypot(gx - 0.00405, gy - 0.00205) <= 3e-3)
    assert masks["boulders <1 m"][100, 44] and not masks["boulders <1 m"][100, 57]


def test_the_tail_beyond_three_gsd_carries_its_share_of_the_squared_error():
    from pwm.evaluate.report import _tail

    distance = np.r_[np.full(97, 0.5e-4), np.full(3, 5e-4)]  # 3% of the vertices 5 GSD off at 10 cm
    tail = _tail(distance, threshold_km=3e-4)
    assert tail["vertex_share"] == pytest.approx(0.03)
    assert tail["squared_error_share"] == pytest.approx(3 * 25 / (3 * 25 + 97 * 0.25))
    assert tail["rms_without_m"] == pytest.approx(0.05)


def test_maps_point_north(tmp_path):
    # an error of zero is drawn white: what is dark inside the map's top right corner (below its
    # frame, left of its right edge) is the arrow
    x, y = np.linspace(-0.01, 0.01, 50), np.linspace(-0.01, 0.01, 50)
    plots.height_error_map(tmp_path / "error.png", x, y, np.zeros((50, 50)), title="flat")
    image = matplotlib.image.imread(tmp_path / "error.png")[..., :3]
    height, width = image.shape[:2]
    dark = image.max(axis=-1) < 0.3
    rows, cols = np.nonzero(dark[int(0.1 * height) : height // 4, int(0.7 * width) : int(0.77 * width)])
    assert len(rows) > 20  # the arrow and its N
    assert np.ptp(rows) > 3 * np.ptp(cols)  # upright: taller than wide
