"""The console in a real browser (headless Chromium): every page loads without a console
error, the 3D view draws, the coverage map and the site page show the catalog's own numbers,
and without the token the release and re-queue controls are refused."""

from __future__ import annotations

import io

import numpy as np
import pytest
from matplotlib.image import imread
from selenium.webdriver.common.by import By
from selenium.webdriver.support.ui import WebDriverWait

from pwm.site import slope_deg
from service.console.documents import unpack
from tests.console.conftest import FAILURE, TOKEN

LOAD_TIMEOUT_S = 90
# page, and the body attribute it sets once it has shown what it loads
PAGES = [("/", "ready"), ("/console/view.html", "drawnMs"), ("/console/view.html?v=1&colour=height", "drawnMs"),
         ("/console/coverage.html", "ready"), ("/console/diff.html", "ready"),
         ("/console/site.html", "ready"), ("/console/jobs.html", "ready")]


def open_page(browser, console, path: str, ready: str = "ready") -> None:
    browser.get_log("browser")  # what earlier pages logged
    browser.get(console.url + path)

    def shown(driver) -> bool:
        failed = driver.find_elements(By.CSS_SELECTOR, ".status.error, .status.refused")
        assert not failed, f"{path}: {failed[0].text}"
        return driver.execute_script(f"return document.body.dataset.{ready} !== undefined")

    WebDriverWait(browser, LOAD_TIMEOUT_S).until(shown)


def console_errors(browser) -> list[dict]:
    return [entry for entry in browser.get_log("browser") if entry["level"] == "SEVERE"]


def cells(browser, table: str) -> list[list[str]]:
    return [[td.text for td in row.find_elements(By.TAG_NAME, "td")]
            for row in browser.find_elements(By.CSS_SELECTOR, f"#{table} tbody tr")]


@pytest.mark.parametrize(("path", "ready"), PAGES)
def test_page_loads_without_a_console_error(browser, console, path, ready):
    open_page(browser, console, path, ready)
    assert console_errors(browser) == []
    # the security headers hold for the pages too
    response = console.api.get(path)
    assert response.status_code == 200
    assert "script-src 'self'" in response.headers["content-security-policy"]


def test_3d_view_draws_the_version(browser, console):
    open_page(browser, console, "/console/view.html?v=2", "drawnMs")
    canvas = browser.find_element(By.CSS_SELECTOR, "#view canvas")
    pixels = imread(io.BytesIO(canvas.screenshot_as_png))[..., :3]
    background = np.array([0x0b, 0x0e, 0x13]) / 255
    drawn = np.abs(pixels - background).max(axis=-1) > 0.05
    assert drawn.mean() > 0.02, f"only {drawn.mean():.4f} of the canvas drawn"
    assert pixels[drawn].std() > 0.02  # shaded and coloured, not one flat colour
    header, _ = unpack(console.api.get("/console/api/versions/2/mesh").content)
    title = browser.find_element(By.ID, "title").text
    assert f"version 2 ({header['faces']} of {header['faces_full']} faces)" in title
    # another colour draws without a reload
    browser.find_element(By.CSS_SELECTOR, "#colour option[value=change]").click()
    legend = browser.find_element(By.ID, "legend").text
    assert legend.startswith("change:") and " m " in legend
    assert console_errors(browser) == []


def test_coverage_map_shows_the_catalogs_numbers(browser, console):
    open_page(browser, console, "/console/coverage.html")
    rows = {row.get_attribute("data-maplet"): row for row in
            browser.find_elements(By.CSS_SELECTOR, "#maplets tbody tr")}
    listed = console.api.get("/maplets", params={"limit": 1000}).json()
    assert len(rows) == listed["total"] > 0
    seen = 0
    for maplet in listed["items"]:
        shown = [td.text for td in rows[str(maplet["id"])].find_elements(By.TAG_NAME, "td")]
        coverage = console.api.get(f"/maplets/{maplet['id']}").json()["coverage"]
        assert shown[0] == coverage["maplet"]
        assert int(shown[1]) == coverage["image_count"] == maplet["image_count"]
        assert int(shown[2]) == coverage["used_count"]
        assert float(shown[3]) == pytest.approx(coverage["region_weight"], abs=5e-4)
        assert shown[4].startswith("yes" if coverage["five_views"] else "no")
        if coverage["incidence_deg"] is None:
            assert shown[5] == "—"
        else:
            low, high = (float(v) for v in shown[5].split("–"))
            assert (low, high) == pytest.approx(coverage["incidence_deg"], abs=0.05)
        seen += coverage["image_count"] > 0
    assert seen > 0  # the tiny downlink's images see some maplets
    map_pixels = imread(io.BytesIO(browser.find_element(By.ID, "map").screenshot_as_png))
    assert map_pixels[..., :3].std() > 0.05  # the map is drawn


def test_site_page_shows_the_sites_numbers(browser, console):
    open_page(browser, console, "/console/site.html?v=2")
    lat = browser.find_element(By.ID, "lat").get_attribute("value")
    lon = browser.find_element(By.ID, "lon").get_attribute("value")
    response = console.api.get("/console/api/versions/2/site",
                               params={"lat": lat, "lon": lon, "radius_km": 0.025})
    assert response.status_code == 200
    header, arrays = unpack(response.content)
    shown = {row[0].split(" ")[0]: row[1:] for row in cells(browser, "site-stats")}
    assert set(shown) == set(header["statistics"]) == {"height", "albedo", "slope", "roughness",
                                                       "relief"}
    for name, extent in header["statistics"].items():
        assert [float(v) for v in shown[name]] == pytest.approx(
            [extent["min"], extent["mean"], extent["max"]], rel=1e-3, abs=1e-6)
    # the maps are pwm.site's of the heights served
    height = arrays["height"].astype(float)
    np.testing.assert_allclose(arrays["slope"], slope_deg(height, spacing_m=header["spacing_m"],
                                                          baseline_m=header["baseline_m"]),
                               rtol=1e-4, atol=1e-4)
    assert f"{header['nx']} x {header['ny']} nodes" in browser.find_element(By.ID, "title").text
    # a profile along a line drawn on the height map
    height_map = browser.find_element(By.ID, "map-height")
    browser.execute_script("document.body.dataset.profile = ''")
    from selenium.webdriver.common.action_chains import ActionChains
    ActionChains(browser).move_to_element_with_offset(height_map, -60, -40).click_and_hold() \
        .move_to_element_with_offset(height_map, 60, 40).release().perform()
    info = browser.find_element(By.ID, "profile-info").text
    assert info.startswith("from (") and "heights" in info
    # the site product to download is the API's export of the same site
    link = browser.find_element(By.ID, "download").get_attribute("href")
    product = console.api.get(link.removeprefix(console.url))
    assert product.status_code == 200 and product.headers["content-type"] == "application/zip"
    assert console_errors(browser) == []


def test_jobs_page_shows_progress_and_failures(browser, console):
    open_page(browser, console, "/console/jobs.html")
    jobs = {row[2]: row for row in cells(browser, "jobs")}
    assert jobs["refine:running"][3] == "running" and jobs["refine:running"][4].endswith("40%")
    assert jobs["refine:failed"][3] == "failed"
    assert jobs["refine:failed"][5] == console.api.get(
        "/jobs", params={"key": "refine:failed"}).json()["items"][0]["error"] == FAILURE
    downlinks = cells(browser, "downlinks")
    assert len(downlinks) == console.api.get("/downlinks").json()["total"] == 1


def test_without_the_token_release_and_requeue_are_refused(browser, console):
    jobs_before = console.api.get("/jobs").json()["total"]
    open_page(browser, console, "/?v=1")
    browser.find_element(By.ID, "release-tag").send_keys("console-test")
    browser.find_element(By.ID, "release").click()
    status = WebDriverWait(browser, LOAD_TIMEOUT_S).until(
        lambda driver: driver.find_element(By.ID, "release-status").text and
        driver.find_element(By.ID, "release-status"))
    assert "refused" in status.get_attribute("class") and "401" in status.text
    assert console.api.get("/versions/1").json()["released"] is False

    open_page(browser, console, "/console/coverage.html")
    row = browser.find_element(By.CSS_SELECTOR, f"#maplets tr[data-maplet='{console.maplet_id}']")
    row.find_element(By.TAG_NAME, "button").click()
    status = WebDriverWait(browser, LOAD_TIMEOUT_S).until(
        lambda driver: row.find_element(By.CSS_SELECTOR, ".status").text and
        row.find_element(By.CSS_SELECTOR, ".status"))
    assert "refused" in status.get_attribute("class") and "401" in status.text
    assert console.api.get("/jobs").json()["total"] == jobs_before

    # with the token the same control goes through: the refusal above was the token's
    open_page(browser, console, "/?v=1")
    browser.find_element(By.ID, "token").send_keys(TOKEN + "\n")
    browser.find_element(By.ID, "release-tag").send_keys("console-test")
    browser.find_element(By.ID, "release").click()
    WebDriverWait(browser, LOAD_TIMEOUT_S).until(
        lambda driver: "released" in driver.find_element(By.ID, "release-status").text)
    assert console.api.get("/versions/1").json()["release_tag"] == "console-test"
    browser.execute_script("sessionStorage.clear()")
