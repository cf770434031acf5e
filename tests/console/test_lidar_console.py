"""The lidar page in headless Chromium: a version's RMS map with each track's cone drawn over
it in the colour of its residual, a colour bar in metres, axes in degrees, a scale bar and a
north arrow; the table holds the API's figures; a version not checked against the lidar says
so. On the small lidar catalog of tests/api/lidar_catalog.py."""

from __future__ import annotations

import io
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest
from matplotlib.image import imread
from selenium.webdriver.common.by import By

from service.api import create_app
from service.settings import Settings
from tests.api.lidar_catalog import add_lidar_catalog
from tests.console.browser import serve
from tests.console.conftest import Console
from tests.console.test_console import console_errors, open_page, readable


@pytest.fixture
def lidar_console(tmp_path: Path) -> Iterator[Console]:
    app = create_app(Settings(data_dir=tmp_path, database_url=f"sqlite:///{tmp_path / 'catalog.sqlite'}"))
    add_lidar_catalog(app.state.sessions, tmp_path)
    with serve(app) as url, httpx.Client(base_url=url, timeout=60) as api:
        yield Console(app=app, url=url, api=api, maplet_id=0)


def test_lidar_page_draws_the_tracks_by_their_residual(browser, lidar_console, screenshot):
    open_page(browser, lidar_console, "/console/lidar.html?v=1")
    assert console_errors(browser) == []
    residuals = lidar_console.api.get("/versions/1/lidar").json()
    tracks = lidar_console.api.get("/lidar/tracks").json()["items"]
    plot = browser.find_element(By.ID, "map")
    drawn = {int(e.get_attribute("data-track")): e
             for e in plot.find_elements(By.CSS_SELECTOR, "[data-role=tracks] ellipse")}
    assert sorted(drawn) == sorted(t["id"] for t in tracks)
    for track_id, outline in drawn.items():
        assert float(outline.get_attribute("data-rms-m")) == pytest.approx(
            residuals["tracks"][str(track_id)]["rms_km"] * 1e3, abs=1e-3)
    cells = plot.find_elements(By.CSS_SELECTOR, "[data-role=cells] rect")
    assert len(cells) == sum(c is not None for row in residuals["map"]["rms_km"] for c in row) > 0
    titles = [t.text for t in plot.find_elements(By.CSS_SELECTOR, "[data-role=axes] text.title")]
    assert titles == ["east longitude (deg)", "latitude (deg)"]
    scale = readable(browser.find_element(By.TAG_NAME, "main"), unit="m")
    # the scale bar at the equator of the 250 m sphere: 360 deg of longitude span its circumference
    width_px = float(plot.find_element(By.CSS_SELECTOR, "[data-role=axes] rect.outline").get_attribute("width"))
    circumference_m = 2 * 3.14159265 * lidar_console.api.get("/versions/1").json()["statistics"]["mean_radius_km"] * 1e3
    assert scale["metres"] / scale["px"] == pytest.approx(circumference_m / width_px, rel=0.02)
    assert imread(io.BytesIO(plot.screenshot_as_png))[..., :3].std() > 0.05
    rows = {r.get_attribute("data-track"): [td.text for td in r.find_elements(By.TAG_NAME, "td")]
            for r in browser.find_elements(By.CSS_SELECTOR, "#tracks tbody tr")}
    adjusted = next(t for t in tracks if t["correction"] is not None)
    assert float(rows[str(adjusted["id"])][3]) == pytest.approx(3.162, abs=0.005)  # |(3, -1, 0)| m, 3 digits
    assert "mean 2." in browser.find_element(By.ID, "summary").text
    screenshot(browser, "lidar")

    open_page(browser, lidar_console, "/console/lidar.html?v=2")
    assert "not checked against the lidar" in browser.find_element(By.ID, "summary").text
    # the browser logs the answer 404 itself, nothing else
    assert all("/versions/2/lidar" in e["message"] and "404" in e["message"] for e in console_errors(browser))
