"""Exports through the API and the CLI: a DSK that SPICE intercepts like the mesh, the real
Deimos DSK imported and exported unchanged, ICQ and decimated meshes, the PDS4 site product and
the same site as a GeoTIFF and an ISIS cube, the vertices as LAS, and every mesh export imported
back."""

from __future__ import annotations

import hashlib
import io
import json
import zipfile
from pathlib import Path

import laspy
import numpy as np
import pds4_tools
import pytest
import rasterio
import spiceypy as sp
from typer.testing import CliRunner

from pwm.frames import unit_to_latlon
from pwm.io.dsk import read_dsk
from pwm.io.icq import icq_to_mesh, read_icq
from pwm.io.meshio import read_obj, read_shape_model
from pwm.io.site_product import label_schema
from pwm.io.spice_kernels import kernel_pool
from pwm.raytrace import RayTracer
from service.cli import app as cli
from service.db import session_scope
from service.exports import icq_size
from service.rows import ModelKind
from service.versions import import_model, publish_version, version_mesh

MM_KM = 1e-6


def _download(client, version, tmp_path: Path, name: str, **params) -> Path:
    response = client.get(f"/versions/{version}/export", params=params)
    assert response.status_code == 200, response.text
    assert response.headers["etag"] == f'"{hashlib.sha256(response.content).hexdigest()}"'
    path = tmp_path / name
    path.write_bytes(response.content)
    return path


def _intercepts_agree(dsk: Path, mesh) -> None:
    """SPICE's intercepts on the DSK of Bennu in IAU_BENNU are the mesh's, within a mm, along
    500 rays from all round that all meet the body."""
    rng = np.random.default_rng(5)
    origins = rng.normal(size=(500, 3))
    origins *= 1.5 / np.linalg.norm(origins, axis=1, keepdims=True)
    directions = rng.uniform(-0.1, 0.1, size=(500, 3)) - origins
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    tracer = RayTracer(mesh)
    hits = tracer.intersect(origins, directions)
    assert hits.hit.all()
    expected = tracer.hit_points(origins, directions, hits)
    with kernel_pool([dsk]):
        points, found = sp.dskxv(False, "BENNU", [], 0.0, "IAU_BENNU", origins, directions)
    assert np.all(found)
    assert np.abs(np.asarray(points) - expected).max() < MM_KM


def test_dsk_intercepts_agree_with_the_mesh(client, populated, tmp_path):
    # body and frame come from the catalog's images: Bennu, IAU_BENNU
    dsk = _download(client, 2, tmp_path, "v2.bds", format="dsk")
    mesh = populated.refined
    back = read_dsk(dsk)
    np.testing.assert_array_equal(back.vertices, mesh.vertices)
    np.testing.assert_array_equal(back.faces, mesh.faces)
    _intercepts_agree(dsk, mesh)


def test_the_real_deimos_dsk_imports_and_round_trips(client, populated, tmp_path, shared_data):
    deimos = shared_data / "spice" / "dsk" / "DEIMOS_K005_THO_V01.BDS"
    with session_scope(populated.app.state.sessions) as session:
        number = import_model(session, data_dir=populated.data_dir, path=deimos).version
    detail = client.get(f"/versions/{number}").json()
    assert detail["kind"] == "imported"
    assert detail["statistics"]["source_sha256"] == hashlib.sha256(
        deimos.read_bytes()).hexdigest()
    # the catalog's frame is Bennu's: the body and frame are given
    exported = _download(client, number, tmp_path, "deimos.bds", format="dsk", body="DEIMOS",
                         frame="IAU_DEIMOS")
    original, again = read_dsk(deimos), read_dsk(exported)
    np.testing.assert_array_equal(again.vertices, original.vertices)
    np.testing.assert_array_equal(again.faces, original.faces)
    handle = sp.dasopr(str(exported))
    try:
        descriptor = sp.dskgd(handle, sp.dlabfs(handle))
    finally:
        sp.dascls(handle)
    assert descriptor.center == 402
    assert client.get(f"/versions/{number}/export",
                      params={"format": "dsk", "body": "NO_SUCH_BODY"}).status_code == 422


def test_icq_and_decimated_exports(client, populated, tmp_path):
    faces = len(populated.refined.faces)
    icq = _download(client, 2, tmp_path, "v2.icq", format="icq")
    grid = read_icq(icq)
    q = icq_size(faces)
    assert grid.shape == (6, q + 1, q + 1, 3)
    # on the model's surface: each vertex is where its cube direction meets the mesh
    tracer = RayTracer(populated.refined)
    directions = grid.reshape(-1, 3) / np.linalg.norm(grid.reshape(-1, 3), axis=1, keepdims=True)
    origins = np.zeros_like(directions)
    hits = tracer.intersect(origins, directions)
    surface = tracer.hit_points(origins, directions, hits)
    assert np.abs(surface - grid.reshape(-1, 3)).max() < 1e-5  # the file's 5 decimals, km
    small = _download(client, 2, tmp_path, "v2-small.icq", format="icq", faces=1200)
    assert read_icq(small).shape == (6, 11, 11, 3)

    obj = _download(client, 2, tmp_path, "v2-2000.obj", format="obj", faces=2000)
    decimated = read_obj(obj)
    assert abs(len(decimated.faces) - 2000) <= 100 and decimated.albedo is not None
    full = _download(client, 2, tmp_path, "v2.ply", format="ply", faces=10 * faces)
    # at full resolution: the version's mesh, with its number and frame in the header
    assert b"comment pwm shape model version 2 (refined)" in full.read_bytes()[:1000]
    assert b"comment frame IAU_BENNU" in full.read_bytes()[:1000]
    # a version without sites is its own global model
    whole = _download(client, 2, tmp_path, "v2-global.ply", format="ply", surface="global")
    assert whole.read_bytes() == full.read_bytes()
    assert client.get("/versions/2/export", params={"format": "ply", "surface": "sites"}).status_code == 422
    assert client.get("/versions/2/export", params={"format": "site", "lat": 10.0, "lon": 40.0, "radius_km": 0.02,
                                                    "surface": "global"}).status_code == 422


def test_site_product_reads_with_pds4_tools(client, populated, tmp_path):
    params = {"format": "site", "lat": 10.0, "lon": 40.0, "radius_km": 0.02}
    response = client.get("/versions/2/export", params=params)
    assert response.status_code == 200 and response.headers["content-type"] == "application/zip"
    with zipfile.ZipFile(io.BytesIO(response.content)) as archive:
        names = archive.namelist()
        archive.extractall(tmp_path)
    label = tmp_path / next(n for n in names if n.endswith(".xml"))
    assert {Path(n).suffix for n in names} == {".xml", ".dat", ".png"}
    label_schema().validate(label.read_text())
    structures = pds4_tools.read(str(label), quiet=True)
    height = np.ma.filled(structures["height"].as_masked().data.astype(float), np.nan)
    albedo = np.ma.filled(structures["albedo"].as_masked().data.astype(float), np.nan)
    assert height.shape == albedo.shape and height.shape[0] >= 3
    assert np.isfinite(height).all()
    # the site frame sits on the surface: the centre node's height is 0 to rounding (m)
    centre = height.shape[0] // 2
    assert abs(height[centre, centre]) < 1e-6
    assert 0.034 - 1e-3 < np.nanmin(albedo) and np.nanmax(albedo) < 0.054 + 1e-3
    text = label.read_text()
    assert "IAU_BENNU" in text and "BENNU" in text
    # the same request is served from the cache: the same bytes
    assert client.get("/versions/2/export", params=params).content == response.content


def test_cli_export_and_release(populated, tmp_path, monkeypatch):
    from service.settings import get_settings

    settings = populated.app.state.settings
    monkeypatch.setenv("PWM_DATA_DIR", str(settings.data_dir))
    monkeypatch.setenv("PWM_DATABASE_URL", settings.database_url)
    get_settings.cache_clear()
    runner = CliRunner()
    try:
        out = tmp_path / "v2.icq"
        result = runner.invoke(cli, ["export", "2", "--format", "icq", "--faces", "1200",
                                     "--out", str(out)])
        assert result.exit_code == 0, result.output
        assert read_icq(out).shape == (6, 11, 11, 3)
        result = runner.invoke(cli, ["export", "2", "--format", "site", "--out", str(out)])
        assert result.exit_code != 0
        tif = tmp_path / "v2.tif"
        result = runner.invoke(cli, ["export", "2", "--format", "geotiff", "--lat", "10", "--lon", "40",
                                     "--radius-km", "0.02", "--out", str(tif)])
        assert result.exit_code == 0, result.output
        with rasterio.open(tif) as raster:
            assert raster.crs.to_dict()["proj"] == "ortho" and raster.count == 5
        result = runner.invoke(cli, ["export", "2", "--format", "obj", "--radius-km", "0.02",
                                     "--out", str(tmp_path / "v2.obj")])
        assert result.exit_code != 0 and "--radius-km" in result.output
        las = tmp_path / "v2.las"
        assert runner.invoke(cli, ["export", "2", "--format", "las", "--out", str(las)]).exit_code == 0
        result = runner.invoke(cli, ["import", str(las)])
        assert result.exit_code == 1 and "LAS point cloud" in result.output
        result = runner.invoke(cli, ["release", "2", "--tag", "cli-1"])
        assert result.exit_code == 0, result.output
        result = runner.invoke(cli, ["release", "2", "--tag", "cli-2"])
        assert result.exit_code == 1 and "cannot be changed" in result.output
    finally:
        get_settings.cache_clear()


SITE = {"lat": 10.0, "lon": 40.0, "radius_km": 0.02}


def test_site_as_geotiff_and_isis_cube(client, populated, tmp_path):
    response = client.get("/versions/2/export", params={"format": "site", **SITE})
    with zipfile.ZipFile(io.BytesIO(response.content)) as archive:
        archive.extractall(tmp_path / "site")
    label = next((tmp_path / "site").glob("*.xml"))
    product = pds4_tools.read(str(label), quiet=True)
    height = np.ma.filled(product["height"].as_masked().data.astype(float), np.nan)
    assert np.isfinite(height).sum() > 9

    tif = _download(client, 2, tmp_path, "v2.tif", format="geotiff", **SITE)
    cub = _download(client, 2, tmp_path, "v2.cub", format="isis", **SITE)
    with rasterio.open(tif) as raster:
        tags = raster.tags()
        assert raster.units[0] == "m" and raster.units[2] == "deg" and raster.units[4] == "m"
    assert tags["PWM_VERSION"] == "2" and tags["BODY_FRAME"] == "IAU_BENNU" and tags["BODY"] == "BENNU"
    # the kernels' triaxial radii; the projection's sphere has their mean
    radii_km = np.array(tags["BODY_RADII_KM"].split(), dtype=float)
    assert len(radii_km) == 3 and 0.24 < radii_km.mean() < 0.29 and np.ptp(radii_km) > 0.01
    # centred on the site frame's z (the regional normal, some degrees off the site's radial
    # line on Bennu), east along its x
    lat, lon = unit_to_latlon(np.array(tags["SITE_FRAME_AXES"].split(), dtype=float)[6:])
    assert abs(lat - SITE["lat"]) < 30.0
    for path, driver, tolerance_m in ((tif, "GTiff", 1e-9), (cub, "ISIS3", 1e-3)):
        with rasterio.open(path) as raster:
            assert raster.driver == driver and raster.count == 5
            assert raster.descriptions == ("height", "albedo", "slope", "roughness", "height_sigma")
            sigma = raster.read(5, masked=True)
            assert 0.02 <= sigma.min() <= sigma.max() <= 0.04  # m
            crs = raster.crs.to_dict()
            assert crs["proj"] == "ortho" and abs(crs["lat_0"] - lat) < 1e-9
            assert abs((crs["lon_0"] - lon + 180.0) % 360.0 - 180.0) < 1e-9
            assert abs(crs["R"] - radii_km.mean() * 1e3) < 1e-6
            assert raster.transform.a == -raster.transform.e > 0
            layers = raster.read(masked=True)
            # the same heights as the PDS4 product, north up in both, no data at the same nodes
            heights = np.ma.filled(layers[0].astype(float), np.nan)
            np.testing.assert_array_equal(np.isnan(heights), np.isnan(height))
            assert np.nanmax(np.abs(heights - height)) < tolerance_m
            albedo = np.ma.filled(layers[1].astype(float), np.nan)
            assert 0.034 - 1e-3 < np.nanmin(albedo) and np.nanmax(albedo) < 0.054 + 1e-3
    text = cub.read_bytes()[:65536].decode("ascii", errors="replace")
    assert "Group = BandBin" in text and "BODY_FRAME" in text and "TargetName         = BENNU" in text
    assert client.get("/versions/2/export", params={"format": "geotiff"}).status_code == 422
    assert client.get("/versions/2/export", params={"format": "las", **SITE}).status_code == 422


def test_las_of_the_vertices(client, populated, tmp_path):
    path = _download(client, 2, tmp_path, "v2.las", format="las")
    cloud = laspy.read(path)
    mesh = populated.refined
    points_m = np.column_stack([cloud.x, cloud.y, cloud.z])
    assert np.abs(points_m - mesh.vertices * 1e3).max() < 1e-3
    np.testing.assert_allclose(cloud.albedo, mesh.albedo, rtol=1e-6)
    assert cloud.header.system_identifier.startswith("pwm v2 IAU_BENNU")
    wkt = next(v for v in cloud.header.vlrs if v.record_id == 2112).record_data_bytes().decode()
    assert wkt.startswith('GEOCCS["BENNU body-fixed (IAU_BENNU)"')
    with session_scope(populated.app.state.sessions) as session, \
            pytest.raises(ValueError, match="LAS point cloud"):
        import_model(session, data_dir=populated.data_dir, path=path)


@pytest.mark.parametrize("fmt", ["obj", "ply", "dsk", "icq"])
def test_every_mesh_export_imports_back(client, populated, tmp_path, fmt):
    exported = _download(client, 2, tmp_path, f"v2.{fmt}", format=fmt)
    with session_scope(populated.app.state.sessions) as session:
        version = import_model(session, data_dir=populated.data_dir, path=exported)
        back = version_mesh(populated.data_dir, version)
    mesh = icq_to_mesh(read_icq(exported)) if fmt == "icq" else populated.refined
    np.testing.assert_array_equal(back.faces, mesh.faces)
    # OBJ prints 9 decimals (1e-9 km); the others keep the doubles
    assert np.abs(back.vertices - mesh.vertices).max() <= (5e-10 if fmt == "obj" else 0.0)
    if fmt in ("obj", "ply"):  # the albedo round trip: PLY's float32, OBJ's stretched colour
        np.testing.assert_allclose(back.albedo, mesh.albedo, rtol=2e-7, atol=1e-8)


def _segments(path: Path) -> int:
    handle = sp.dasopr(str(path))
    try:
        count, descriptor, found = 0, sp.dlabfs(handle), True
        while found:
            count += 1
            with sp.no_found_check():
                descriptor, found = sp.dlafns(handle, descriptor)
    finally:
        sp.dascls(handle)
    return count


def test_a_version_too_big_for_one_file_is_stored_and_exported_in_tiles(client, populated, tmp_path,
                                                                         monkeypatch):
    from service.settings import get_settings

    mesh = populated.refined
    most = len(mesh.faces) // 6
    with session_scope(populated.app.state.sessions) as session:
        version = publish_version(session, data_dir=populated.data_dir, mesh=mesh, kind=ModelKind.REFINED,
                                  tile_faces=most)
        number = version.version
        assert "tiles" in version.artifacts and "ply" not in version.artifacts
        # stored in tiles, read back whole: the very mesh
        back = version_mesh(populated.data_dir, version)
    for name in ("vertices", "faces", "albedo", "sigma"):
        np.testing.assert_array_equal(getattr(back, name), getattr(mesh, name))

    listed = client.get(f"/versions/{number}/tiles").json()
    tiles = listed["tiles"]
    assert listed["faces"] == len(mesh.faces) and len(tiles) >= 6
    assert sum(t["faces"] for t in tiles) == len(mesh.faces) and max(t["faces"] for t in tiles) <= most
    assert client.get("/versions/2/tiles").status_code == 404  # stored whole

    # the whole is too big for one PLY: refused, saying how to get it
    refused = client.get(f"/versions/{number}/export", params={"format": "ply"})
    assert refused.status_code == 422 and "tile" in refused.json()["detail"]
    assert client.get(f"/versions/{number}/export", params={"format": "ply", "tile": "t99999"}).status_code == 422
    assert client.get(f"/versions/{number}/export", params={"format": "ply", "tile": "../x"}).status_code == 422
    # each tile as a PLY: its faces, over vertices the whole's at the same place, so that the
    # tiles together are the mesh, each face once, meeting vertex on vertex
    index = {tuple(v): i for i, v in enumerate(mesh.vertices)}
    faces = []
    for tile in tiles:
        part = read_shape_model(_download(client, number, tmp_path, f"{tile['key']}.ply", format="ply",
                                          tile=tile["key"]))
        assert len(part.faces) == tile["faces"]
        box = np.array([tile["box_min_km"], tile["box_max_km"]])
        assert (part.vertices >= box[0]).all() and (part.vertices <= box[1]).all()
        ids = np.array([index[tuple(v)] for v in part.vertices])
        faces.append(ids[part.faces])
    joined = np.concatenate(faces)
    assert len(joined) == len(mesh.faces)
    assert {tuple(f) for f in joined} == {tuple(f) for f in mesh.faces}
    # decimated, the whole is one file
    small = read_obj(_download(client, number, tmp_path, "small.obj", format="obj", faces=2000))
    assert abs(len(small.faces) - 2000) <= 100

    # the DSK: a segment per tile, which SPICE intercepts as the mesh
    dsk = _download(client, number, tmp_path, "tiled.bds", format="dsk")
    assert _segments(dsk) == len(tiles)
    _intercepts_agree(dsk, mesh)

    # the CLI writes every tile and their index
    settings = populated.app.state.settings
    monkeypatch.setenv("PWM_DATA_DIR", str(settings.data_dir))
    monkeypatch.setenv("PWM_DATABASE_URL", settings.database_url)
    get_settings.cache_clear()
    try:
        out = tmp_path / "tiles"
        result = CliRunner().invoke(cli, ["export", str(number), "--format", "obj", "--tile", "all", "--out", str(out)])
        assert result.exit_code == 0, result.output
        written = json.loads((out / "tiles.json").read_text())
        assert [t["key"] for t in written["tiles"]] == [t["key"] for t in tiles]
        assert sum(len(read_obj(out / t["file"]).faces) for t in written["tiles"]) == len(mesh.faces)
        result = CliRunner().invoke(cli, ["export", "2", "--format", "obj", "--tile", "all", "--out", str(out)])
        assert result.exit_code == 1 and "stored whole" in result.output
    finally:
        get_settings.cache_clear()
