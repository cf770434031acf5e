"""Release tags under concurrency, on SQLite and PostgreSQL: of parallel releases of one version
under different tags exactly one succeeds; a tag names one version; the same release repeated
in parallel succeeds every time."""

from __future__ import annotations

import threading
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import trimesh
from fastapi.testclient import TestClient
from sqlalchemy.orm import Session, sessionmaker

from pwm.mesh import Mesh
from service.api import create_app
from service.db import session_scope
from service.releases import ReleaseConflict, release_version
from service.rows import ModelKind
from service.settings import Settings
from service.versions import get_version, publish_version

PARALLEL = 10
TOKEN = "release-test-token"


def _publish(sessions: sessionmaker[Session], data_dir: Path, count: int) -> None:
    sphere = trimesh.creation.icosphere(subdivisions=1, radius=0.25)
    for k in range(count):
        with session_scope(sessions) as session:
            publish_version(session, data_dir=data_dir, kind=ModelKind.START,
                            mesh=Mesh(np.asarray(sphere.vertices) * (1 + 0.01 * k),
                                      np.asarray(sphere.faces)))


def _in_parallel(call: Callable[[int], str]) -> list[str]:
    """call(i) for i in range(PARALLEL), started together; their outcomes."""
    barrier = threading.Barrier(PARALLEL)

    def started(i: int) -> str:
        barrier.wait()
        return call(i)

    with ThreadPoolExecutor(PARALLEL) as pool:
        return list(pool.map(started, range(PARALLEL), timeout=120))


def _release(sessions: sessionmaker[Session], ref: int, tag: str) -> str:
    try:
        with sessions() as session, session.begin():
            release_version(session, ref, tag=tag)
    except ReleaseConflict:
        return "conflict"
    return tag


def test_parallel_releases_of_one_version_one_wins(catalog, tmp_path):
    _publish(catalog, tmp_path, 1)
    outcomes = _in_parallel(lambda i: _release(catalog, 1, f"tag-{i}"))
    winners = [o for o in outcomes if o != "conflict"]
    assert len(winners) == 1, outcomes
    with catalog() as session:
        version = get_version(session, 1)
        assert version.released and version.release_tag == winners[0]


def test_parallel_releases_of_one_tag_name_one_version(catalog, tmp_path):
    _publish(catalog, tmp_path, PARALLEL)
    outcomes = _in_parallel(lambda i: _release(catalog, i + 1, "nav-1"))
    assert outcomes.count("nav-1") == 1 and outcomes.count("conflict") == PARALLEL - 1
    with catalog() as session:
        assert get_version(session, "nav-1").version == outcomes.index("nav-1") + 1
        assert sum(get_version(session, n).released for n in range(1, PARALLEL + 1)) == 1


def test_the_same_release_repeated_in_parallel_succeeds(catalog, tmp_path):
    _publish(catalog, tmp_path, 1)
    assert _in_parallel(lambda i: _release(catalog, 1, "nav-1")) == ["nav-1"] * PARALLEL


def test_parallel_releases_through_the_api(db_url, tmp_path):
    app = create_app(Settings(data_dir=tmp_path, database_url=db_url, api_token=TOKEN))
    _publish(app.state.sessions, tmp_path, 1)
    with TestClient(app) as client:
        codes = _in_parallel(lambda i: str(client.post(
            "/versions/1/release", json={"tag": f"tag-{i}"},
            headers={"Authorization": f"Bearer {TOKEN}"}).status_code))
    assert sorted(codes) == ["200"] + ["409"] * (PARALLEL - 1)
