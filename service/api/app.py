"""The FastAPI application: routers per resource, the catalog per request, a request body
limit, and the OpenAPI schema at /openapi.json."""

from __future__ import annotations

from collections.abc import AsyncIterator
from contextlib import asynccontextmanager

from fastapi import FastAPI, HTTPException, status
from fastapi.responses import JSONResponse
from starlette.types import ASGIApp, Message, Receive, Scope, Send

import pwm
from service.api.routers import diffs, downlinks, images, jobs, maplets, versions
from service.catalog import open_catalog
from service.settings import Settings, get_settings

# Request bodies are small JSON documents; anything larger is refused with 413.
MAX_BODY_BYTES = 64 * 1024


def create_app(settings: Settings | None = None) -> FastAPI:
    """The API over the catalog of `settings` (default: from the environment), migrated first.
    Reads are open; changing calls need `Authorization: Bearer <PWM_API_TOKEN>` and are refused
    when no token is configured."""
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
    for module in (versions, diffs, maplets, images, downlinks, jobs):
        app.include_router(module.router)
    app.add_middleware(BodyLimit, max_bytes=MAX_BODY_BYTES)
    return app


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
