"""Terrain and point products without the catalog: the site projection against PROJ, GeoTIFF and
ISIS cube layers, LAS point clouds, OBJ and PLY albedo round trips, and the import's refusal of
exports that hold no mesh."""

import laspy
import numpy as np
import pvl
import pytest
import rasterio
from rasterio.warp import transform as warp

from pwm.frames import latlon_to_unit, local_frame, unit_to_latlon
from pwm.io.las import body_fixed_wkt, write_las
from pwm.io.meshio import ALBEDO_COLOUR_FLOOR, read_obj, read_ply, read_shape_model, write_obj, write_ply
from pwm.io.terrain import ISIS_NULL, TerrainDriver, TerrainLayer, site_projection, write_terrain
from pwm.mesh import Mesh

RADII_KM = (0.2825, 0.2675, 0.254)


def _grid():
    x = np.arange(21) * 1e-3 - 0.01
    y = np.arange(15) * 1e-3 - 0.007
    xx, yy = np.meshgrid(x, y)
    height = 1e-3 * np.sin(xx / 0.004) + 0.2 * yy
    height[2, 3] = np.nan
    return x, y, height


@pytest.mark.parametrize("normal", [(0.4, -0.5, 0.6), (1e-9, 0.0, 1.0)], ids=["tilted", "pole"])
def test_site_projection_is_the_site_frame_plane(normal):
    origin = 0.27 * latlon_to_unit(35.0, -50.0) if normal[2] < 1 else np.array([0.0, 0.0, 0.25])
    frame = local_frame(origin, np.array(normal))
    projection = site_projection(frame, body="BENNU", radii_km=RADII_KM)
    sphere = f"+proj=longlat +R={projection.sphere_radius_km * 1e3!r} +no_defs"
    # points of the sphere about the site: PROJ's orthographic eastings and northings are their
    # site frame x and y plus the origin's offset
    rng = np.random.default_rng(3)
    local = np.column_stack([rng.uniform(-0.02, 0.02, (50, 2)), np.zeros(50)])
    directions = frame.to_body(local)
    lat, lon = unit_to_latlon(directions)
    on_sphere = latlon_to_unit(lat, lon) * projection.sphere_radius_km
    east, north = warp(sphere, projection.wkt(), list(lon), list(lat))
    expected = frame.to_local(on_sphere)[:, :2].T + np.array(projection.offset_km)[:, None]
    np.testing.assert_allclose(np.array([east, north]) * 1e-3, expected, atol=1e-9)


def test_geotiff_and_isis_layers_read_back(tmp_path):
    x, y, height = _grid()
    frame = local_frame(0.27 * latlon_to_unit(35.0, -50.0), np.array([0.4, -0.5, 0.6]))
    projection = site_projection(frame, body="BENNU", radii_km=RADII_KM)
    layers = [TerrainLayer("height", height * 1e3, "m", "height (m)"),
              TerrainLayer("albedo", np.full(height.shape, 0.044), "", "normal albedo")]
    for driver, name in ((TerrainDriver.GEOTIFF, "a.tif"), (TerrainDriver.ISIS3, "a.cub")):
        path = tmp_path / name
        write_terrain(path, driver=driver, layers=layers, x_km=x, y_km=y, projection=projection,
                      metadata={"PWM_VERSION": "7", "BODY_FRAME": "IAU_BENNU"})
        with rasterio.open(path) as raster:
            back = raster.read(1, masked=True)
            assert raster.descriptions == ("height", "albedo")
            west, north = projection.upper_left_m(x, y)
            assert raster.transform.c == pytest.approx(west) and raster.transform.f == pytest.approx(north)
        # row 0 is the northernmost line; the gap is nodata
        np.testing.assert_allclose(np.flipud(back.filled(np.nan)), height * 1e3, atol=1e-4, equal_nan=True)
        assert back.mask.sum() == 1
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.cub", "a.tif"]  # one file each, no sidecar
    label = pvl.loads((tmp_path / "a.cub").read_bytes()[:65536].split(b"\0")[0].decode())
    assert list(label["IsisCube"]["BandBin"]["Name"]) == ["height", "albedo"]
    assert label["IsisCube"]["PwmTerrain"]["BODY_FRAME"] == "IAU_BENNU"
    raw = np.frombuffer((tmp_path / "a.cub").read_bytes()[65536:65536 + 4 * 21 * 15], "<f4")
    assert np.count_nonzero(raw == np.float32(ISIS_NULL)) == 1
    with pytest.raises(FileExistsError):
        write_terrain(tmp_path / "a.tif", driver=TerrainDriver.GEOTIFF, layers=layers, x_km=x, y_km=y,
                      projection=projection, metadata={})
    with pytest.raises(ValueError, match="grid"):
        write_terrain(tmp_path / "b.tif", driver=TerrainDriver.GEOTIFF, layers=[layers[0]], x_km=x[1:],
                      y_km=y, projection=projection, metadata={})


def test_las_round_trip_and_scale(tmp_path):
    rng = np.random.default_rng(1)
    vertices = rng.normal(size=(500, 3)) * 0.25
    albedo = rng.uniform(0.03, 0.06, 500)
    wkt = body_fixed_wkt(body="BENNU", frame="IAU_BENNU", radius_km=0.245)
    write_las(tmp_path / "a.las", vertices_km=vertices, albedo=albedo, crs_wkt=wkt,
              system_identifier="pwm v7 IAU_BENNU", description="test points")
    cloud = laspy.read(tmp_path / "a.las")
    assert np.abs(np.column_stack([cloud.x, cloud.y, cloud.z]) - vertices * 1e3).max() < 1e-3
    np.testing.assert_allclose(cloud.albedo, albedo, rtol=1e-6)
    assert cloud.header.scales[0] == pytest.approx(1e-4)
    # a body of 500 km (Vesta's size) does not fit 0.1 mm steps in 32-bit integers
    write_las(tmp_path / "big.las", vertices_km=vertices * 2000, albedo=None, crs_wkt=wkt,
              system_identifier="big", description="big")
    big = laspy.read(tmp_path / "big.las")
    assert big.header.scales[0] == pytest.approx(1e-3)
    assert np.abs(np.column_stack([big.x, big.y, big.z]) - vertices * 2e6).max() < 1e-3
    with pytest.raises(ValueError, match="32"):
        write_las(tmp_path / "c.las", vertices_km=vertices, albedo=None, crs_wkt=wkt,
                  system_identifier="x" * 33, description="")
    with pytest.raises(ValueError, match="finite"):
        write_las(tmp_path / "d.las", vertices_km=np.full((3, 3), np.nan), albedo=None, crs_wkt=wkt,
                  system_identifier="x", description="")


def _tetrahedron() -> Mesh:
    vertices = np.array([[0, 0, 0.3], [0.25, 0, -0.1], [-0.12, 0.2, -0.1], [-0.12, -0.2, -0.1]])
    faces = np.array([[0, 1, 2], [0, 2, 3], [0, 3, 1], [1, 3, 2]])
    return Mesh(vertices, faces, albedo=np.array([0.031, 0.044, 0.052, 0.047]))


def test_obj_and_ply_keep_the_albedo_and_their_headers(tmp_path):
    mesh = _tetrahedron()
    comments = ["pwm shape model version 7 (refined)", "frame IAU_BENNU", "units km"]
    write_obj(tmp_path / "a.obj", mesh, comments=comments)
    write_ply(tmp_path / "a.ply", mesh, comments=comments)
    obj_text = (tmp_path / "a.obj").read_text()
    assert all(f"# {c}\n" in obj_text for c in comments)
    # the colours span [floor, 1]: a body of albedo 0.03-0.05 shows grey to white, not black
    colours = np.array([line.split()[4:] for line in obj_text.splitlines() if line.startswith("v ")], float)
    assert colours.min() == pytest.approx(ALBEDO_COLOUR_FLOOR) and colours.max() == pytest.approx(1.0)
    header = (tmp_path / "a.ply").read_bytes().split(b"end_header")[0].decode()
    assert "property double z\nproperty float albedo\n" in header
    assert all(f"comment {c}\n" in header for c in comments)
    for back in (read_obj(tmp_path / "a.obj"), read_ply(tmp_path / "a.ply"),
                 read_shape_model(tmp_path / "a.obj"), read_shape_model(tmp_path / "a.ply")):
        np.testing.assert_allclose(back.vertices, mesh.vertices, atol=1e-9)
        np.testing.assert_allclose(back.albedo, mesh.albedo, rtol=1e-6)
    # an OBJ without the scale comment (older pwm, other tools) keeps its first channel as albedo
    (tmp_path / "old.obj").write_text("v 0 0 0 0.04 0.04 0.04\nv 1 0 0 0.05 0.05 0.05\n"
                                      "v 0 1 0 0.06 0.06 0.06\nf 1 2 3\n")
    np.testing.assert_allclose(read_obj(tmp_path / "old.obj").albedo, [0.04, 0.05, 0.06])
    with pytest.raises(ValueError, match="single"):
        write_obj(tmp_path / "b.obj", mesh, comments=["two\nlines"])


@pytest.mark.parametrize(("head", "what"), [(b"LASF\x00\x00", "LAS point cloud"), (b"II*\x00\x08", "TIFF"),
                                            (b"Object = IsisCube\n", "ISIS cube"), (b"PK\x03\x04", "zip")])
def test_import_refuses_exports_without_faces(tmp_path, head, what):
    path = tmp_path / "product"
    path.write_bytes(head + bytes(64))
    with pytest.raises(ValueError, match=f"{what}.*no faces"):
        read_shape_model(path)


def test_projection_rejects_bad_radii():
    frame = local_frame(np.array([0.0, 0.0, 0.25]), np.array([0.3, 0.1, 1.0]))
    for radii in ((0.2, 0.2), (0.2, -0.1, 0.2), (0.2, np.nan, 0.2)):
        with pytest.raises(ValueError, match="radii"):
            site_projection(frame, body="X", radii_km=radii)
