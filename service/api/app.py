"""The FastAPI application: routers per resource, the catalog per request, a request body
limit, security headers on every response, CORS only for configured origins, 503 with
Retry-After when exports or the catalog's connections are all busy, error answers that render
whatever a client sent, a logged 500 without a traceback for what nothing else handled, requests
framed two ways refused, /healthz for probes, and the OpenAPI schema at /openapi.json."""

from __future__ import annotations

import json
import logging
import math
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from typing import Any

from fastapi import FastAPI, HTTPException, Request, status
from fastapi.encoders import jsonable_encoder
from fastapi.exceptions import RequestValidationError
from fastapi.middleware.cors import CORSMiddleware
from fastapi.responses import JSONResponse, Response
from fastapi.utils import is_body_allowed_for_status_code
from sqlalchemy.exc import TimeoutError as PoolTimeout
from starlette.datastructures import MutableHeaders
from starlette.types import ASGIApp, Message, Receive, Scope, Send

import pwm
from service.api.routers import console, diffs, downlinks, health, images, jobs, lidar, maplets, versions
from service.artifacts import RETRY_AFTER_S, CacheBusy
from service.catalog import open_catalog
from service.jobs import JobQueue
from service.settings import Settings, get_settings

log = logging.getLogger(__name__)

# Request bodies are small JSON documents; anything larger is refused with 413.
MAX_BODY_BYTES = 64 * 1024
# Every response: no MIME sniffing, no framing, no referrer; the policy is the one a console
# served from this origin needs (its own scripts, styles and images, API calls to itself).
SECURITY_HEADERS = {
    "X-Content-Type-Options": "nosniff",
    "X-Frame-Options": "DENY",
    "Referrer-Policy": "no-referrer",
    "Content-Security-Policy": "default-src 'self'; script-src 'self'; style-src 'self'; "
                               "img-src 'self' data: blob:; connect-src 'self'; "
                               "object-src 'none'; base-uri 'none'; form-action 'self'; "
                               "frame-ancestors 'none'",
    "Cross-Origin-Opener-Policy": "same-origin",
}
# FastAPI's /docs and /redoc pages load their scripts from a CDN and start them inline.
DOCS_CSP = ("default-src 'self'; script-src 'self' 'unsafe-inline' https://cdn.jsdelivr.net; "
            "style-src 'self' 'unsafe-inline' https://cdn.jsdelivr.net; "
            "img-src 'self' data: https://fastapi.tiangolo.com; worker-src blob:; "
            "object-src 'none'; base-uri 'none'; frame-ancestors 'none'")
DOCS_PATHS = frozenset({"/docs", "/docs/oauth2-redirect", "/redoc"})


def create_app(settings: Settings | None = None, *, job_queue: JobQueue | None = None) -> FastAPI:
    """The API over the catalog of `settings` (default: from the environment), migrated first,
    submitting work to `job_queue` (without one, the calls that submit work answer 503).
    Reads are open; changing calls need `Authorization: Bearer <PWM_API_TOKEN>` and are refused
    when no token is configured. Browsers may call it from the origins of PWM_CORS_ORIGINS only
    (none by default)."""
    settings = settings or get_settings()
    sessions = open_catalog(settings)

    @asynccontextmanager
    async def lifespan(_app: FastAPI) -> AsyncIterator[None]:
        health.quiet_access_log()  # here: the server configures its loggers before it starts the app
        yield
        sessions.kw["bind"].dispose()

    app = FastAPI(title="pwm", version=pwm.__version__, lifespan=lifespan,
                  description="Shape model versions, exports, maplets, images, downlinks and "
                              "jobs of the pwm catalog. Body-fixed frame, km.")
    app.state.settings = settings
    app.state.sessions = sessions
    app.state.job_queue = job_queue
    for module in (health, versions, lidar, diffs, maplets, images, downlinks, jobs, console):
        app.include_router(module.router)
    app.mount("/console", console.static_files(), name="console")
    app.add_exception_handler(CacheBusy, _busy_making)
    app.add_exception_handler(PoolTimeout, _busy_catalog)
    app.add_exception_handler(RequestValidationError, _invalid_request)
    app.add_exception_handler(HTTPException, _http_error)
    app.add_middleware(Unhandled)
    app.add_middleware(BodyLimit, max_bytes=MAX_BODY_BYTES)
    if settings.cors_origins:
        app.add_middleware(CORSMiddleware, allow_origins=settings.cors_origins,
                           allow_methods=["GET", "POST"],
                           allow_headers=["Authorization", "Content-Type"],
                           expose_headers=["ETag", "Retry-After", "Content-Disposition"])
    app.add_middleware(SingleFraming)
    app.add_middleware(SecurityHeaders)  # outermost: on the other middlewares' answers too
    return app


async def _busy_making(_request: Request, exc: Exception) -> JSONResponse:
    assert isinstance(exc, CacheBusy)
    return JSONResponse({"detail": str(exc)}, status_code=status.HTTP_503_SERVICE_UNAVAILABLE,
                        headers={"Retry-After": str(exc.retry_after_s)})


async def _busy_catalog(_request: Request, _exc: Exception) -> JSONResponse:
    # every connection of the pool stayed in use for the pool's whole timeout
    return JSONResponse({"detail": "the catalog is busy; try again shortly"},
                        status_code=status.HTTP_503_SERVICE_UNAVAILABLE,
                        headers={"Retry-After": str(RETRY_AFTER_S)})


class ClientJSONResponse(JSONResponse):
    """JSON of an answer that may repeat what a client sent: a lone surrogate (valid in a JSON
    string, not in UTF-8) becomes '?', and a non-finite number (Python's JSON reader takes NaN
    and Infinity) its name as a string, so that the answer renders instead of failing with 500."""

    def render(self, content: Any) -> bytes:
        return json.dumps(_encodable(content), ensure_ascii=False, allow_nan=False,
                          separators=(",", ":")).encode("utf-8", "replace")


def _encodable(value: Any) -> Any:
    if isinstance(value, float) and not math.isfinite(value):
        return str(value)
    if isinstance(value, dict):
        return {_encodable(key): _encodable(item) for key, item in value.items()}
    if isinstance(value, list | tuple):
        return [_encodable(item) for item in value]
    return value


async def _invalid_request(_request: Request, exc: Exception) -> JSONResponse:
    assert isinstance(exc, RequestValidationError)
    return ClientJSONResponse({"detail": jsonable_encoder(exc.errors())},
                              status_code=status.HTTP_422_UNPROCESSABLE_CONTENT)


async def _http_error(_request: Request, exc: Exception) -> Response:
    assert isinstance(exc, HTTPException)
    if not is_body_allowed_for_status_code(exc.status_code):
        return Response(status_code=exc.status_code, headers=exc.headers)
    return ClientJSONResponse({"detail": exc.detail}, status_code=exc.status_code,
                              headers=exc.headers)


class Unhandled:
    """Answer an exception that nothing else handled with a plain 500 (the traceback goes to the
    log, never to the client), so that the outer middlewares still add their headers."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        started = False

        async def watched(message: Message) -> None:
            nonlocal started
            started = started or message["type"] == "http.response.start"
            await send(message)

        try:
            await self.app(scope, receive, watched)
        except Exception:
            log.exception("unhandled error answering %s %s", scope["method"], scope["path"])
            if started:  # too late for another answer: the server drops the connection
                raise
            await JSONResponse({"detail": "internal error; the server's log has the details"},
                               status_code=status.HTTP_500_INTERNAL_SERVER_ERROR)(
                scope, receive, send)


class SingleFraming:
    """Refuse a request that gives both Content-Length and Transfer-Encoding with 400 and close
    its connection (RFC 9112 section 6.1): a proxy in front that frames it by the other header
    sees another request boundary, which smuggles a request past it; what follows on the
    connection cannot be trusted."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        names = {name for name, _ in scope["headers"]} if scope["type"] == "http" else set()
        if {b"content-length", b"transfer-encoding"} <= names:
            await JSONResponse({"detail": "a request gives Content-Length or Transfer-Encoding, "
                                          "not both"},
                               status_code=status.HTTP_400_BAD_REQUEST,
                               headers={"Connection": "close"})(scope, receive, send)
            return
        await self.app(scope, receive, send)


class SecurityHeaders:
    """Add SECURITY_HEADERS to every HTTP response (the docs pages get DOCS_CSP); headers a
    route set itself are kept."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        added = dict(SECURITY_HEADERS)
        if scope["path"] in DOCS_PATHS:
            added["Content-Security-Policy"] = DOCS_CSP

        async def with_headers(message: Message) -> None:
            if message["type"] == "http.response.start":
                headers = MutableHeaders(scope=message)
                for name, value in added.items():
                    if name not in headers:
                        headers[name] = value
            await send(message)

        await self.app(scope, receive, with_headers)


class BodyLimit:
    """Refuse request bodies over `max_bytes` with 413 and a message naming the limit: at once
    when Content-Length says so, else when the body read so far passes it."""

    def __init__(self, app: ASGIApp, max_bytes: int) -> None:
        self.app, self.max_bytes = app, max_bytes

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        message = f"the request body is over the limit of {self.max_bytes} bytes"
        declared = dict(scope["headers"]).get(b"content-length", b"0")
        if not declared.isdigit() or int(declared) > self.max_bytes:
            code, detail = ((status.HTTP_413_CONTENT_TOO_LARGE, message) if declared.isdigit()
                            else (status.HTTP_400_BAD_REQUEST, "malformed Content-Length"))
            await JSONResponse({"detail": detail}, status_code=code)(scope, receive, send)
            return
        received = 0

        async def limited() -> Message:
            nonlocal received
            chunk = await receive()
            received += len(chunk.get("body", b""))
            if received > self.max_bytes:
                # FastAPI passes an HTTPException raised while reading the body to its handler.
                raise HTTPException(status.HTTP_413_CONTENT_TOO_LARGE, message)
            return chunk

        await self.app(scope, limited, send)
