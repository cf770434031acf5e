"""The FastAPI application: routers per resource, the catalog per request, a request body
limit, security headers on every response, CORS only for configured origins, 503 with
Retry-After when exports or the catalog's connections are all busy, and the OpenAPI schema at
/openapi.json."""

from __future__ import annotations

from collections.abc import AsyncIterator
from contextlib import asynccontextmanager

from fastapi import FastAPI, HTTPException, Request, status
from fastapi.middleware.cors import CORSMiddleware
from fastapi.responses import JSONResponse
from sqlalchemy.exc import TimeoutError as PoolTimeout
from starlette.datastructures import MutableHeaders
from starlette.types import ASGIApp, Message, Receive, Scope, Send

import pwm
from service.api.routers import console, diffs, downlinks, images, jobs, maplets, versions
from service.catalog import open_catalog
from service.exports import RETRY_AFTER_S, ExportBusy
from service.jobs import JobQueue
from service.settings import Settings, get_settings

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
        yield
        sessions.kw["bind"].dispose()

    app = FastAPI(title="pwm", version=pwm.__version__, lifespan=lifespan,
                  description="Shape model versions, exports, maplets, images, downlinks and "
                              "jobs of the pwm catalog. Body-fixed frame, km.")
    app.state.settings = settings
    app.state.sessions = sessions
    app.state.job_queue = job_queue
    for module in (versions, diffs, maplets, images, downlinks, jobs, console):
        app.include_router(module.router)
    app.mount("/console", console.static_files(), name="console")
    app.add_exception_handler(ExportBusy, _busy_exports)
    app.add_exception_handler(PoolTimeout, _busy_catalog)
    app.add_middleware(BodyLimit, max_bytes=MAX_BODY_BYTES)
    if settings.cors_origins:
        app.add_middleware(CORSMiddleware, allow_origins=settings.cors_origins,
                           allow_methods=["GET", "POST"],
                           allow_headers=["Authorization", "Content-Type"],
                           expose_headers=["ETag", "Retry-After", "Content-Disposition"])
    app.add_middleware(SecurityHeaders)  # outermost: on the other middlewares' answers too
    return app


async def _busy_exports(_request: Request, exc: Exception) -> JSONResponse:
    assert isinstance(exc, ExportBusy)
    return JSONResponse({"detail": str(exc)}, status_code=status.HTTP_503_SERVICE_UNAVAILABLE,
                        headers={"Retry-After": str(exc.retry_after_s)})


async def _busy_catalog(_request: Request, _exc: Exception) -> JSONResponse:
    # every connection of the pool stayed in use for the pool's whole timeout
    return JSONResponse({"detail": "the catalog is busy; try again shortly"},
                        status_code=status.HTTP_503_SERVICE_UNAVAILABLE,
                        headers={"Retry-After": str(RETRY_AFTER_S)})


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
