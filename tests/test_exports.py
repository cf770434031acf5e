"""Export formats: SPICE DSK, Gaskell ICQ, decimated meshes, PDS4 site products (their labels
validated against the shipped PDS4 schemas)."""

import re
from pathlib import Path

import numpy as np
import pds4_tools
import pytest
import spiceypy as sp
import trimesh
from matplotlib.image import imread

from pwm.decimate import decimate
from pwm.evaluate.distance import ClosestPoint
from pwm.frames import latlon_to_unit, local_frame, unit_to_latlon
from pwm.io.dsk import read_dsk, write_dsk
from pwm.io.icq import cube_points, icq_to_mesh, mesh_to_icq, read_icq, write_icq
from pwm.io.meshio import read_obj
from pwm.io.pds4 import checksum_md5
from pwm.io.site_product import CART_NS, SCHEMA_DIR, label_schema, write_site_product
from pwm.io.spice_kernels import SpkSegment, bundled_kernels, kernel_pool, write_spk
from pwm.io.terrain import site_projection
from pwm.mesh import Mesh
from pwm.raytrace import RayTracer
from pwm.site import BASELINE_M, roughness_m, slope_deg

BENNU_OBJ = (Path(__file__).resolve().parents[1] / "pwm" / "data" / "shapes"
             / "bennu_radar_nolan2013_sbgat.obj")
BENNU, OBSERVER = 2101955, -999
MM_KM = 1e-6


@pytest.fixture(scope="module")
def bennu() -> Mesh:
    return read_obj(BENNU_OBJ)


def _subdivided(mesh: Mesh, times: int) -> Mesh:
    vertices, faces = mesh.vertices, mesh.faces
    for _ in range(times):
        vertices, faces = trimesh.remesh.subdivide(vertices, faces)
    return Mesh(vertices, faces)


def _rays(n: int, distance_km: float, aim_km: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Rays from a sphere of radius distance_km towards random points within aim_km of the
    centre: all of them hit a body that contains that ball."""
    rng = np.random.default_rng(seed)
    origins = rng.normal(size=(n, 3))
    origins *= distance_km / np.linalg.norm(origins, axis=1, keepdims=True)
    directions = rng.uniform(-aim_km, aim_km, size=(n, 3)) - origins
    return origins, directions / np.linalg.norm(directions, axis=1, keepdims=True)


def _rays_and_rays_at(site: np.ndarray, spread_km: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """500 rays as `_rays` gives, and 500 from high above `site` towards points within
    spread_km of it."""
    origins, directions = _rays(500, 1.0, 0.1, seed=seed)
    towards = site + np.random.default_rng(seed + 1).uniform(-spread_km, spread_km, (500, 3))
    above = np.tile(3 * site, (500, 1))
    aimed = towards - above
    return (np.vstack([origins, above]),
            np.vstack([directions, aimed / np.linalg.norm(aimed, axis=1, keepdims=True)]))


def _mesh_intercepts(mesh: Mesh, origins: np.ndarray, directions: np.ndarray) -> np.ndarray:
    """The mesh's own intercepts: the plate Embree hits, met by the float64 ray (Embree's float32
    rays are off by ~1e-7 of their length, 2 mm at Deimos)."""
    tracer = RayTracer(mesh)
    hits = tracer.intersect(origins, directions)
    assert hits.hit.all()
    corner = mesh.vertices[mesh.faces[hits.face, 0]]
    normal = mesh.face_normals()[hits.face]
    t = np.einsum("ij,ij->i", corner - origins, normal) / np.einsum("ij,ij->i", directions, normal)
    points = origins + t[:, None] * directions
    assert np.abs(points - tracer.hit_points(origins, directions, hits)).max() < 1e-6 * t.max()
    return points


def _dskxv(target: str, frame: str, origins: np.ndarray, directions: np.ndarray) -> np.ndarray:
    points, found = sp.dskxv(False, target, [], 0.0, frame, origins, directions)
    assert np.all(found)
    return np.asarray(points)


def _descriptor(path: Path):
    handle = sp.dasopr(str(path))
    try:
        descriptor = sp.dskgd(handle, sp.dlabfs(handle))
        comments = [line for line in sp.dasec(handle)[1] if line.strip()]
    finally:
        sp.dascls(handle)
    return descriptor, comments


@pytest.mark.parametrize("subdivisions", [0, 2])
def test_dsk_intercepts_match_the_mesh(tmp_path, bennu, subdivisions):
    mesh = _subdivided(bennu, subdivisions)
    dsk = tmp_path / "bennu.bds"
    n = 1000
    origins, directions = _rays(n, 1.0, 0.1, seed=subdivisions)
    epochs = np.arange(n) * 60.0
    # one observer position per epoch, in the body-fixed frame, for sincpt (which also wants
    # Bennu's state relative to the solar system barycentre: a stand-in at the barycentre)
    spk = tmp_path / "observer.bsp"
    write_spk(spk, segments=[
        SpkSegment(OBSERVER, BENNU, epochs, np.hstack([origins, np.zeros((n, 3))]), "IAU_BENNU"),
        SpkSegment(BENNU, 0, epochs, np.zeros((n, 6)))])
    kernels = list(bundled_kernels().values())
    with kernel_pool(kernels):
        write_dsk(dsk, mesh, body=BENNU, frame="IAU_BENNU",
                  comment="Bennu radar shape (Nolan et al. 2013)\nwritten by the pwm tests")
    back = read_dsk(dsk)
    np.testing.assert_array_equal(back.vertices, mesh.vertices)
    np.testing.assert_array_equal(back.faces, mesh.faces)
    descriptor, comments = _descriptor(dsk)
    assert (descriptor.center, descriptor.surfce) == (BENNU, BENNU)
    assert comments == ["Bennu radar shape (Nolan et al. 2013)", "written by the pwm tests"]
    radii = np.linalg.norm(mesh.vertices, axis=1)
    assert descriptor.co3min <= radii.min() and descriptor.co3max >= radii.max() * (1 - 1e-12)
    assert (descriptor.co1min, descriptor.co1max) == (-np.pi, np.pi)

    expected = _mesh_intercepts(mesh, origins, directions)
    with kernel_pool([*kernels, dsk, spk]):
        assert sp.frmnam(descriptor.frmcde) == "IAU_BENNU"
        from_dskxv = _dskxv("BENNU", "IAU_BENNU", origins, directions)
        from_sincpt = np.array([
            sp.sincpt("DSK/UNPRIORITIZED", "BENNU", et, "IAU_BENNU", "NONE", str(OBSERVER),
                      "IAU_BENNU", d)[0] for et, d in zip(epochs, directions, strict=True)])
    assert np.abs(from_dskxv - expected).max() < MM_KM
    assert np.abs(from_sincpt - expected).max() < MM_KM


def _dense_site(mesh: Mesh, times: int) -> Mesh:
    """`mesh` with its first plate subdivided `times` times: 4^times small plates on a body of
    large ones (the midpoints lie on the edges they split, so the surface stays closed)."""
    corners = mesh.vertices[mesh.faces[0]]
    centre, reach = corners.mean(axis=0), np.linalg.norm(corners - corners.mean(axis=0), axis=1)
    vertices, faces = mesh.vertices, mesh.faces
    for _ in range(times):
        inside = np.linalg.norm(vertices[faces].mean(axis=1) - centre, axis=1) < reach.max()
        vertices, faces = trimesh.remesh.subdivide(vertices, faces,
                                                   face_index=np.flatnonzero(inside))
    return Mesh(vertices, faces)


def test_dsk_size_follows_the_plates_of_an_uneven_mesh(tmp_path, bennu):
    # a dense site on a coarse body: the mean plate extent is a tenth of the body's plates',
    # which a spatial index sized from it alone spends voxels on by the cube (24 MB, 2 kB a plate)
    mesh = _dense_site(decimate(bennu, 60), 6)
    assert len(mesh.faces) > 4000
    dsk = tmp_path / "site.bds"
    with kernel_pool(bundled_kernels().values()):
        write_dsk(dsk, mesh, body=BENNU, frame="IAU_BENNU", comment="dense site")
    # an even mesh of 4000 plates takes 180 bytes a plate
    assert dsk.stat().st_size < 400 * len(mesh.faces)

    site = mesh.vertices[mesh.faces[-1]].mean(axis=0)
    origins, directions = _rays_and_rays_at(site, 0.003, seed=11)
    expected = _mesh_intercepts(mesh, origins, directions)
    with kernel_pool([*bundled_kernels().values(), dsk]):
        assert np.abs(_dskxv("BENNU", "IAU_BENNU", origins, directions) - expected).max() < MM_KM


def test_a_dsk_in_segments_parts_the_mesh_and_gives_its_intercepts(tmp_path, bennu):
    # the body and a dense site as two segments (as a version with a site level is exported):
    # SPICE's intercepts over both are the mesh's own, at the site, across the seam and beyond
    mesh = _dense_site(decimate(bennu, 60), 6)
    site = mesh.vertices[mesh.faces[-1]].mean(axis=0)
    small = mesh.face_areas() < 0.01 * mesh.face_areas().max()
    parts = np.where(small, 7, 3)
    dsk = tmp_path / "parts.bds"
    with kernel_pool(bundled_kernels().values()):
        write_dsk(dsk, mesh, body=BENNU, frame="IAU_BENNU", comment="body and site", parts=parts)
    handle = sp.dasopr(str(dsk))
    try:
        first = sp.dlabfs(handle)
        with sp.no_found_check():
            second, found = sp.dlafns(handle, first)
        assert found and [sp.dskz02(handle, d)[1] for d in (first, second)] == [(~small).sum(), small.sum()]
    finally:
        sp.dascls(handle)
    # read back as one mesh, a vertex the two segments share made one again
    back = read_dsk(dsk)
    assert (len(back.vertices), len(back.faces)) == (len(mesh.vertices), len(mesh.faces))
    corners = [np.sort(m.vertices[m.faces].reshape(-1, 9), axis=0) for m in (mesh, back)]
    np.testing.assert_array_equal(*corners)

    origins, directions = _rays_and_rays_at(site, 0.02, seed=13)  # the site is about 15 m across
    expected = _mesh_intercepts(mesh, origins, directions)
    with kernel_pool([*bundled_kernels().values(), dsk]):
        assert np.abs(_dskxv("BENNU", "IAU_BENNU", origins, directions) - expected).max() < MM_KM
    tracer = RayTracer(mesh)
    hit = parts[tracer.intersect(origins, directions).face]
    assert (hit == 7).sum() > 300 and (hit == 3).sum() > 300  # both segments answer, and rays cross the seam


def test_dsk_with_an_unknown_frame_leaves_no_file(tmp_path, bennu):
    dsk = tmp_path / "bad.bds"
    with kernel_pool([]), pytest.raises(sp.exceptions.SpiceyError, match="PWM_NO_SUCH_FRAME"):
        write_dsk(dsk, bennu, body=BENNU, frame="PWM_NO_SUCH_FRAME", comment="no FK defines it")
    assert not dsk.exists()


def test_real_dsk_reads_and_round_trips(tmp_path, shared_data):
    deimos_dsk = shared_data / "spice" / "dsk" / "DEIMOS_K005_THO_V01.BDS"
    deimos = read_dsk(deimos_dsk)
    original, _ = _descriptor(deimos_dsk)
    assert np.array_equal(np.unique(deimos.faces), np.arange(len(deimos.vertices)))
    with kernel_pool([shared_data / "spice" / "generic" / "pck00010.tpc"]):
        a, b, c = sp.bodvrd("DEIMOS", "RADII", 3)[1]
    # a lat/lon grid model (degenerate plates at the poles): closed and outward, not manifold
    volume = trimesh.Trimesh(deimos.vertices, deimos.faces, process=False).volume
    assert abs(volume / (4 / 3 * np.pi * a * b * c) - 1) < 0.1
    radii = np.linalg.norm(deimos.vertices, axis=1)
    assert original.co3min <= radii.min() and radii.max() <= original.co3max

    copy = tmp_path / "deimos.bds"
    with kernel_pool([]):  # IAU_DEIMOS is built into SPICE
        write_dsk(copy, deimos, body=402, frame="IAU_DEIMOS", comment="Deimos, rewritten")
    again = read_dsk(copy)
    np.testing.assert_array_equal(again.vertices, deimos.vertices)
    np.testing.assert_array_equal(again.faces, deimos.faces)

    origins, directions = _rays(1000, 20.0, 2.0, seed=7)
    expected = _mesh_intercepts(deimos, origins, directions)
    intercepts = []
    for path in (deimos_dsk, copy):
        with kernel_pool([shared_data / "spice" / "generic" / "pck00010.tpc", path]):
            intercepts.append(_dskxv("DEIMOS", "IAU_DEIMOS", origins, directions))
        assert np.abs(intercepts[-1] - expected).max() < MM_KM, path.name
    # same plates, different spatial index: the same answers to rounding
    assert np.abs(intercepts[0] - intercepts[1]).max() < 1e-9


@pytest.mark.parametrize("lat0, lon0", [(5.0, 180.0), (90.0, 0.0)])
def test_dsk_coverage_of_a_patch(tmp_path, bennu, lat0, lon0):
    centre = latlon_to_unit(lat0, lon0)
    centroids = bennu.vertices[bennu.faces].mean(axis=1)
    near = centroids @ centre > np.cos(np.radians(35)) * np.linalg.norm(centroids, axis=1)
    used, faces = np.unique(bennu.faces[near], return_inverse=True)
    patch = Mesh(bennu.vertices[used], faces.reshape(-1, 3))
    dsk = tmp_path / "patch.bds"
    with kernel_pool(bundled_kernels().values()):
        write_dsk(dsk, patch, body=BENNU, frame="IAU_BENNU", surface=7, comment="patch")
    d, _ = _descriptor(dsk)
    assert d.surfce == 7
    lat, lon = (np.radians(a) for a in unit_to_latlon(patch.vertices))
    assert d.co2min <= lat.min() and lat.max() <= d.co2max
    if lat0 == 90.0:  # the cap covers the pole, which is no vertex: all longitudes
        assert d.co2max == np.pi / 2 and (d.co1min, d.co1max) == (-np.pi, np.pi)
        assert d.co2min > 0
    else:  # a range wrapping through 180 degrees is stored with min > max
        assert d.co1min > d.co1max and d.co2max - d.co2min < np.radians(90)
        lon = np.where(lon > np.pi, lon - 2 * np.pi, lon)
        assert np.all((lon >= d.co1min) | (lon <= d.co1max))

    aim = 0.2 * centre
    origins = np.tile(aim * 5, (200, 1))
    directions = aim + np.random.default_rng(3).uniform(-0.03, 0.03, (200, 3)) - origins
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    expected = _mesh_intercepts(patch, origins, directions)
    with kernel_pool([*bundled_kernels().values(), dsk]):
        assert np.abs(_dskxv("BENNU", "IAU_BENNU", origins, directions) - expected).max() < MM_KM


def test_icq_file_round_trip_is_exact_to_the_printed_digits(tmp_path, bennu):
    grid = mesh_to_icq(bennu, 16)
    first, second = tmp_path / "a.icq", tmp_path / "b.icq"
    write_icq(first, grid)
    lines = first.read_text().splitlines()
    assert lines[0] == f"{16:12d}" and len(lines) == 1 + 6 * 17 ** 2
    assert all(len(line) == 36 for line in lines[1:])  # 3F12.5
    back = read_icq(first)
    assert back.shape == (6, 17, 17, 3)
    assert np.abs(back - grid).max() <= 0.5e-5 * (1 + 1e-9)
    write_icq(second, back)
    assert second.read_text() == first.read_text()
    np.testing.assert_array_equal(read_icq(second), back)

    first.write_text("\n".join(lines[:-1]) + "\n")
    with pytest.raises(ValueError, match="vertices"):
        read_icq(first)


def test_icq_layout_follows_gaskell(bennu):
    q = 8
    grid = mesh_to_icq(bennu, q)
    # Shared edges as public ICQ readers state them, grid[face, j, i]
    edges = [(grid[1, 0, :], grid[0, q, :]), (grid[2, 0, :], grid[0, :, 0]),
             (grid[3, 0, :], grid[0, 0, ::-1]), (grid[4, 0, :], grid[0, ::-1, q]),
             (grid[2, :, q], grid[1, :, 0]), (grid[3, :, q], grid[2, :, 0]),
             (grid[4, :, q], grid[3, :, 0]), (grid[1, :, q], grid[4, :, 0]),
             (grid[5, 0, :], grid[1, q, :]), (grid[5, :, 0], grid[2, q, ::-1]),
             (grid[5, q, :], grid[3, q, ::-1]), (grid[5, :, q], grid[4, q, :])]
    for a, b in edges:
        np.testing.assert_array_equal(a, b)
    # SPC's SHAPE.TXT begins at the (-x, +y, +z) corner and steps towards +x
    corner = grid[0, 0, 0] / np.linalg.norm(grid[0, 0, 0])
    np.testing.assert_allclose(corner, np.array([-1, 1, 1]) / np.sqrt(3), atol=1e-6)
    assert grid[0, 0, 1, 0] > grid[0, 0, 0, 0]
    face_centres = [[0, 0, 1], [0, -1, 0], [-1, 0, 0], [0, 1, 0], [1, 0, 0], [0, 0, -1]]
    np.testing.assert_array_equal(np.sign(cube_points(q)[:, q // 2, q // 2]), face_centres)


def test_icq_mesh_is_closed_and_on_the_surface(bennu):
    q = 16
    mesh = icq_to_mesh(mesh_to_icq(bennu, q))
    assert len(mesh.vertices) == 6 * q * q + 2 and len(mesh.faces) == 12 * q * q
    solid = trimesh.Trimesh(mesh.vertices, mesh.faces, process=False)
    assert solid.is_watertight and solid.is_winding_consistent
    original = trimesh.Trimesh(bennu.vertices, bennu.faces, process=False).volume
    assert solid.volume > 0 and abs(solid.volume / original - 1) < 0.02
    distance, _, _ = ClosestPoint(bennu).query(mesh.vertices)
    assert distance.max() < MM_KM


def test_decimate_keeps_shape_and_albedo(bennu):
    mesh = _subdivided(bennu, 2)
    vertices = mesh.vertices
    albedo = 0.044 + 0.01 * np.sin(vertices[:, 0] / 0.05)
    mesh = Mesh(vertices, mesh.faces, albedo)
    target = 5000
    small = decimate(mesh, target)
    assert abs(len(small.faces) - target) <= 0.05 * target
    assert small.albedo is not None and small.albedo.shape == (len(small.vertices),)
    size = np.linalg.norm(np.ptp(vertices, axis=0))
    hausdorff = max(ClosestPoint(small).query(vertices)[0].max(),
                    ClosestPoint(mesh).query(small.vertices)[0].max())
    assert hausdorff < 0.01 * size
    # the albedo field survives: kept vertices carry what their neighbourhood had
    truth = 0.044 + 0.01 * np.sin(small.vertices[:, 0] / 0.05)
    assert np.abs(small.albedo - truth).max() < 0.003
    assert decimate(Mesh(vertices, mesh.faces), target).albedo is None
    with pytest.raises(ValueError):
        decimate(mesh, len(mesh.faces))



def test_a_decimation_only_drawn_takes_the_first_collapse_unchecked(bennu, monkeypatch):
    # the console's 3D view decimates every published version; on a site's millions of faces
    # the closed-surface checks took many minutes per version and a picture needs none of them
    import pwm.decimate as module
    mesh = _subdivided(bennu, 2)
    collapses = []
    simplify = module.fast_simplification.simplify

    def counted(*args, **kwargs):
        collapses.append(kwargs.get("agg"))
        return simplify(*args, **kwargs)

    def forbidden(*args, **kwargs):
        raise AssertionError("a drawn decimation checked for crossing faces")

    monkeypatch.setattr(module.fast_simplification, "simplify", counted)
    monkeypatch.setattr(module, "self_intersections", forbidden)
    target = 5000
    small = decimate(mesh, target, keep_closed=False)
    assert collapses == [module.ATTEMPTS[0][0]]
    assert abs(len(small.faces) - target) <= 0.05 * target
    size = np.linalg.norm(np.ptp(mesh.vertices, axis=0))
    assert ClosestPoint(mesh).query(small.vertices)[0].max() < 0.01 * size
    with pytest.raises(AssertionError, match="crossing"):
        decimate(mesh, target)

def _site(tmp_path: Path, **overrides):
    frame = local_frame(np.array([0.12, -0.2, 0.15]), np.array([0.4, -0.5, 0.6]))
    x = np.arange(40) * 1e-3 - 0.02
    y = np.arange(30) * 1e-3 - 0.01
    xx, yy = np.meshgrid(x, y)
    height = 2e-3 * np.exp(-(xx ** 2 + (yy - 0.005) ** 2) / 0.006 ** 2) + 0.05 * xx
    albedo = 0.044 + 0.01 * np.sin(xx / 0.003)
    height[3, 4] = np.nan
    albedo[5, 6] = np.nan
    projection = site_projection(frame, body="BENNU", radii_km=(0.2825, 0.2675, 0.254))
    args = dict(name="site_a", frame=frame, x_km=x, y_km=y, height_km=height, albedo=albedo,
                projection=projection, source_lidvid="urn:nasa:pds:pwm:shape_model:v0042::1.0",
                lid="urn:nasa:pds:orex.pwm:data_site:site_a", version="1.0", model_version="v0042",
                body_frame="IAU_BENNU", target_name="(101955) Bennu", mission="OSIRIS-REx",
                host_name="OSIRIS-REx", start_utc="2019-03-03T10:59:40",
                stop_utc="2019-04-01T00:00:00Z")
    args.update(overrides)
    return write_site_product(tmp_path, **args), args


def _north_up(structures, name: str) -> np.ndarray:
    """A layer with its rows back in the grid's order (y increasing): the product has north up."""
    return np.flipud(np.ma.filled(structures[name].as_masked().data.astype(float), np.nan))


def test_site_product_reads_back_with_pds4_tools(tmp_path):
    files, args = _site(tmp_path)
    structures = pds4_tools.read(str(files.label), quiet=True)
    height, albedo = _north_up(structures, "height"), _north_up(structures, "albedo")
    np.testing.assert_array_equal(height, args["height_km"] * 1e3)
    np.testing.assert_array_equal(albedo, args["albedo"].astype(np.float32))
    assert structures["height"].data.dtype == ">f8" and structures["albedo"].data.dtype == ">f4"
    # slope and roughness are pwm.site's of the heights carried over the baseline, in deg and m
    slope, roughness = _north_up(structures, "slope"), _north_up(structures, "roughness")
    expected_slope = slope_deg(args["height_km"] * 1e3, spacing_m=1.0, baseline_m=BASELINE_M)
    np.testing.assert_allclose(slope, expected_slope, rtol=1e-6)
    assert np.isnan(slope[3, 4]) and np.nanmax(slope) > 10
    np.testing.assert_allclose(roughness, roughness_m(args["height_km"] * 1e3, spacing_m=1.0),
                               rtol=1e-5, atol=1e-9)
    assert "<unit>deg</unit>" in files.label.read_text()

    label = files.label.read_text()
    assert f"<md5_checksum>{checksum_md5(files.data)}</md5_checksum>" in label
    assert f'<file_size unit="byte">{files.data.stat().st_size}</file_size>' in label
    assert "<unit>m</unit>" in label and "v0042" in label
    comment = structures.label.find(".//Observation_Area/comment").text
    vectors = re.findall(r"\(([-+0-9.e, ]+)\)", comment)
    numbers = [float(v) for vector in vectors for v in vector.split(",")]
    frame = args["frame"]
    np.testing.assert_allclose(numbers, np.concatenate([frame.origin, frame.rotation.ravel()]),
                               rtol=1e-11, atol=1e-12)

    preview = imread(files.preview)
    assert files.preview.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert preview.ndim == 3 and preview.shape[1] > preview.shape[0] > 200
    assert preview[..., :3].std() > 0.05

    with pytest.raises(FileExistsError):
        _site(tmp_path)


def test_site_product_carries_the_height_sigma_where_the_model_has_one(tmp_path):
    sigma = np.full((30, 40), 2e-5)
    sigma[:, :10] = np.nan  # no refined maplet there
    files, _ = _site(tmp_path, sigma_km=sigma)
    label_schema().validate(files.label.read_text())
    structures = pds4_tools.read(str(files.label), quiet=True)
    back = _north_up(structures, "height_sigma")
    assert np.isnan(back[:, :10]).all()
    np.testing.assert_allclose(back[:, 10:], 0.02, rtol=1e-6)  # m
    with pytest.raises(ValueError, match="sigma"):
        _site(tmp_path / "x", sigma_km=sigma[1:])


def test_site_product_rejects_irregular_grids(tmp_path):
    x = np.arange(40) * 1e-3
    x[-1] += 1e-4
    with pytest.raises(ValueError, match="regular"):
        _site(tmp_path, x_km=x)
    with pytest.raises(ValueError, match="len"):
        _site(tmp_path, y_km=np.arange(31) * 1e-3)
    with pytest.raises(ValueError, match="same step"):
        _site(tmp_path, y_km=np.arange(30) * 2e-3)


def test_site_label_has_cartography_and_validates_offline(tmp_path):
    files, args = _site(tmp_path)
    schema = label_schema()
    # every schema document was read from the shipped files, none from the network
    pds4 = {document.url for document in schema.maps.iter_schemas()
            if document.target_namespace.startswith("http://pds.nasa.gov/")}
    assert {Path(url.removeprefix("file://")).parent for url in pds4} == {SCHEMA_DIR}
    assert len(pds4) == 3
    schema.validate(files.label.read_text())
    label = pds4_tools.read(str(files.label), quiet=True).label
    cart = f"{{{CART_NS}}}"
    model = label.find(f".//{cart}Geodetic_Model")
    radii = [float(model.find(f"{cart}{axis}_axis_radius").text) for axis in "abc"]
    assert radii == [0.2825, 0.2675, 0.254]
    assert label.find(f".//{cart}map_projection_name").text == "Orthographic"
    projection = args["projection"]
    centre = float(label.find(f".//{cart}latitude_of_projection_origin").text)
    assert abs(centre - projection.centre_lat_deg) < 1e-9
    # the bounds hold the nodes: the origin's latitude lies inside them
    lat0, lon0 = unit_to_latlon(args["frame"].origin)
    south, north = (float(label.find(f".//{cart}{side}_bounding_coordinate").text)
                    for side in ("south", "north"))
    assert south < lat0 < north and north - south < 20.0
    corner_x = float(label.find(f".//{cart}upperleft_corner_x").text)
    assert abs(corner_x - projection.upper_left_m(args["x_km"], args["y_km"])[0]) < 1e-6
    source = label.find(".//Source_Product_Internal/lidvid_reference").text
    assert source == "urn:nasa:pds:pwm:shape_model:v0042::1.0"
    # the schema is strict: a label without its projection does not validate
    text = files.label.read_text()
    broken = re.sub(r"<cart:Spatial_Reference_Information>.*</cart:Spatial_Reference_Information>",
                    "", text, flags=re.S)
    assert broken != text and not schema.is_valid(broken)
