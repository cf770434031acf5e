"""Benchmark the console: screenshots of every page into a folder, and the time the 3D view of a
version takes to draw its first frame, cold and warm. Prints a table.

    .venv/bin/python bench/console.py DATA_DIR [--version V] [--shots DIR] [--repeat 3]

DATA_DIR is a pwm data directory with its SQLite catalog, e.g. the `site` scenario run through
`pwm run` (bench/RESULTS.md says how). The API is served by uvicorn in this process and read by
headless Chromium (tests/console/browser.py: Debian's chromium and chromium-driver, WebGL on
SwiftShader). The first draw is the page's own measure (body[data-drawn-ms]): from navigation
start to the first frame finished (gl.finish), the version's mesh document fetched, parsed and
drawn. Cold: a fresh browser without HTTP cache each time; warm: the same page loaded again in
a browser that keeps its cache. The mesh document is made at publication (service.publish); a
version published before that was made is given it first, as publication would, timed apart.
Aim: the cold first draw within 3 s.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from selenium.webdriver.support.ui import WebDriverWait  # noqa: E402

from service.api import create_app  # noqa: E402
from service.console.documents import MeshRequest, mesh_document, unpack  # noqa: E402
from service.settings import Settings  # noqa: E402
from service.versions import get_version  # noqa: E402
from tests.console.browser import chromium, serve  # noqa: E402

TIMEOUT_S = 300
PAGES = {"versions": "/?v={v}", "view": "/console/view.html?v={v}",
         "view-change": "/console/view.html?v={v}&colour=change",
         "coverage": "/console/coverage.html", "diff": "/console/diff.html?new={v}",
         "site": "/console/site.html?v={v}", "jobs": "/console/jobs.html"}


def first_draw_s(browser, url: str) -> float:
    browser.get(url)
    drawn = WebDriverWait(browser, TIMEOUT_S).until(
        lambda driver: driver.execute_script("return document.body.dataset.drawnMs"))
    return float(drawn) / 1e3


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("data_dir", type=Path)
    parser.add_argument("--version", default="latest")
    parser.add_argument("--shots", type=Path, default=Path("console-shots"))
    parser.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args()
    settings = Settings(data_dir=args.data_dir)
    app = create_app(settings)
    with app.state.sessions() as session:
        version = get_version(session, args.version)
        request = MeshRequest.of(version)
        number, faces = version.version, version.statistics.get("faces")
    clock = time.perf_counter()
    path = mesh_document(settings.data_dir, request, cache_bytes=settings.export_cache_bytes)
    prepared_s = time.perf_counter() - clock
    header, _ = unpack(path.read_bytes())
    view = PAGES["view"].format(v=number)
    with serve(app) as base:
        cold = []
        for _ in range(args.repeat):
            with chromium(cache=False) as browser:
                cold.append(first_draw_s(browser, base + view))
        with chromium() as browser:
            first_draw_s(browser, base + view)
            warm = [first_draw_s(browser, base + view) for _ in range(args.repeat)]
            args.shots.mkdir(parents=True, exist_ok=True)
            for name, page in PAGES.items():
                browser.get(base + page.format(v=number))
                WebDriverWait(browser, TIMEOUT_S).until(lambda driver: driver.execute_script(
                    "return document.body.dataset.ready !== undefined"
                    " || document.body.dataset.drawnMs !== undefined"))
                time.sleep(0.5)  # images and canvases settle
                browser.save_screenshot(str(args.shots / f"{name}.png"))
    print(f"version {number}: {faces} faces, drawn as {header['faces']} "
          f"({path.stat().st_size / 1e6:.1f} MB document, ready in {prepared_s:.2f} s: read if "
          f"publication made it, else made now as publication would)")
    print("| first draw of the 3D view | median s | runs (s) |")
    print("|---|---|---|")
    for label, runs in (("cold (fresh browser, no HTTP cache)", cold), ("warm (cached)", warm)):
        print(f"| {label} | {statistics.median(runs):.2f} | "
              f"{', '.join(f'{r:.2f}' for r in runs)} |")
    print(f"screenshots: {', '.join(sorted(p.name for p in args.shots.glob('*.png')))} in "
          f"{args.shots}")


if __name__ == "__main__":
    main()
