"""/healthz: 200 while the catalog answers, 503 with the reason when it does not, and its probes
kept out of the access log."""

from __future__ import annotations

import logging

from fastapi.testclient import TestClient

from service.api import create_app
from service.api.routers.health import QuietProbes
from service.db import make_engine, make_sessionmaker
from service.settings import Settings


def test_healthz_answers_ok_then_503_when_the_catalog_is_gone(tmp_path) -> None:
    app = create_app(Settings(data_dir=tmp_path / "data", database_url=f"sqlite:///{tmp_path / 'catalog.db'}"))
    with TestClient(app) as client:
        ok = client.get("/healthz")
        assert ok.status_code == 200
        assert ok.json() == {"status": "ok", "catalog": "ok"}
        # a database that refuses connections (nothing listens on port 1)
        app.state.sessions = make_sessionmaker(make_engine("postgresql://pwm:secret@127.0.0.1:1/pwm"))
        down = client.get("/healthz")
    assert down.status_code == 503
    body = down.json()
    assert body["status"] == "unavailable"
    assert body["catalog"].startswith("unavailable") and "OperationalError" in body["catalog"]
    assert "secret" not in down.text and "127.0.0.1" not in down.text  # no details to an anonymous caller


def test_health_probes_stay_out_of_the_access_log() -> None:
    def record(path: str) -> logging.LogRecord:
        return logging.LogRecord("uvicorn.access", logging.INFO, __file__, 1, '%s - "%s %s HTTP/%s" %d',
                                 ("10.0.0.1:5000", "GET", path, "1.1", 200), None)

    probes = QuietProbes()
    assert not probes.filter(record("/healthz"))
    assert not probes.filter(record("/healthz?probe=1"))
    assert probes.filter(record("/versions"))
