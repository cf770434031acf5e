"""`/healthz`: whether the API and its catalog answer, for a load balancer or compose's health
check. Unauthenticated and cheap (one trivial query); its probes stay out of the access log."""

from __future__ import annotations

import logging

from fastapi import APIRouter, Request, status
from fastapi.responses import JSONResponse
from pydantic import BaseModel
from sqlalchemy import text
from sqlalchemy.exc import SQLAlchemyError

PATH = "/healthz"

log = logging.getLogger(__name__)
router = APIRouter(tags=["health"])


class Health(BaseModel):
    """status: ok or unavailable; catalog: ok, or why the catalog did not answer."""

    status: str
    catalog: str


@router.get(PATH, response_model=Health, responses={503: {"model": Health}})
def healthz(request: Request) -> JSONResponse:
    """200 {"status": "ok", "catalog": "ok"} when the catalog answers a trivial query; 503 with
    the reason when it does not (the details go to the server's log, not to the caller)."""
    try:
        with request.app.state.sessions() as session:
            session.execute(text("SELECT 1"))
    except SQLAlchemyError as exc:
        log.warning("health check: the catalog did not answer: %s", exc)
        reason = f"unavailable: the catalog did not answer ({type(exc).__name__})"
        return JSONResponse(Health(status="unavailable", catalog=reason).model_dump(),
                            status_code=status.HTTP_503_SERVICE_UNAVAILABLE)
    return JSONResponse(Health(status="ok", catalog="ok").model_dump())


class QuietProbes(logging.Filter):
    """Drops uvicorn's access-log lines of health probes, which come every few seconds."""

    def filter(self, record: logging.LogRecord) -> bool:
        # uvicorn.access records carry (client, method, path, http version, status) as args
        args = record.args
        return not (isinstance(args, tuple) and len(args) >= 3 and str(args[2]).split("?")[0] == PATH)


def quiet_access_log() -> None:
    """Install QuietProbes on uvicorn's access logger, once per process."""
    access = logging.getLogger("uvicorn.access")
    if not any(isinstance(f, QuietProbes) for f in access.filters):
        access.addFilter(QuietProbes())
