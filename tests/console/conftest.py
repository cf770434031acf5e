"""The console over a SQLite catalog built from the simulated `tiny` downlink (images, geometry,
maplets and coverage by ingest), with two versions (the downlink's start model, and a refinement
of it: subdivided, raised by RAISE_M, with albedo), a maplet revision, and jobs queued, running
and failed; served by uvicorn on a free port and read by headless Chromium; and where the tests
put their pages' screenshots (PWM_SCREENSHOT_DIR, else pytest's tmp_path) for a person to look at."""

from __future__ import annotations

import base64
import os
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import httpx
import numpy as np
import pytest
import trimesh
from fastapi import FastAPI
from selenium import webdriver
from sqlalchemy import select

from pwm.io.meshio import read_mesh
from pwm.mesh import Mesh
from service.api import create_app
from service.conductor import weigh
from service.db import session_scope
from service.ingest import ingest_directory
from service.jobs import claim_job, fail_job, report_progress, submit_job
from service.rows import Downlink, JobKind, Maplet, MapletRevision, ModelKind
from service.settings import Settings
from service.versions import get_version, import_model, publish_version
from tests.console.browser import chromium, serve

TOKEN = "console-token-0123456789"
RAISE_M = 0.2  # the refined version's surface stands this far outside the start's
FAILURE = "ValueError: too few images see maplet 1"


@dataclass(frozen=True)
class Console:
    app: FastAPI
    url: str
    api: httpx.Client
    maplet_id: int


def raised(start: Mesh) -> Mesh:
    """The start subdivided once, moved RAISE_M outward along the radius, with albedo, and a
    1-sigma height of 1-3 cm over its northern half (none over the south: no refined maplet)."""
    vertices, faces = trimesh.remesh.subdivide(start.vertices, start.faces)
    radius = np.linalg.norm(vertices, axis=1, keepdims=True)
    vertices = vertices * (1 + RAISE_M * 1e-3 / radius)
    sigma = np.where(vertices[:, 2] > 0, 1e-5 * (2 + np.cos(vertices[:, 1] / 0.02)), np.nan)
    return Mesh(vertices, faces, albedo=0.044 + 0.01 * np.sin(vertices[:, 0] / 0.02), sigma=sigma)


@pytest.fixture(scope="module")
def console(tiny_sim, tmp_path_factory) -> Iterator[Console]:
    data_dir = tmp_path_factory.mktemp("console-data")
    app = create_app(Settings(data_dir=data_dir, api_token=TOKEN))
    sessions = app.state.sessions
    downlink = tiny_sim / "downlink"
    start_path = downlink / "start_model.obj"
    start = read_mesh(start_path)
    ingest_directory(sessions, downlink, shape=start)
    weigh(sessions, start)
    with session_scope(sessions) as session:
        maplet = session.scalars(select(Maplet).order_by(Maplet.id)).first()
        assert maplet is not None
        revision = MapletRevision(maplet=maplet, revision=1, input_hash=f"{1:064x}", mode="pwm",
                                  statistics={"residual_rms": 0.02}, artifact_path="maplets/1.npz",
                                  sha256=f"{1:064x}")
        session.add(revision)
        session.flush()
        maplet.current_revision = revision
        start = import_model(session, data_dir=data_dir, path=start_path, kind=ModelKind.START)
        publish_version(session, data_dir=data_dir, mesh=raised(read_mesh(start_path)),
                        kind=ModelKind.REFINED, parent=start, maplet_revisions=[revision],
                        downlinks=session.scalars(select(Downlink)).all(),
                        statistics={"note": "refined for the console tests"})
        maplet_id = maplet.id
        submit_job(session, kind=JobKind.INGEST, key="ingest:queued")
        running = claim_job(session, kind=JobKind.REFINE, key="refine:running", grace_s=600,
                            maplet_id=maplet_id)
        assert running is not None
        report_progress(session, running, 0.4, "registering 3 of 7 images")
        failed = claim_job(session, kind=JobKind.REFINE, key="refine:failed", grace_s=600,
                           maplet_id=maplet_id)
        assert failed is not None
        fail_job(session, failed, error=FAILURE)
    with serve(app) as url, httpx.Client(base_url=url, timeout=120) as api:
        yield Console(app=app, url=url, api=api, maplet_id=maplet_id)


@pytest.fixture(scope="module")
def tiled_version(console, tiny_sim) -> int:
    """A third version, the refinement again, stored in four tiles or more (a mesh too big for
    one file, pwm.mesh_tiles); its number. Published when first asked for: the tests that take
    it come last in their module, since it becomes the latest version."""
    mesh = raised(read_mesh(tiny_sim / "downlink" / "start_model.obj"))
    with session_scope(console.app.state.sessions) as session:
        version = publish_version(session, data_dir=console.app.state.settings.data_dir, mesh=mesh,
                                  kind=ModelKind.REFINED, parent=get_version(session, 2),
                                  tile_faces=len(mesh.faces) // 4)
        assert "tiles" in version.artifacts
        return version.version


@pytest.fixture(scope="module")
def browser() -> Iterator[webdriver.Chrome]:
    """Headless Chromium (tests/console/browser.py); tests using it are marked `browser`."""
    with chromium() as driver:
        yield driver


@pytest.fixture
def screenshot(tmp_path) -> Callable[[webdriver.Chrome, str], Path]:
    """A function that saves the whole page the browser shows (beyond the window too) as
    NAME.png in the folder PWM_SCREENSHOT_DIR names, else the test's tmp_path; its path."""
    folder = Path(os.environ.get("PWM_SCREENSHOT_DIR") or tmp_path)
    folder.mkdir(parents=True, exist_ok=True)

    def save(browser: webdriver.Chrome, name: str) -> Path:
        shot = browser.execute_cdp_cmd("Page.captureScreenshot",
                                       {"format": "png", "captureBeyondViewport": True})
        path = folder / f"{name}.png"
        path.write_bytes(base64.b64decode(shot["data"]))
        return path

    return save
