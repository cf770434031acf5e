"""The console in a real browser (headless Chromium): every page loads without a console
error, the 3D view draws the whole body and goes back to it, the coverage map and the site page
show the catalog's own numbers, every map reads (colour bar with its unit, scale bar, north arrow,
axes), the site page warns away from refined data, the versions page names its statistics, and
without the token the release and re-queue controls are refused. Each page's screenshot is saved
(the `screenshot` fixture) for a person to look at."""

from __future__ import annotations

import io
import math
import re

import numpy as np
import pytest
from matplotlib.image import imread
from selenium.webdriver.common.action_chains import ActionChains
from selenium.webdriver.common.actions.wheel_input import ScrollOrigin
from selenium.webdriver.common.by import By
from selenium.webdriver.support.ui import WebDriverWait

from pwm.site import slope_deg
from service.console.documents import unpack
from tests.console.conftest import FAILURE, TOKEN

LOAD_TIMEOUT_S = 90
# page, and the body attribute it sets once it has shown what it loads
PAGES = [("/", "ready"), ("/console/view.html", "drawnMs"), ("/console/view.html?v=1&colour=height", "drawnMs"),
         ("/console/coverage.html", "ready"), ("/console/diff.html", "ready"),
         ("/console/site.html", "ready"), ("/console/jobs.html", "ready"), ("/console/lidar.html", "ready")]


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


# a scale bar's text: a round length in m or km
SCALE_TEXT = re.compile(r"^(1|2|5)(0*|\.0*[125])? (m|km)$")


def readable(element, *, unit: str, north_deg: float | None = 0.0) -> dict:
    """Assert that the map `element` holds a colour bar titled with `unit`, a scale bar with a
    round length in m or km, and a north arrow at north_deg clockwise from up (None: no north
    arrow asked); the scale bar's metres and its drawn length (px)."""
    bar = element.find_element(By.CSS_SELECTOR, "[data-role=colour-bar]")
    assert f"({unit})" in bar.find_element(By.CSS_SELECTOR, "text.title").text
    scale = element.find_element(By.CSS_SELECTOR, "[data-role=scale-bar]")
    assert SCALE_TEXT.match(scale.text), scale.text
    drawn = sum(float(r.get_attribute("width")) for r in scale.find_elements(By.CSS_SELECTOR, "rect.dark, rect.light"))
    if north_deg is not None:
        arrow = element.find_element(By.CSS_SELECTOR, "[data-role=north-arrow]")
        assert arrow.text == "N"
        assert float(arrow.get_attribute("data-angle")) == pytest.approx(north_deg, abs=0.1)
    return {"metres": float(scale.get_attribute("data-metres")), "px": drawn}


def cells(browser, table: str) -> list[list[str]]:
    return [[td.text for td in row.find_elements(By.TAG_NAME, "td")]
            for row in browser.find_elements(By.CSS_SELECTOR, f"#{table} tbody tr")]


@pytest.mark.parametrize(("path", "ready"), PAGES)
def test_page_loads_without_a_console_error(browser, console, screenshot, path, ready):
    open_page(browser, console, path, ready)
    assert console_errors(browser) == []
    screenshot(browser, "page-" + (re.sub(r"[^a-z0-9]+", "-", path.lower()).strip("-") or "versions"))
    # the security headers hold for the pages too
    response = console.api.get(path)
    assert response.status_code == 200
    assert "script-src 'self'" in response.headers["content-security-policy"]


def drawn_pixels(browser) -> tuple[np.ndarray, np.ndarray]:
    """The 3D view's canvas (RGB in [0, 1]) and where it is drawn (not the background)."""
    canvas = browser.find_element(By.CSS_SELECTOR, "#view canvas")
    pixels = imread(io.BytesIO(canvas.screenshot_as_png))[..., :3]
    background = np.array([0x0b, 0x0e, 0x13]) / 255
    return pixels, np.abs(pixels - background).max(axis=-1) > 0.05


def test_3d_view_draws_the_version(browser, console, screenshot):
    open_page(browser, console, "/console/view.html?v=2&colour=height", "drawnMs")
    pixels, drawn = drawn_pixels(browser)
    assert drawn.mean() > 0.02, f"only {drawn.mean():.4f} of the canvas drawn"
    assert pixels[drawn].std() > 0.02  # shaded and coloured, not one flat colour
    # the whole body in view: every vertex inside it, filling a good part; nothing drawn at
    # the canvas's edges
    framing = float(browser.execute_script("return document.body.dataset.framing"))
    assert 0.4 < framing < 1.0
    inside = drawn[2:-2, 2:-2]  # within the canvas's 1 px border
    edges = [inside[0], inside[:, -1], inside[:-60, 0], inside[-1, 200:]]  # not the scale bar's corner
    assert not any(edge.any() for edge in edges)
    rows = np.nonzero(drawn)[0]
    assert np.ptp(rows) > 0.4 * drawn.shape[0]
    # its colour bar (height in m), a scale and the body's extent
    readable(browser.find_element(By.TAG_NAME, "main"), unit="m", north_deg=None)
    extent = browser.find_element(By.CSS_SELECTOR, "[data-role=extent]").text
    assert re.search(r"\d m x \d+(\.\d+)? m x", extent), extent
    screenshot(browser, "view-whole-body")
    # turned and zoomed in, then reset: back to the whole body
    view = browser.find_element(By.CSS_SELECTOR, "#view canvas")
    ActionChains(browser).click_and_hold(view).move_by_offset(120, 40).release().perform()
    ActionChains(browser).scroll_from_origin(ScrollOrigin.from_element(view), 0, -800).perform()
    browser.find_element(By.CSS_SELECTOR, "[data-role=reset-view]").click()
    assert float(browser.execute_script("return document.body.dataset.framing")) == framing
    _, again = drawn_pixels(browser)
    assert (again == drawn).mean() > 0.99
    assert "drawn in" not in browser.find_element(By.ID, "status").text
    header, _ = unpack(console.api.get("/console/api/versions/2/mesh").content)
    title = browser.find_element(By.ID, "title").text
    assert f"version 2 ({header['faces']} of {header['faces_full']} faces)" in title
    # another colour draws without a reload
    browser.find_element(By.CSS_SELECTOR, "#colour option[value=change]").click()
    legend = browser.find_element(By.ID, "legend").text
    assert legend.startswith("change:") and " m " in legend
    bar = browser.find_element(By.CSS_SELECTOR, "#colour-bar [data-role=colour-bar]")
    assert bar.find_element(By.CSS_SELECTOR, "text.title").text == "height change since the parent (m)"
    assert float(bar.get_attribute("data-max")) == pytest.approx(header["colours"]["change"]["max"])
    browser.find_element(By.CSS_SELECTOR, "#colour option[value=albedo]").click()
    assert "(no unit)" in browser.find_element(By.CSS_SELECTOR, "#colour-bar text.title").text
    browser.find_element(By.CSS_SELECTOR, "#colour option[value=sigma]").click()
    bar = browser.find_element(By.CSS_SELECTOR, "#colour-bar [data-role=colour-bar]")
    assert bar.find_element(By.CSS_SELECTOR, "text.title").text == "height uncertainty (1 sigma) (m)"
    assert float(bar.get_attribute("data-max")) == pytest.approx(header["colours"]["sigma"]["max"])
    assert console_errors(browser) == []


def test_coverage_map_shows_the_catalogs_numbers(browser, console, screenshot):
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
    # readable: axes in degrees, a colour bar with its unit, a scale bar in km, north up
    coverage_map = browser.find_element(By.ID, "map")
    titles = [t.text for t in coverage_map.find_elements(By.CSS_SELECTOR, "[data-role=axes] text.title")]
    assert titles == ["east longitude (deg)", "latitude (deg)"]
    scale = readable(browser.find_element(By.TAG_NAME, "main"), unit="count")
    # each maplet drawn over its square: its height on the map is its side at the scale bar's
    # metres per pixel (the squares lie east-north, so their outline is barely turned)
    metres_per_px = scale["metres"] / scale["px"]
    sizes = {m["id"]: m["size_km"] for m in listed["items"]}
    cells_drawn = coverage_map.find_elements(By.CSS_SELECTOR, "[data-role=cells] polygon")
    assert len(cells_drawn) == len(sizes)
    for cell in cells_drawn[:5]:
        ys = [float(point.split(",")[1]) for point in cell.get_attribute("points").split()]
        side_m = sizes[int(cell.get_attribute("data-maplet"))] * 1e3
        assert np.ptp(ys) * metres_per_px == pytest.approx(side_m, rel=0.15)
    screenshot(browser, "coverage")


def test_site_page_shows_the_sites_numbers(browser, console, screenshot):
    open_page(browser, console, "/console/site.html?v=2")
    lat = browser.find_element(By.ID, "lat").get_attribute("value")
    lon = browser.find_element(By.ID, "lon").get_attribute("value")
    response = console.api.get("/console/api/versions/2/site",
                               params={"lat": lat, "lon": lon, "radius_km": 0.025})
    assert response.status_code == 200
    header, arrays = unpack(response.content)
    shown = {row[0].split(" ")[0]: row[1:] for row in cells(browser, "site-stats")}
    assert set(shown) == set(header["statistics"]) == {"height", "albedo", "slope", "roughness",
                                                       "relief", "sigma"}
    for name, extent in header["statistics"].items():
        assert [float(v) for v in shown[name]] == pytest.approx(
            [extent["min"], extent["mean"], extent["max"]], rel=1e-3, abs=1e-6)
    # the maps are pwm.site's of the heights served
    height = arrays["height"].astype(float)
    np.testing.assert_allclose(arrays["slope"], slope_deg(height, spacing_m=header["spacing_m"],
                                                          baseline_m=header["baseline_m"]),
                               rtol=1e-4, atol=1e-4)
    assert f"{header['nx']} x {header['ny']} nodes" in browser.find_element(By.ID, "title").text
    # every map reads: its colour bar with the unit, a scale bar as long as it says, north
    # where the body's +Z axis projects in the site frame (clockwise from the map's +y)
    rotation = np.array(header["frame"]["rotation"])
    north_deg = math.degrees(math.atan2(rotation[0, 2], rotation[1, 2]))
    extent_m = header["nx"] * header["spacing_m"]
    units = {"height": "m", "slope": "deg", "roughness": "m", "albedo": "no unit", "sigma": "m"}
    figures = browser.find_elements(By.CSS_SELECTOR, "#maps figure")
    assert [f.get_attribute("data-map") for f in figures] == [*units, "hazard"]
    for figure in figures:
        name = figure.get_attribute("data-map")
        if name == "hazard":
            legend = figure.find_element(By.CSS_SELECTOR, "[data-role=colour-bar]").text
            assert "hazard" in legend and "safe" in legend and "no data" in legend
            continue
        scale = readable(figure, unit=units[name], north_deg=north_deg)
        image_px = float(figure.find_element(By.CSS_SELECTOR, "image").get_attribute("width"))
        assert scale["metres"] == pytest.approx(scale["px"] * extent_m / image_px, rel=1e-3)
        axes_titles = [t.text for t in figure.find_elements(By.CSS_SELECTOR, "[data-role=axes] text.title")]
        assert axes_titles == ["x east (m, site frame)", "y north (m)"]
    # the version's refined maplet covers the site's middle, and the page says so
    assert header["fine"]["fraction"] > 0 and header["fine"]["maplets"]
    assert browser.find_element(By.ID, "coarse-warning").is_displayed() is False
    note = browser.find_element(By.CSS_SELECTOR, "[data-role=fine-note]").text
    assert note.startswith("Refined data") and header["fine"]["maplets"][0] in note
    # the profile: axes in metres, ticks with no more digits than their step
    profile_titles = [t.text for t in browser.find_elements(By.CSS_SELECTOR, "[data-role=profile] text.title")]
    assert profile_titles == ["distance along the line (m)", "height (m)"]
    ticks = browser.execute_script(
        "return [...document.querySelectorAll('[data-role=profile] [data-role=axes] text:not(.title)')]"
        ".map((t) => t.textContent)")
    assert len(ticks) >= 6
    for tick in ticks:
        assert re.fullmatch(r"-?\d+(\.\d{1,3})?", tick), tick
    screenshot(browser, "site-refined")
    # a profile along a line drawn on the height map
    height_map = browser.find_element(By.CSS_SELECTOR, "#map-height image")
    browser.execute_script("document.body.dataset.profile = ''")
    ActionChains(browser).move_to_element_with_offset(height_map, -60, -40).click_and_hold() \
        .move_to_element_with_offset(height_map, 60, 40).release().perform()
    info = browser.find_element(By.ID, "profile-info").text
    assert info.startswith("from (") and "heights" in info
    # the site product to download is the API's export of the same site
    link = browser.find_element(By.ID, "download").get_attribute("href")
    product = console.api.get(link.removeprefix(console.url))
    assert product.status_code == 200 and product.headers["content-type"] == "application/zip"
    assert console_errors(browser) == []


def test_site_page_warns_away_from_refined_data(browser, console, screenshot):
    # the start version was fused from no maplet: the same site has no refined data there
    open_page(browser, console, "/console/site.html?v=1")
    warning = browser.find_element(By.CSS_SELECTOR, "[data-role=coarse-warning]")
    assert warning.is_displayed() and "No refined (site-level) data here" in warning.text
    assert "version 1" in warning.text.lower() and "not a site terrain model" in warning.text
    assert not browser.find_element(By.ID, "site-body").is_displayed()
    screenshot(browser, "site-coarse-warning")
    # shown on request, still with its colour bars
    browser.find_element(By.ID, "show-coarse").click()
    assert browser.find_element(By.ID, "site-body").is_displayed()
    readable(browser.find_element(By.CSS_SELECTOR, "#maps figure[data-map=height]"), unit="m",
             north_deg=None)
    assert console_errors(browser) == []


def test_versions_page_names_its_statistics(browser, console, screenshot):
    open_page(browser, console, "/?v=2")
    shown = {row.get_attribute("data-name"): [td.text for td in row.find_elements(By.XPATH, "./td")]
             for row in browser.find_elements(By.CSS_SELECTOR, "#statistics > tbody > tr")}
    statistics = console.api.get("/versions/2").json()["statistics"]
    assert set(statistics) <= set(shown)
    assert shown["area_km2"][0] == "surface area" and shown["area_km2"][1].endswith(" km²")
    assert float(shown["area_km2"][1].split()[0].replace(",", "")) == pytest.approx(
        statistics["area_km2"], rel=1e-3)
    assert shown["mean_edge_m"] == ["mean edge length", shown["mean_edge_m"][1]]
    assert shown["mean_edge_m"][1].endswith(" m")
    assert shown["faces"][1] == f"{statistics['faces']:,}"
    for label, value in shown.values():
        assert "_" not in label and not value.startswith(("{", "[")), (label, value)
    # what a fusion publishes (service/publish.py), nested figures included, reads the same way
    fused = browser.execute_async_script("""
        const done = arguments[arguments.length - 1];
        import("/console/labels.js").then(({ statistic }) => done(Object.entries({
          maplets_changed: 3, incremental: true, base_version: 1, fusion_seconds: 200.5,
          levels: { "3": { surface: "closed", voxel_m: 8, voxels: 12345 } },
          composition: { regions_laid: 2, regions_carried: 5, closed_levels_made: false },
          lateral_m_prior: 0.25,
        }).map(([key, value]) => {
          const [label, shown] = statistic(key, value);
          return [label, shown instanceof Node ? shown.textContent : shown];
        })));""")
    assert fused == [
        ["maplets changed", "3"], ["parent's fusion sums reused", "yes"], ["base version", "v1"],
        ["fusion time", "3.342 min"], ["levels (spacing 2^k m)", "3surface madeclosedvoxel size8 mvoxels12,345"],
        ["surface composition", "regions laid2regions carried over5closed levels made againno"],
        ["lateral prior", "0.25 m"]]
    # the lineage's edges cross no label
    crossings = browser.execute_script("""
        const svg = document.getElementById("lineage");
        const boxes = [...svg.querySelectorAll("text")].map((t) => t.getBBox());
        let crossed = 0;
        for (const line of svg.querySelectorAll("line")) {
          const [x1, y1, x2, y2] = ["x1", "y1", "x2", "y2"].map((k) => Number(line.getAttribute(k)));
          for (let k = 0; k <= 50; k++) {
            const x = x1 + (k / 50) * (x2 - x1), y = y1 + (k / 50) * (y2 - y1);
            if (boxes.some((b) => x > b.x && x < b.x + b.width && y > b.y && y < b.y + b.height)) { crossed++; break; }
          }
        }
        return [crossed, svg.querySelectorAll("line").length];""")
    assert crossings == [0, 1]
    screenshot(browser, "versions")


def test_difference_page_names_its_figures(browser, console, screenshot):
    open_page(browser, console, "/console/diff.html?old=1&new=2")
    shown = {row.get_attribute("data-name"): [td.text for td in row.find_elements(By.TAG_NAME, "td")]
             for row in browser.find_elements(By.CSS_SELECTOR, "#figures tbody tr")}
    figures = console.api.get("/diffs/1/2").json()
    assert shown["rms_m"][0] == "RMS height change"
    assert float(shown["rms_m"][1].removesuffix(" m")) == pytest.approx(figures["rms_m"], rel=1e-3)
    assert shown["area_changed_m2"][1].endswith(" m²")
    assert all("_" not in label for label, _ in shown.values())
    key = browser.find_element(By.ID, "map-key")
    assert key.find_element(By.CSS_SELECTOR, "[data-role=north-arrow]").get_attribute("data-angle") == "0.0"
    assert re.search(r"1° of latitude = [\d.]+ m", key.find_element(By.CSS_SELECTOR, "[data-role=scale]").text)
    screenshot(browser, "difference")


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


def test_3d_view_draws_a_tile_at_full_resolution_where_double_clicked_or_zoomed_in(
        browser, console, screenshot, tiled_version):
    open_page(browser, console, f"/console/view.html?v={tiled_version}&colour=albedo", "drawnMs")
    tiles = console.api.get(f"/versions/{tiled_version}/tiles").json()["tiles"]
    note = browser.find_element(By.CSS_SELECTOR, "[data-role=tiles-note]").text
    assert f"Stored in {len(tiles)} tiles" in note
    assert browser.execute_script("return document.body.dataset.tilesLoaded") == "0"
    _, before = drawn_pixels(browser)
    view = browser.find_element(By.CSS_SELECTOR, "#view canvas")
    ActionChains(browser).double_click(view).perform()  # the canvas's centre: the body
    WebDriverWait(browser, LOAD_TIMEOUT_S).until(
        lambda driver: driver.execute_script("return document.body.dataset.tilesLoaded") == "1")
    title = browser.find_element(By.ID, "title").text
    loaded = re.search(rf"1 of {len(tiles)} tiles at full resolution, ([\d,]+) faces", title)
    assert loaded and int(loaded.group(1).replace(",", "")) in {t["faces"] for t in tiles}, title
    # drawn in place of its decimated faces: no crack along the tile's border, where the space
    # behind would show through
    _, after = drawn_pixels(browser)
    assert (before & ~after).sum() <= 20
    # double-clicked again on the tile drawn: nothing more loaded; another colour colours it too
    ActionChains(browser).double_click(view).perform()
    browser.find_element(By.CSS_SELECTOR, "#colour option[value=height]").click()
    assert browser.execute_script("return document.body.dataset.tilesLoaded") == "1"
    assert console_errors(browser) == []
    screenshot(browser, "view-tile-at-full-resolution")
    # zoomed in until the drawn faces' edges span more than a few pixels: the level of detail
    # the view needs, the tile at its centre, comes by itself
    open_page(browser, console, f"/console/view.html?v={tiled_version}", "drawnMs")
    view = browser.find_element(By.CSS_SELECTOR, "#view canvas")
    ActionChains(browser).scroll_from_origin(ScrollOrigin.from_element(view), 0, -800).perform()
    WebDriverWait(browser, LOAD_TIMEOUT_S).until(
        lambda driver: driver.execute_script("return document.body.dataset.tilesLoaded") == "1")
    assert console_errors(browser) == []
