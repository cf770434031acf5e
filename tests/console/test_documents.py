"""The console's documents without a browser: the binary layout, the 3D view's mesh with its
colours (change since the parent against a known displacement), decimation above the limit,
and bad requests refused with a reason."""

from __future__ import annotations

import numpy as np
import pytest

from service.console.documents import MESH_FACES, UNKNOWN_GREY, MeshRequest, mesh_document, pack, unpack
from service.db import session_scope
from service.versions import get_version
from tests.console.conftest import RAISE_M


def test_pack_round_trip_and_refusals():
    arrays = [("a", np.arange(5, dtype=np.float32)), ("b", np.array([[1, 2], [3, 4]], np.uint32)),
              ("c", np.array([1, 0, 1], np.uint8))]
    header, back = unpack(pack({"kind": "test"}, arrays))
    assert header["kind"] == "test" and [a["name"] for a in header["arrays"]] == ["a", "b", "c"]
    for name, array in arrays:
        np.testing.assert_array_equal(back[name], array)
        assert header["arrays"][[n for n, _ in arrays].index(name)]["offset"] % 4 == 0
    with pytest.raises(TypeError, match="float64"):
        pack({}, [("x", np.zeros(3))])
    with pytest.raises(ValueError, match="magic"):
        unpack(b"JUNK" + bytes(8))


def test_mesh_document_of_a_refined_version(console):
    response = console.api.get("/console/api/versions/2/mesh")
    assert response.status_code == 200
    assert response.headers["content-type"] == "application/vnd.pwm.console"
    assert "immutable" in response.headers["cache-control"]
    assert console.api.get("/console/api/versions/latest/mesh").headers["cache-control"] == "no-cache"
    header, arrays = unpack(response.content)
    version = console.api.get("/versions/2").json()
    assert header["faces"] == header["faces_full"] == version["faces"] <= MESH_FACES
    assert arrays["vertices"].shape == (version["vertices"], 3)
    assert arrays["faces"].shape == (version["faces"], 3)
    assert arrays["faces"].max() == version["vertices"] - 1
    normals = arrays["normals"].astype(float) / 127
    np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1.0, atol=0.02)
    for name in ("albedo", "height", "slope", "change", "sigma"):
        assert arrays[f"colour_{name}"].shape == (version["vertices"], 3)
    colours = header["colours"]
    # the 1-3 cm sigma of the northern half, in m (percentiles of it)
    assert colours["sigma"]["unit"] == "m" and 0.01 <= colours["sigma"]["min"] < colours["sigma"]["max"] <= 0.03
    # the refinement stands RAISE_M outside its parent everywhere: the change map's range
    assert colours["change"]["max"] == pytest.approx(RAISE_M, abs=0.01)
    assert colours["change"]["min"] == -colours["change"]["max"]
    assert 0.034 <= colours["albedo"]["min"] < colours["albedo"]["max"] <= 0.054
    assert colours["slope"]["unit"] == "deg" and 0 <= colours["slope"]["min"]
    assert arrays["colour_albedo"].std(axis=0).max() > 10  # coloured, not one grey
    # what the colour bars draw: the colour maps' own samples, ends first and last
    assert colours["albedo"]["colormap"] == "viridis" and colours["change"]["colormap"] == "RdBu_r"
    assert colours["albedo"]["stops"][0] == [68, 1, 84] and colours["albedo"]["stops"][-1] == [253, 231, 37]
    # the body's size for the view's scale: the mesh's bounding box (km)
    vertices = arrays["vertices"].astype(float)
    np.testing.assert_allclose(header["extent_km"]["sides"], np.ptp(vertices, axis=0), rtol=1e-5)
    # the start has no parent (no change) and no albedo in its OBJ: grey
    header1, arrays1 = unpack(console.api.get("/console/api/versions/1/mesh").content)
    assert header1["parent"] is None and header1["colours"]["change"]["min"] is None
    assert header1["colours"]["sigma"]["min"] is None  # nothing refined, no sigma
    assert (arrays1["colour_change"] == arrays1["colour_change"][0]).all()


def test_mesh_document_is_decimated_above_the_limit(console, tmp_path):
    settings = console.app.state.settings
    with session_scope(console.app.state.sessions) as session:
        request = MeshRequest.of(get_version(session, 2))
    faces = console.api.get("/versions/2").json()["faces"] // 2
    path = mesh_document(settings.data_dir, request, cache_bytes=settings.export_cache_bytes,
                         faces=faces)
    header, arrays = unpack(path.read_bytes())
    assert header["faces_full"] == 2 * faces and 0.9 * faces <= header["faces"] <= faces
    assert len(arrays["normals"]) == len(arrays["vertices"]) == header["vertices"]
    assert len(arrays["faces"]) == header["faces"] and header["colours"]["albedo"]["min"] > 0


@pytest.mark.parametrize(("params", "status"), [
    ({"lat": 0, "lon": 0, "radius_km": 2}, 422),  # over the console's 1 km
    ({"lat": 0, "lon": 0}, 422),
    ({"lat": 0, "lon": 0, "radius_km": 0.01, "max_slope_deg": 90}, 422),
])
def test_bad_site_requests_are_refused(console, params, status):
    response = console.api.get("/console/api/versions/2/site", params=params)
    assert response.status_code == status and response.json()["detail"]


def test_unknown_version_is_404(console):
    response = console.api.get("/console/api/versions/99/mesh")
    assert response.status_code == 404 and "99" in response.json()["detail"]


def test_coverage_of_a_site_is_the_maplets_near_it(console):
    everything = console.api.get("/console/api/coverage").json()
    first = everything[0]
    near = {"lat": first["center_lat_deg"], "lon": first["center_lon_deg"], "radius_km": 0.001}
    site = console.api.get("/console/api/coverage", params=near).json()
    listed = console.api.get("/maplets", params={**near, "limit": 1000}).json()["items"]
    assert sorted(m["id"] for m in site) == sorted(m["id"] for m in listed)
    assert 0 < len(site) < len(everything) and first in site
    assert console.api.get("/console/api/coverage", params={"lat": 1}).status_code == 422


def test_site_document_says_where_refined_data_lies_and_where_north_is(console):
    # the refined version was fused from one maplet's revision: a site twice its side about its
    # centre holds it over a quarter of its square; the start version holds no refined data
    maplet = next(m for m in console.api.get("/console/api/coverage").json()
                  if m["current_revision"] is not None)
    site = {"lat": maplet["center_lat_deg"], "lon": maplet["center_lon_deg"],
            "radius_km": maplet["size_km"]}
    header, arrays = unpack(console.api.get("/console/api/versions/2/site", params=site).content)
    fine = arrays["fine"]
    assert fine.shape == (header["ny"], header["nx"]) and fine.dtype == np.uint8
    assert header["fine"]["maplets"] == [maplet["name"]]
    assert header["fine"]["fraction"] == pytest.approx(fine.mean()) == pytest.approx(0.25, abs=0.04)
    assert fine[header["ny"] // 2, header["nx"] // 2] == 1 and fine[0, 0] == 0
    start, start_arrays = unpack(console.api.get("/console/api/versions/1/site", params=site).content)
    assert start["fine"] == {"level": None, "maplets": [], "gsd_m": None, "fraction": 0.0}
    assert not start_arrays["fine"].any()
    # the refined version's 1-sigma heights (1-3 cm north of the equator, the site's side); none
    # in the start
    sigma = arrays["sigma"][np.isfinite(arrays["sigma"])]
    assert sigma.size > 0.9 * arrays["sigma"].size and 0.01 <= sigma.min() <= sigma.max() <= 0.03
    assert np.isnan(start_arrays["sigma"]).all()
    # north: the body's +Z axis in the site frame's x-y plane; near 8 deg latitude with x east,
    # nearly the frame's +y
    rotation = np.array(header["frame"]["rotation"])
    z_local = rotation @ np.array([0.0, 0.0, 1.0])
    np.testing.assert_allclose(header["north"], z_local[:2] / np.linalg.norm(z_local[:2]), atol=1e-9)
    assert header["north"][1] > 0.9


def test_coverage_outlines_are_the_maplets_squares(console):
    # the outline's sides, on the sphere of the maplet's radius, are the maplet's side
    for maplet in console.api.get("/console/api/coverage").json()[:5]:
        lat, lon = np.radians(np.array(maplet["outline"])).T
        points = maplet["radius_km"] * np.stack(
            [np.cos(lat) * np.cos(lon), np.cos(lat) * np.sin(lon), np.sin(lat)], axis=1)
        sides = np.linalg.norm(points - np.roll(points, 1, axis=0), axis=1)
        np.testing.assert_allclose(sides, maplet["size_km"], rtol=0.02)


def test_a_version_in_tiles_is_drawn_decimated_and_a_tile_at_full_resolution(console, tiled_version):
    whole_header, whole = unpack(console.api.get(f"/console/api/versions/{tiled_version}/mesh").content)
    listed = console.api.get(f"/versions/{tiled_version}/tiles").json()["tiles"]
    assert [t["key"] for t in whole_header["tiles"]] == [t["key"] for t in listed]
    # each drawn face's tile: the one whose box holds the face (decimated or not, it lies on it)
    owner = whole["face_tile"]
    assert owner.shape == (whole_header["faces"],) and owner.max() == len(listed) - 1
    centres = whole["vertices"][whole["faces"]].astype(float).mean(axis=1)
    boxes = np.array([[t["box_min_km"], t["box_max_km"]] for t in listed])
    inside = ((centres >= boxes[owner, 0] - 1e-6) & (centres <= boxes[owner, 1] + 1e-6)).all(axis=1)
    assert inside.mean() > 0.99
    # a tile at full resolution, coloured on the whole's ranges: a vertex's albedo, height and
    # sigma colours are the whole's at the same place (the whole is small enough to be drawn full)
    assert whole_header["faces"] == whole_header["faces_full"]
    key = listed[1]["key"]
    response = console.api.get(f"/console/api/versions/{tiled_version}/tiles/{key}/mesh")
    assert response.status_code == 200 and "immutable" in response.headers["cache-control"]
    header, tile = unpack(response.content)
    assert header["tile"] == key and header["faces"] == listed[1]["faces"]
    for name in ("albedo", "height", "sigma"):
        assert header["colours"][name]["min"] == whole_header["colours"][name]["min"]
        assert header["colours"][name]["max"] == whole_header["colours"][name]["max"]
    index = {tuple(v): i for i, v in enumerate(whole["vertices"])}
    same = np.array([index[tuple(v)] for v in tile["vertices"]])
    for name in ("albedo", "height", "sigma"):
        np.testing.assert_array_equal(tile[f"colour_{name}"], whole[f"colour_{name}"][same])
    assert (tile["colour_change"] == UNKNOWN_GREY).all()  # not coloured on a tile: grey
    assert console.api.get(f"/console/api/versions/{tiled_version}/tiles/t99999/mesh").status_code == 404
    assert console.api.get(f"/console/api/versions/{tiled_version}/tiles/..%2Fx/mesh").status_code in (404, 422)
    assert console.api.get("/console/api/versions/2/tiles/t00000/mesh").status_code == 404
