"""Security: every changing call needs the bearer token, request paths stay inside the incoming
area, oversized and malformed requests get a 4xx with a message, releases never change, job
tracebacks only with the token, security headers on every response, CORS only when configured."""

from __future__ import annotations

import json
import re
import traceback
from datetime import timedelta

import pytest
from fastapi.routing import iter_route_contexts
from fastapi.testclient import TestClient

from service.api import create_app
from service.db import session_scope
from service.jobs import claim_job, fail_job
from service.rows import JobKind, utcnow
from service.settings import Settings
from workers.tasks import ingest_key

READS = {"GET", "HEAD", "OPTIONS"}


def changing_calls(app) -> list[tuple[str, str]]:
    """(method, path) of every route of the app, its routers' included, that is not a read;
    path parameters filled with 1."""
    # a mount (the console's static files, StaticFiles) has no methods: it answers reads only,
    # as test_static_files_change_nothing checks
    calls = [(method, re.sub(r"\{[^}]+\}", "1", route.path))
             for route in iter_route_contexts(app.routes)
             for method in (route.methods or set()) - READS]
    assert len(calls) >= 3  # ingest, re-queue, release at least
    return calls


@pytest.mark.parametrize("header, code", [
    (None, 401), ("Bearer wrong", 403), ("Bearer {token}x", 403), ("Bearer {token[0]}", 403),
    ("{token}", 401), ("Basic {token}", 401), ("Bearer", 401)])
def test_every_changing_call_needs_the_token(client, populated, token, header, code):
    headers = {} if header is None else {"Authorization": header.format(token=token)}
    for method, path in changing_calls(populated.app):
        for body in ({}, {"path": "x", "tag": "v1"}):
            response = client.request(method, path, json=body, headers=headers)
            assert response.status_code == code, (method, path, response.text)
            assert response.json()["detail"]


def test_static_files_change_nothing(client, populated):
    for method in ("POST", "PUT", "DELETE", "PATCH"):
        assert client.request(method, "/console/index.html").status_code == 405
    assert client.get("/console/index.html").status_code == 200


def test_without_a_configured_token_changing_calls_are_refused(populated, auth, tmp_path):
    settings = populated.app.state.settings
    app = create_app(Settings(data_dir=tmp_path, database_url=settings.database_url))
    with TestClient(app) as client:
        for method, path in changing_calls(app):
            assert client.request(method, path, json={}, headers=auth).status_code == 403
            assert client.request(method, path, json={}).status_code == 401


def test_a_server_without_a_job_queue_submits_nothing(populated, auth, tmp_path):
    settings = populated.app.state.settings
    (tmp_path / "incoming" / "dl-1").mkdir(parents=True)
    app = create_app(Settings(data_dir=tmp_path, database_url=settings.database_url,
                              api_token=settings.api_token))
    with TestClient(app) as client:
        for path, body in (("/ingests", {"path": "dl-1"}),
                           (f"/maplets/{populated.maplet_id}/requeue", {})):
            response = client.post(path, json=body, headers=auth)
            assert response.status_code == 503, (path, response.text)
            assert "job queue" in response.json()["detail"]
        assert client.get("/jobs", params={"key": ingest_key(tmp_path / "incoming" / "dl-1")}
                          ).json()["total"] == 0


def test_the_token_is_declared_in_the_openapi_schema(client, populated):
    operations = client.get("/openapi.json").json()["paths"]
    changing = {(method.lower(), path) for method, path in changing_calls(populated.app)}
    for template, methods in operations.items():
        for method, operation in methods.items():
            if (method, re.sub(r"\{[^}]+\}", "1", template)) in changing:
                assert operation["security"] == [{"HTTPBearer": []}], (method, template)
            else:
                assert "security" not in operation, (method, template)


def test_ingest_paths_stay_inside_the_incoming_area(client, populated, broker, tmp_path, auth):
    incoming = populated.data_dir / "incoming"
    (incoming / "dl-1").mkdir(parents=True)
    outside = tmp_path / "outside"
    outside.mkdir()
    (incoming / "escape").symlink_to(outside)
    (incoming / "up").symlink_to("..")
    refused = {"../dl-1": 400, "dl-1/../../incoming/dl-1": 400, str(outside): 400,
               str(incoming / "dl-1"): 400, "escape": 400, "up": 400, "up/artifacts": 400,
               "escape/.": 400, "missing": 404, "dl-1/\x00": 422, "": 422,
               "x" * 2000: 422}
    for path, code in refused.items():
        response = client.post("/ingests", json={"path": path}, headers=auth)
        assert response.status_code == code, (path, response.text)
        assert response.json()["detail"]
    assert broker.llen("ingest") == 0

    response = client.post("/ingests", json={"path": "dl-1"}, headers=auth)
    assert response.status_code == 202
    assert response.json()["key"] == ingest_key(incoming / "dl-1")
    assert broker.llen("ingest") == 1
    job = client.get("/jobs", params={"key": ingest_key(incoming / "dl-1")}).json()
    assert job["items"][0]["status"] == "queued"


def test_artifact_and_export_paths_cannot_leave_the_data_directory(client):
    for path in ("/versions/1/artifacts/..%2F..%2Fetc%2Fpasswd", "/versions/1/artifacts/%2Fetc",
                 "/versions/..%2F1", "/versions/1/export?format=../../x"):
        assert client.get(path).status_code in (404, 422), path


def test_oversized_and_malformed_requests(client, auth):
    big = client.post("/ingests", content=b"{" + b" " * 70_000 + b"}", headers={
        **auth, "Content-Type": "application/json"})
    assert big.status_code == 413 and "limit" in big.json()["detail"]
    streamed = client.post("/ingests", content=(b" " * 1000 for _ in range(100)),
                           headers={**auth, "Content-Type": "application/json"})
    assert streamed.status_code == 413 and "limit" in streamed.json()["detail"]
    malformed = client.post("/versions/1/release", content=b"{tag:", headers={
        **auth, "Content-Type": "application/json"})
    assert malformed.status_code == 422
    assert malformed.json()["detail"][0]["msg"] == "JSON decode error"
    extra = client.post("/versions/1/release", json={"tag": "a", "released": False}, headers=auth)
    assert extra.status_code == 422 and extra.json()["detail"][0]["loc"] == ["body", "released"]
    for tag in ("1", "latest", "Released", "-x", "a" * 65, "a b"):
        response = client.post("/versions/1/release", json={"tag": tag}, headers=auth)
        assert response.status_code == 422, tag
    for path in ("/versions/1/export?format=tar", "/versions/1/export?format=obj&faces=2",
                 "/versions/1/export?format=site&lat=0&lon=0",
                 "/versions/1/export?format=obj&lat=0&lon=0&radius_km=0.01",
                 "/images?start_after=yesterday", "/jobs/99999999999", "/maplets?lat=91&lon=0"):
        response = client.get(path)
        assert response.status_code == 422, path
        assert response.json()["detail"]


def test_released_versions_cannot_be_changed(client, populated, auth):
    first = client.post("/versions/1/release", json={"tag": "nav-2026a"}, headers=auth)
    assert first.status_code == 200
    assert first.json()["released"] and first.json()["release_tag"] == "nav-2026a"
    again = client.post("/versions/1/release", json={"tag": "nav-2026a"}, headers=auth)
    assert again.status_code == 200  # the same release again changes nothing
    retag = client.post("/versions/1/release", json={"tag": "nav-2026b"}, headers=auth)
    assert retag.status_code == 409 and "cannot be changed" in retag.json()["detail"]
    taken = client.post("/versions/2/release", json={"tag": "nav-2026a"}, headers=auth)
    assert taken.status_code == 409 and "names version 1" in taken.json()["detail"]
    for method in ("DELETE", "PUT", "PATCH"):
        assert client.request(method, "/versions/1", headers=auth).status_code == 405
    assert client.get("/versions/released").json()["version"] == 1
    assert client.get("/versions/nav-2026a").json()["version"] == 1
    assert client.get("/versions/2").json()["released"] is False


def test_requeue_a_maplet(client, populated, broker, auth):
    response = client.post(f"/maplets/{populated.maplet_id}/requeue", headers=auth)
    assert response.status_code == 202, response.text
    job = client.get("/jobs", params={"key": response.json()["key"]}).json()["items"][0]
    assert (job["kind"], job["maplet_id"]) == ("refine", populated.maplet_id)
    assert broker.llen("refine") == 1
    assert client.post("/maplets/999999/requeue", headers=auth).status_code == 404


def _failed_job(populated) -> tuple[int, str]:
    """A job whose attempt failed with a real traceback naming server paths: its id and the
    traceback."""
    missing = populated.data_dir / "incoming" / "no such dir" / "image 1.xml"
    try:
        missing.read_text()
    except OSError:
        error = traceback.format_exc()
    with session_scope(populated.app.state.sessions) as session:
        job = claim_job(session, kind=JobKind.INGEST, key="ingest:fails", grace_s=60)
        fail_job(session, job, error=error)
        return job.id, error


def test_job_errors_show_a_reason_and_the_traceback_only_with_the_token(client, populated,
                                                                         auth):
    job_id, error = _failed_job(populated)
    assert str(populated.data_dir) in error and "Traceback" in error
    reason = "FileNotFoundError: [Errno 2] No such file or directory: 'image 1.xml'"
    for headers in ({}, {"Authorization": "Bearer wrong"}):
        listed = client.get("/jobs", params={"key": "ingest:fails"}, headers=headers).json()
        for shown in (listed["items"][0], client.get(f"/jobs/{job_id}", headers=headers).json()):
            assert shown["status"] == "failed"
            assert shown["error"] == reason and shown["traceback"] is None
        for item in client.get("/jobs", headers=headers).json()["items"]:
            assert item["traceback"] is None
            assert "/" not in (item["error"] or ""), item
    for shown in (client.get("/jobs", params={"key": "ingest:fails"}, headers=auth)
                  .json()["items"][0], client.get(f"/jobs/{job_id}", headers=auth).json()):
        assert shown["error"] == reason and shown["traceback"] == error
    schema = client.get("/openapi.json").json()["components"]["schemas"]["JobOut"]
    assert {"error", "traceback"} <= set(schema["properties"])


def test_every_response_carries_the_security_headers(client, populated, auth):
    responses = [client.get("/versions"), client.get("/versions/999"),
                 client.get("/versions/1/export", params={"format": "ply"}),
                 client.get("/jobs", params={"limit": 0}), client.post("/ingests", json={}),
                 client.post("/ingests", content=b"{" + b" " * 70_000 + b"}",
                             headers={**auth, "Content-Type": "application/json"}),
                 client.get("/openapi.json"), client.get("/no/such/route")]
    assert [r.status_code for r in responses] == [200, 404, 200, 422, 401, 413, 200, 404]
    for response in responses:
        headers = response.headers
        assert headers["x-content-type-options"] == "nosniff"
        assert headers["x-frame-options"] == "DENY"
        assert headers["referrer-policy"] == "no-referrer"
        policy = dict(part.strip().split(" ", 1)
                      for part in headers["content-security-policy"].split(";"))
        assert policy["default-src"] == "'self'" and policy["script-src"] == "'self'"
        assert policy["frame-ancestors"] == "'none'" and policy["object-src"] == "'none'"
    # the interactive docs still load their scripts
    docs = client.get("/docs")
    assert docs.status_code == 200 and "cdn.jsdelivr.net" in docs.headers[
        "content-security-policy"]


def test_cors_is_off_unless_origins_are_configured(client, populated, tmp_path):
    preflight = {"Origin": "https://console.example", "Access-Control-Request-Method": "GET"}
    assert "access-control-allow-origin" not in client.get(
        "/versions", headers={"Origin": "https://console.example"}).headers
    assert "access-control-allow-origin" not in client.options("/versions",
                                                               headers=preflight).headers
    settings = populated.app.state.settings
    app = create_app(Settings(data_dir=tmp_path, database_url=settings.database_url,
                              cors_origins=["https://console.example"]))
    with TestClient(app) as allowed:
        answer = allowed.options("/versions", headers=preflight)
        assert answer.status_code == 200
        assert answer.headers["access-control-allow-origin"] == "https://console.example"
        assert answer.headers["x-content-type-options"] == "nosniff"
        read = allowed.get("/versions", headers={"Origin": "https://console.example"})
        assert read.headers["access-control-allow-origin"] == "https://console.example"
        other = allowed.get("/versions", headers={"Origin": "https://elsewhere.example"})
        assert "access-control-allow-origin" not in other.headers


def test_pwm_jobs_shows_what_the_api_shows(client, populated, auth, monkeypatch):
    from typer.testing import CliRunner

    from service.cli import app as cli
    from service.settings import get_settings

    settings = populated.app.state.settings
    with session_scope(populated.app.state.sessions) as session:
        # An attempt whose worker died two hours ago: its heartbeat stopped then.
        lost = claim_job(session, kind=JobKind.REFINE, key="refine:lost-in-test", grace_s=60,
                         worker="gone@host:7", now=utcnow() - timedelta(hours=2))
    _failed_job(populated)
    monkeypatch.setenv("PWM_DATA_DIR", str(settings.data_dir))
    monkeypatch.setenv("PWM_DATABASE_URL", settings.database_url)
    get_settings.cache_clear()
    runner = CliRunner()
    try:
        for options, params in (([], {}), (["--status", "lost"], {"status": "lost"}),
                                (["--kind", "ingest", "--limit", "2"], {"kind": "ingest",
                                                                        "limit": 2})):
            listed = runner.invoke(cli, ["jobs", "list", "--json", *options])
            assert listed.exit_code == 0, listed.output
            api = client.get("/jobs", params={"limit": 50} | params, headers=auth).json()
            assert json.loads(listed.stdout) == api and api["total"] > 0
        [shown] = api_lost = client.get("/jobs", params={"status": "lost"}, headers=auth
                                        ).json()["items"]
        assert (shown["id"], shown["status"], shown["worker"]) == (lost.id, "lost", "gone@host:7")
        assert all(item["status"] != "lost" for item in client.get(
            "/jobs", params={"status": "running"}).json()["items"])
        one = runner.invoke(cli, ["jobs", "show", str(lost.id)])
        assert one.exit_code == 0 and json.loads(one.stdout) == client.get(
            f"/jobs/{lost.id}", headers=auth).json() == api_lost[0]
        table = runner.invoke(cli, ["jobs", "list", "--status", "lost"])
        assert table.exit_code == 0 and table.stdout.splitlines()[1].split("\t")[:3] == [
            str(lost.id), "refine", "lost"]
        refused = runner.invoke(cli, ["jobs", "retry", "999999"])
        assert refused.exit_code == 1 and "no job 999999" in refused.output
    finally:
        get_settings.cache_clear()
