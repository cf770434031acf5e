"""The lidar through the API: a version's residuals (overall, per track, the map), the
catalog's tracks with their strip corrections, and a downlink's lidar counts; on a small SQLite
catalog whose statistics come from pwm.lidar.model.residual_summary itself."""

from __future__ import annotations

from collections.abc import Iterator
from datetime import UTC, datetime
from pathlib import Path

import numpy as np
import pytest
import trimesh
from fastapi.testclient import TestClient
from typer.testing import CliRunner

from pwm.lidar.model import residual_summary
from pwm.lidar.shots import Shots
from pwm.mesh import Mesh
from service.api import create_app
from service.cli import app as pwm
from service.db import session_scope
from service.rows import Acceptance, Downlink, LidarProduct, LidarTrack, ModelKind
from service.settings import Settings, get_settings
from service.versions import publish_version

RADIUS_KM = 0.25
OFFSET_KM = 0.002  # every spot 2 m outside the sphere


def _shots(n: int) -> Shots:
    """n shots straight down from 1 km above a 250 m sphere, ranging OFFSET_KM short."""
    rng = np.random.default_rng(3)
    down = rng.normal(size=(n, 3))
    down /= np.linalg.norm(down, axis=1, keepdims=True)
    return Shots(frame="IAU_BENNU", et=np.arange(n, dtype=float), origin_km=down * (RADIUS_KM + 1.0),
                 direction=-down, range_km=np.full(n, 1.0 - OFFSET_KM), sigma_km=np.full(n, 1e-4),
                 invalid=np.zeros(n, dtype=np.int8))


@pytest.fixture
def client(tmp_path: Path) -> Iterator[TestClient]:
    app = create_app(Settings(data_dir=tmp_path, database_url=f"sqlite:///{tmp_path / 'catalog.sqlite'}"))
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=RADIUS_KM)
    with session_scope(app.state.sessions) as session:
        downlink = Downlink(name="dl1", path="/downlinks/dl1")
        session.add(downlink)
        session.flush()
        product = LidarProduct(lidvid="urn:lidar:a::1.0", lid="urn:lidar:a", vid="1.0", label_path="a.xml",
                               data_path="a.dat", sha256="0" * 64, size_bytes=10, downlink_id=downlink.id,
                               status=Acceptance.ACCEPTED, shots=300, valid_shots=200, invalid_shots={})
        box = dict(min_x_km=-1.0, min_y_km=-1.0, min_z_km=-1.0, max_x_km=1.0, max_y_km=1.0, max_z_km=1.0)
        adjusted = LidarTrack(product=product, track=0, start_et=0.0, stop_et=99.0, shots=100, cone_axis_x=1.0,
                              cone_axis_y=0.0, cone_axis_z=0.0, cone_half_angle_rad=0.5, axis_lat_deg=0.0,
                              axis_lon_deg=0.0, rotation_x_rad=1e-4, rotation_y_rad=0.0, rotation_z_rad=0.0,
                              translation_x_km=0.003, translation_y_km=-0.001, translation_z_km=0.0,
                              about_x_km=0.25, about_y_km=0.0, about_z_km=0.0,
                              correction_sigma=[1e-5, 1e-5, None, 1e-4, 1e-4, 1e-4],
                              adjusted_at=datetime(2026, 12, 6, tzinfo=UTC), **box)
        plain = LidarTrack(product=product, track=1, start_et=100.0, stop_et=199.0, shots=100, cone_axis_x=0.0,
                           cone_axis_y=1.0, cone_axis_z=0.0, cone_half_angle_rad=0.5, axis_lat_deg=0.0,
                           axis_lon_deg=90.0, **box)
        session.add(product)
        session.flush()
        track = np.repeat([adjusted.id, plain.id], 100)
        figures = residual_summary(_shots(200), Mesh(sphere.vertices, sphere.faces), track)
        adjusted.residual_version, adjusted.residual_rms_km = 1, figures["tracks"][str(adjusted.id)]["rms_km"]
        publish_version(session, data_dir=tmp_path, mesh=Mesh(sphere.vertices, sphere.faces),
                        kind=ModelKind.LIDAR, statistics={"lidar": figures | {"products": 1, "usable_shots": 200}},
                        downlinks=[downlink])
        publish_version(session, data_dir=tmp_path, mesh=Mesh(sphere.vertices, sphere.faces),
                        kind=ModelKind.IMPORTED)
    with TestClient(app) as test_client:
        yield test_client


def test_the_api_serves_the_lidar(client: TestClient) -> None:
    residuals = client.get("/versions/1/lidar")
    assert residuals.status_code == 200, residuals.text
    body = residuals.json()
    # every spot 2 m out: the icosphere's facets lie inside the sphere, so a little more
    assert body["version"] == 1 and body["shots"] == body["measured"] == 200 and body["missed"] == 0
    assert OFFSET_KM < body["mean_km"] < OFFSET_KM + 0.0005 and body["rms_km"] >= body["mean_km"]
    assert {figures["shots"] for figures in body["tracks"].values()} == {100}
    assert (body["map"]["lon_cells"], body["map"]["lat_cells"]) == (36, 18)
    cells = [c for row in body["map"]["rms_km"] for c in row if c is not None]
    assert len(body["map"]["rms_km"]) == 18 and cells and all(OFFSET_KM < c < OFFSET_KM + 0.0005 for c in cells)
    assert client.get("/versions/1").json()["kind"] == "lidar"

    missing = client.get("/versions/2/lidar")
    assert missing.status_code == 404 and "not checked against the lidar" in missing.json()["detail"]

    tracks = client.get("/lidar/tracks").json()
    assert tracks["total"] == 2
    adjusted, plain = tracks["items"]
    assert adjusted["product"] == "urn:lidar:a::1.0" and adjusted["cone_half_angle_deg"] == pytest.approx(28.6479)
    assert adjusted["correction"]["translation_km"] == [0.003, -0.001, 0.0]
    assert adjusted["correction"]["sigma"][2] is None
    assert adjusted["residual_version"] == 1 and adjusted["residual_rms_km"] == pytest.approx(
        body["tracks"][str(adjusted["id"])]["rms_km"])
    assert plain["correction"] is None and plain["residual_version"] is None
    assert client.get("/lidar/tracks", params={"offset": 1}).json()["items"][0]["id"] == plain["id"]

    downlink = client.get("/downlinks").json()["items"][0]
    assert (downlink["lidar"], downlink["lidar_shots"], downlink["lidar_valid_shots"]) == (
        {"accepted": 1}, 300, 200)


def test_pwm_version_show_prints_the_lidar_in_words(client: TestClient, tmp_path: Path,
                                                     monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("PWM_DATA_DIR", str(tmp_path))
    monkeypatch.setenv("PWM_DATABASE_URL", f"sqlite:///{tmp_path / 'catalog.sqlite'}")
    get_settings.cache_clear()
    try:
        shown = CliRunner().invoke(pwm, ["version", "show", "1", "--lidar"])
        refused = CliRunner().invoke(pwm, ["version", "show", "2", "--lidar"])
    finally:
        get_settings.cache_clear()
    assert shown.exit_code == 0, shown.output
    lines = shown.stdout.splitlines()
    assert lines[0] == "version 1 (lidar) against 1 lidar products (200 usable shots):"
    assert lines[1].startswith("200 shots, 200 measured, 0 without a surface near their spot; mean 2.")
    assert sum(line.startswith("  track ") for line in lines) == 2
    # the map north up: 18 rows of 36 cells, the top one from +90 deg
    rows = [line for line in lines if line.endswith("|") and "|" in line[:12]]
    assert len(rows) == 18 and rows[0].startswith("   +90.0 |") and all(len(r.split("|")[1]) == 36 for r in rows)
    assert any(c != " " for r in rows for c in r.split("|")[1])
    assert refused.exit_code == 1 and "not checked against the lidar" in refused.output
