"""The lidar through the API: a version's residuals (overall, per track, the map), the
catalog's tracks with their strip corrections, and a downlink's lidar counts; on a small SQLite
catalog with lidar (tests/api/lidar_catalog.py)."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest
from fastapi.testclient import TestClient
from typer.testing import CliRunner

from service.api import create_app
from service.cli import app as pwm
from service.settings import Settings, get_settings
from tests.api.lidar_catalog import OFFSET_KM, add_lidar_catalog


@pytest.fixture
def client(tmp_path: Path) -> Iterator[TestClient]:
    app = create_app(Settings(data_dir=tmp_path, database_url=f"sqlite:///{tmp_path / 'catalog.sqlite'}"))
    add_lidar_catalog(app.state.sessions, tmp_path)
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
    assert (adjusted["crossovers"], adjusted["crossover_rms_km"]) == (3, 2e-4)
    assert plain["correction"] is None and plain["residual_version"] is None and plain["crossovers"] is None
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
