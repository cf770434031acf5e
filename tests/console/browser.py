"""Debian's headless Chromium driven through chromium-driver (Selenium), and the API served by
uvicorn in a thread on a free local port: what the console's tests and bench/console.py share.
Chromium and its driver come from Debian's `chromium` and `chromium-driver` packages
(scripts/test.sh installs them)."""

from __future__ import annotations

import shutil
import socket
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager

import uvicorn
from fastapi import FastAPI
from selenium import webdriver
from selenium.webdriver.chrome.service import Service

START_TIMEOUT_S = 30.0
# WebGL without a GPU: ANGLE on SwiftShader, which Chromium gates behind the second flag.
CHROMIUM_ARGS = ("--headless=new", "--no-sandbox", "--disable-dev-shm-usage",
                 "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
                 "--window-size=1280,1000", "--hide-scrollbars")


@contextmanager
def chromium(*, cache: bool = True) -> Iterator[webdriver.Chrome]:
    """A headless Chromium that keeps its console log ("browser") for get_log; cache=False: no
    HTTP cache, every load cold."""
    binary, driver = shutil.which("chromium"), shutil.which("chromedriver")
    if binary is None or driver is None:
        raise RuntimeError("chromium and chromedriver not found: install Debian's `chromium` "
                           "and `chromium-driver` packages (scripts/test.sh does)")
    options = webdriver.ChromeOptions()
    options.binary_location = binary
    for arg in CHROMIUM_ARGS + (() if cache else ("--disk-cache-size=1", "--media-cache-size=1")):
        options.add_argument(arg)
    options.set_capability("goog:loggingPrefs", {"browser": "ALL"})
    browser = webdriver.Chrome(options=options, service=Service(driver))
    try:
        yield browser
    finally:
        browser.quit()


@contextmanager
def serve(app: FastAPI) -> Iterator[str]:
    """`app` served by uvicorn in a thread on a free port of 127.0.0.1; its base URL."""
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]
    server = uvicorn.Server(uvicorn.Config(app, host="127.0.0.1", port=port, log_level="warning"))
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    deadline = time.monotonic() + START_TIMEOUT_S
    while not server.started:
        if not thread.is_alive() or time.monotonic() > deadline:
            raise RuntimeError(f"uvicorn did not start on port {port}")
        time.sleep(0.05)
    try:
        yield f"http://127.0.0.1:{port}"
    finally:
        server.should_exit = True
        thread.join(timeout=START_TIMEOUT_S)
