"""Hostile input to the API: nothing a client sends gets a 500 or a traceback. Lone surrogates
and non-finite numbers in JSON, over-long path components, an exception nothing handles, and a
request framed by both Content-Length and Transfer-Encoding (through a real server)."""

from __future__ import annotations

import logging
import socket
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
import uvicorn
from fastapi import FastAPI
from fastapi.testclient import TestClient
from pydantic import SecretStr

from service.api import create_app
from service.api.routers import downlinks
from service.settings import Settings

TOKEN = "hostile-token-0123456789"
AUTH = {"Authorization": f"Bearer {TOKEN}", "Content-Type": "application/json"}


class _Queue:
    """Takes every submission (nothing runs): the routes get past their job queue."""

    def submit_ingest(self, directory: Path, **_: object) -> str:
        return f"ingest:{directory.name}"

    def submit_refinement(self, _session: object, *, maplet_id: int) -> str:
        return f"refine:{maplet_id}"


@pytest.fixture(scope="module")
def app(tmp_path_factory) -> FastAPI:
    data_dir = tmp_path_factory.mktemp("pwm-data")
    (data_dir / "incoming" / "dl-1").mkdir(parents=True)
    return create_app(Settings(data_dir=data_dir, api_token=SecretStr(TOKEN)), job_queue=_Queue())


@pytest.fixture(scope="module")
def client(app) -> Iterator[TestClient]:
    # the server's errors come back as the client would see them, not raised in the test
    with TestClient(app, raise_server_exceptions=False) as client:
        yield client


def _refused(response, code: int) -> dict:
    assert response.status_code == code, response.text
    assert response.headers["content-type"] == "application/json"
    assert response.headers["x-content-type-options"] == "nosniff"
    return response.json()


@pytest.mark.parametrize("path, body", [
    ("/ingests", b'{"path": "\\ud800"}'),
    ("/ingests", b'{"path": "dl-1/\\udfff"}'),
    ("/ingests", b'{"path": "dl-1", "x\\ud800": 1}'),
    ("/ingests", b'{"\\ud800": "\\ud800"}'),
    ("/ingests", b'{"path": NaN}'),
    ("/ingests", b'{"path": [Infinity, -Infinity]}'),
    ("/versions/1/release", b'{"tag": "\\udc80"}'),
])
def test_unencodable_json_is_refused_not_a_500(client, path, body):
    detail = _refused(client.post(path, content=body, headers=AUTH), 422)["detail"]
    assert detail and all(error["msg"] for error in detail)


@pytest.mark.parametrize("path", ["x" * 256, "dl-1/" + "y" * 300, "é" * 128, "a/" + "€" * 86],
                         ids=["256 ascii", "300 under dl-1", "128 two-byte", "86 three-byte"])
def test_a_path_component_over_255_bytes_is_refused_with_a_reason(client, path):
    [error] = _refused(client.post("/ingests", json={"path": path}, headers=AUTH), 422)["detail"]
    assert "over 255 bytes" in error["msg"]


def test_a_path_component_of_255_bytes_is_looked_up(client):
    for path in ("x" * 255, "é" * 127):
        assert "no directory" in _refused(
            client.post("/ingests", json={"path": path}, headers=AUTH), 404)["detail"]
    assert client.post("/ingests", json={"path": "dl-1"}, headers=AUTH).json() == {
        "key": "ingest:dl-1"}


def test_a_path_the_system_cannot_look_up_is_a_400(client, monkeypatch):
    def unreadable(_data_dir: Path, requested: str) -> Path:
        raise PermissionError(13, "Permission denied", requested)

    monkeypatch.setattr(downlinks, "incoming_directory", unreadable)
    detail = _refused(client.post("/ingests", json={"path": "dl-1"}, headers=AUTH), 400)["detail"]
    assert detail == "the path cannot be looked up: Permission denied"


def test_an_unhandled_error_is_logged_and_answered_without_its_traceback(client, monkeypatch,
                                                                         caplog):
    def broken(_data_dir: Path, _requested: str) -> Path:
        raise RuntimeError("secret detail of /srv/pwm")

    monkeypatch.setattr(downlinks, "incoming_directory", broken)
    with caplog.at_level(logging.ERROR, logger="service.api.app"):
        response = client.post("/ingests", json={"path": "dl-1"}, headers=AUTH)
    detail = _refused(response, 500)["detail"]
    assert "log" in detail and "secret" not in response.text and "Traceback" not in response.text
    assert response.headers["x-frame-options"] == "DENY"  # the outer middlewares still ran
    [record] = [r for r in caplog.records if r.exc_info]
    assert "POST /ingests" in record.getMessage()
    assert "secret detail" in str(record.exc_info[1])


def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


@pytest.fixture(scope="module")
def server(app) -> Iterator[int]:
    """A uvicorn server (the one `pwm serve` runs) of `app` in a thread; its port."""
    port = _free_port()
    running = uvicorn.Server(uvicorn.Config(app, host="127.0.0.1", port=port,
                                            log_level="warning", lifespan="off"))
    thread = threading.Thread(target=running.run, daemon=True)
    thread.start()
    deadline = time.monotonic() + 20
    while not running.started:
        assert thread.is_alive() and time.monotonic() < deadline, "uvicorn did not start"
        time.sleep(0.05)
    yield port
    running.should_exit = True
    thread.join(timeout=10)


def _exchange(port: int, request: bytes) -> bytes:
    """All the server sends back for `request`, until it closes the connection (a timeout:
    it kept the connection open)."""
    received = b""
    with socket.create_connection(("127.0.0.1", port), timeout=5) as sock:
        sock.sendall(request)
        try:
            while chunk := sock.recv(65536):
                received += chunk
        except TimeoutError:
            pytest.fail(f"the connection was kept open after: {received!r}")
    return received


def test_content_length_with_transfer_encoding_is_refused_and_the_connection_closed(server):
    # a smuggling attempt: framed by Transfer-Encoding, the body ends at once and a second
    # request follows; framed by Content-Length, that request is the body
    smuggled = (b"POST /ingests HTTP/1.1\r\nHost: pwm\r\nContent-Type: application/json\r\n"
                b"Content-Length: 44\r\nTransfer-Encoding: chunked\r\n\r\n0\r\n\r\n"
                b"GET /versions HTTP/1.1\r\nHost: pwm\r\n\r\n")
    received = _exchange(server, smuggled)
    head, _, body = received.partition(b"\r\n\r\n")
    assert head.startswith(b"HTTP/1.1 400 "), received
    assert b"connection: close" in head.lower()
    assert b"not both" in body
    assert received.count(b"HTTP/1.1") == 1  # the smuggled request was never answered


def test_a_request_framed_one_way_is_answered(server):
    for framing in (b"Content-Length: 0\r\n", b"Transfer-Encoding: chunked\r\n\r\n0\r\n"):
        received = _exchange(server, b"GET /versions HTTP/1.1\r\nHost: pwm\r\nConnection: close\r\n"
                                      + framing + b"\r\n")
        assert received.startswith(b"HTTP/1.1 200 "), received
