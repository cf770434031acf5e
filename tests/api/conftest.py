"""An API over a populated PostgreSQL catalog: the simulated `tiny` downlink ingested with its
start model (images, geometry, maplets, coverage), two model versions (the Bennu radar model and
a refinement of it with albedo), revisions of one maplet and a few jobs."""

from __future__ import annotations

import uuid
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import redis
import trimesh
from fastapi import FastAPI
from fastapi.testclient import TestClient
from sqlalchemy import select

from pwm.io.meshio import read_mesh
from pwm.mesh import Mesh
from service.api import create_app
from service.conductor import weigh
from service.db import session_scope
from service.ingest import ingest_directory
from service.jobs import submit_job
from service.rows import Downlink, JobKind, Maplet, MapletRevision, ModelKind
from service.settings import Settings
from service.versions import import_model, publish_version
from workers.app import app as celery_app
from workers.tasks import CeleryQueue

TOKEN = "test-token-0123456789"
AUTH = {"Authorization": f"Bearer {TOKEN}"}
BENNU_OBJ = (Path(__file__).resolve().parents[2] / "pwm" / "data" / "shapes"
             / "bennu_radar_nolan2013_sbgat.obj")


@dataclass(frozen=True)
class Catalog:
    """What the populated catalog holds, for the tests to look for."""

    app: FastAPI
    data_dir: Path
    refined: Mesh
    maplet_id: int
    downlink_id: int


@pytest.fixture(scope="module")
def module_postgres_url(postgres_server) -> Iterator[str]:
    """A PostgreSQL database shared by the tests of one module, dropped afterwards."""
    name = f"pwm_api_{uuid.uuid4().hex[:12]}"
    with postgres_server.admin() as admin:
        admin.execute(f'CREATE DATABASE "{name}"')
    yield postgres_server.url(name)
    with postgres_server.admin() as admin:
        admin.execute(f'DROP DATABASE "{name}" WITH (FORCE)')


def refined_bennu() -> Mesh:
    """The Bennu radar model subdivided once, with an albedo pattern and a 1-sigma height of 2-4
    cm over its northern half (none over the south, as where no maplet was refined)."""
    start = read_mesh(BENNU_OBJ)
    vertices, faces = trimesh.remesh.subdivide(start.vertices, start.faces)
    sigma = np.where(vertices[:, 2] > 0, 1e-5 * (3 + np.cos(vertices[:, 1] / 0.05)), np.nan)
    return Mesh(vertices, faces, albedo=0.044 + 0.01 * np.sin(vertices[:, 0] / 0.05), sigma=sigma)


@pytest.fixture(scope="module")
def populated(module_postgres_url, tiny_sim, tmp_path_factory) -> Catalog:
    data_dir = tmp_path_factory.mktemp("pwm-data")
    app = create_app(Settings(data_dir=data_dir, database_url=module_postgres_url,
                              api_token=TOKEN), job_queue=CeleryQueue())
    sessions = app.state.sessions
    downlink = tiny_sim / "downlink"
    start = read_mesh(downlink / "start_model.obj")
    ingest_directory(sessions, downlink, shape=start)
    weigh(sessions, start)
    refined = refined_bennu()
    with session_scope(sessions) as session:
        maplet = session.scalars(select(Maplet).order_by(Maplet.id)).first()
        revisions = [MapletRevision(maplet=maplet, revision=k, input_hash=f"{k:064x}",
                                    mode="pwm", statistics={"residual_rms": 0.02 / k,
                                                            "iterations": 3 + k},
                                    artifact_path=f"maplets/{k}.npz", sha256=f"{k:064x}")
                     for k in (1, 2)]
        session.add_all(revisions)
        session.flush()
        maplet.current_revision = revisions[-1]
        start = import_model(session, data_dir=data_dir, path=BENNU_OBJ, kind=ModelKind.START)
        publish_version(session, data_dir=data_dir, mesh=refined, kind=ModelKind.REFINED,
                        parent=start, maplet_revisions=revisions,
                        downlinks=session.scalars(select(Downlink)).all(),
                        statistics={"note": "refined for the API tests"})
        for kind, key in ((JobKind.INGEST, "ingest:a"), (JobKind.REFINE, "refine:b"),
                          (JobKind.REFINE, "refine:c")):
            submit_job(session, kind=kind, key=key)
        downlink_id = session.scalar(select(Downlink.id))
    return Catalog(app=app, data_dir=data_dir, refined=refined, maplet_id=maplet.id,
                   downlink_id=downlink_id)


@pytest.fixture
def token() -> str:
    """The API token of `populated`."""
    return TOKEN


@pytest.fixture
def auth() -> dict[str, str]:
    """Headers that carry the API token of `populated`."""
    return AUTH


@pytest.fixture(scope="module")
def client(populated) -> Iterator[TestClient]:
    with TestClient(populated.app) as client:
        yield client


@pytest.fixture(scope="module")
def broker(redis_url) -> Iterator[redis.Redis]:
    """The workers' Celery app sending to a Redis database of the test server (no worker takes
    the tasks), instead of running them in the calling process; restored afterwards."""
    url = redis_url.rsplit("/", 1)[0] + "/15"
    keys = ("broker_url", "result_backend", "task_always_eager", "task_eager_propagates")
    saved = {key: celery_app.conf[key] for key in keys}
    connection = redis.Redis.from_url(url)
    connection.flushdb()
    celery_app.close()  # its connection pool is made again, for the new broker, when next used
    celery_app.conf.update(broker_url=url, result_backend=url, task_always_eager=False,
                           task_eager_propagates=False)
    yield connection
    celery_app.close()
    celery_app.conf.update(saved)
    connection.flushdb()
    connection.close()
