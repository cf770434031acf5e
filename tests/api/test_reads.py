"""Open reads: versions with lineage and downloads, maplets near a point with their image sets
and revisions, images with geometry, downlinks and jobs; pagination and filters."""

from __future__ import annotations

import hashlib

import numpy as np
import pytest
from sqlalchemy import func, select

from service.rows import Coverage, Image, ImageStatus, Maplet


def test_versions_list_detail_and_lineage(client, populated):
    page = client.get("/versions").json()
    assert page["total"] == 2 and [v["version"] for v in page["items"]] == [2, 1]
    assert client.get("/versions", params={"kind": "start"}).json()["items"][0]["version"] == 1
    assert client.get("/versions", params={"released": True}).json()["total"] == 0
    second = client.get("/versions", params={"limit": 1, "offset": 1}).json()
    assert [v["version"] for v in second["items"]] == [1] and second["total"] == 2

    latest = client.get("/versions/latest").json()
    assert latest["version"] == 2 and latest["parent"] == 1
    assert latest["faces"] == len(populated.refined.faces)
    assert latest["statistics"]["note"] == "refined for the API tests"
    assert latest["lineage"]["ancestors"] == [1] and latest["lineage"]["maplet_revisions"] == 2
    assert [d["id"] for d in latest["lineage"]["downlinks"]] == [populated.downlink_id]
    assert client.get("/versions/1").json()["lineage"]["children"] == [2]
    assert client.get("/versions/9").status_code == 404
    assert client.get("/versions/released").status_code == 404


def test_artifact_download_is_the_published_file(client, populated):
    detail = client.get("/versions/2").json()
    response = client.get("/versions/2/artifacts/ply")
    assert response.status_code == 200
    assert hashlib.sha256(response.content).hexdigest() == detail["artifacts"]["ply"]["sha256"]
    assert client.get("/versions/2/artifacts/grid").status_code == 404


@pytest.mark.parametrize("ordering", ["near", "listing"])
def test_maplets_near_a_point_and_their_detail(client, populated, ordering):
    with populated.app.state.sessions() as session:
        maplet = session.get(Maplet, populated.maplet_id)
        lat, lon = maplet.center_lat_deg, maplet.center_lon_deg
        seen = session.scalar(select(func.count()).where(Coverage.maplet_id == maplet.id,
                                                         Coverage.visible_fraction > 0))
        count = session.scalar(select(func.count(Maplet.id)))
    params = {"lat": lat, "lon": lon, "radius_km": 0.0} if ordering == "near" else {}
    page = client.get("/maplets", params={**params, "limit": 2}).json()
    if ordering == "near":
        assert page["items"][0]["id"] == populated.maplet_id
        assert page["items"][0]["distance_km"] == 0.0
    else:
        assert page["total"] == count and len(page["items"]) == 2

    detail = client.get(f"/maplets/{populated.maplet_id}").json()
    assert detail["maplet"]["current_revision"] == 2
    assert [r["revision"] for r in detail["revisions"]] == [1, 2]
    assert [r["current"] for r in detail["revisions"]] == [False, True]
    assert detail["revisions"][1]["statistics"]["residual_rms"] == pytest.approx(0.01)
    weights = [i["weight"] for i in detail["images"]]
    assert len(weights) == seen == detail["coverage"]["image_count"] > 0
    assert weights == sorted(weights, reverse=True)
    assert client.get("/maplets/999999").status_code == 404


def test_images_with_geometry_and_filters(client, populated):
    with populated.app.state.sessions() as session:
        accepted = session.scalar(select(func.count()).where(Image.status == ImageStatus.ACCEPTED))
        first, last = session.execute(select(func.min(Image.start_utc),
                                             func.max(Image.start_utc))).one()
    page = client.get("/images", params={"status": "accepted"}).json()
    assert page["total"] == accepted > 0
    image = page["items"][0]
    geometry = image["geometry"]
    assert geometry["body_frame"] == "IAU_BENNU"
    assert np.linalg.norm(geometry["camera_km"]) == pytest.approx(geometry["range_km"])
    assert client.get("/images", params={"status": "rejected"}).json()["total"] == 0
    later = client.get("/images", params={"start_after": last.isoformat()}).json()
    assert later["total"] == 1
    earlier = client.get("/images", params={"start_before": last.isoformat(),
                                            "downlink_id": populated.downlink_id}).json()
    assert earlier["total"] == accepted - 1
    assert first.isoformat() <= image["start_utc"].replace("Z", "+00:00")

    detail = client.get(f"/images/{image['id']}").json()
    assert detail["lidvid"] == image["lidvid"] and len(detail["maplets"]) > 0
    assert client.get("/images", params={"start_after": "2019-01-01T00:00:00"}).status_code == 422


def test_downlinks_and_jobs(client, populated):
    downlinks = client.get("/downlinks").json()
    assert downlinks["total"] == 1
    downlink = downlinks["items"][0]
    assert downlink["kernels"] > 0 and downlink["images"]["accepted"] > 0
    assert client.get(f"/downlinks/{downlink['id']}").json() == downlink
    assert client.get("/downlinks", params={"status": "failed"}).json()["total"] == 0

    assert client.get("/jobs").json()["total"] == 3
    refines = client.get("/jobs", params={"kind": "refine", "status": "queued"}).json()
    assert sorted(j["key"] for j in refines["items"]) == ["refine:b", "refine:c"]
    one = client.get("/jobs", params={"key": "ingest:a"}).json()["items"][0]
    assert client.get(f"/jobs/{one['id']}").json()["kind"] == "ingest"
    assert client.get("/jobs/999999").status_code == 404


@pytest.mark.parametrize("params", [{"limit": 0}, {"limit": 1001}, {"offset": -1},
                                    {"offset": 10**12}, {"limit": "many"}])
def test_pagination_bounds(client, params):
    response = client.get("/jobs", params=params)
    assert response.status_code == 422
    assert response.json()["detail"][0]["loc"][-1] in params


def test_openapi_is_published(client):
    schema = client.get("/openapi.json").json()
    assert {"/versions", "/versions/{ref}/export", "/maplets", "/images", "/downlinks", "/jobs",
            "/ingests"} <= set(schema["paths"])
    assert schema["components"]["securitySchemes"]["HTTPBearer"]["scheme"] == "bearer"


def test_diff_between_versions(client):
    diff = client.get("/diffs/1/2").json()
    assert (diff["old"], diff["new"]) == (1, 2) and diff["png"] is None
    assert diff["vertices_compared"] > 0 and diff["vertices_total"] > diff["vertices_compared"] / 2
    # the refinement subdivides the same surface: a flat facet's midpoints do not move
    assert diff["max_abs_m"] < 1.0
    assert client.get("/diffs/1/2", params={"threshold_m": 0}).status_code == 422
    assert client.get("/diffs/1/99").status_code == 404
    png = client.get("/diffs/1/latest/map.png")
    assert png.status_code == 200 and png.content[:8] == b"\x89PNG\r\n\x1a\n"
    assert client.get("/diffs/1/2/map.png").content == png.content  # made once
