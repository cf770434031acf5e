"""What the routes share: the settings, a catalog session per request, the job queue, the bearer
token check for changing calls, pagination, and version references."""

from __future__ import annotations

import hmac
from collections.abc import Iterator
from typing import Annotated

from fastapi import Depends, Header, HTTPException, Path, Query, Request, status
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from pydantic import BaseModel, Field, SecretStr
from sqlalchemy.orm import Session

from service.api.schemas import VERSION_REF_PATTERN
from service.jobs import JobQueue
from service.rows import ModelVersion
from service.settings import Settings
from service.versions import get_version

MAX_LIMIT = 1000
# Row offsets stay far inside PostgreSQL's bigint.
MAX_OFFSET = 10**9
# Database ids are 32-bit integers.
MAX_ID = 2**31 - 1

_bearer = HTTPBearer(auto_error=False, description="PWM_API_TOKEN of the service")


class Paging(BaseModel):
    """limit: rows per page; offset: rows skipped first."""

    limit: int = Field(100, ge=1, le=MAX_LIMIT)
    offset: int = Field(0, ge=0, le=MAX_OFFSET)


def get_settings(request: Request) -> Settings:
    return request.app.state.settings


def get_session(request: Request) -> Iterator[Session]:
    """A session for one request; changing routes commit it themselves."""
    with request.app.state.sessions() as session:
        yield session


def get_jobs(request: Request) -> JobQueue:
    """The queue jobs are submitted to (given to create_app), or 503 when this server has none."""
    jobs: JobQueue | None = request.app.state.job_queue
    if jobs is None:
        raise HTTPException(status.HTTP_503_SERVICE_UNAVAILABLE,
                            "this server runs no jobs: it was started without a job queue")
    return jobs


def require_token(request: Request, credentials: Annotated[
        HTTPAuthorizationCredentials | None, Depends(_bearer)]) -> None:
    """Let a changing call through only with `Authorization: Bearer <PWM_API_TOKEN>`: 401
    without a token, 403 with a wrong one or when the service has none configured."""
    expected = get_settings(request).api_token
    if credentials is None:
        raise HTTPException(status.HTTP_401_UNAUTHORIZED, "this call needs a bearer token",
                            headers={"WWW-Authenticate": "Bearer"})
    if expected is None:
        raise HTTPException(status.HTTP_403_FORBIDDEN,
                            "changing calls are disabled: the service has no PWM_API_TOKEN")
    if not _token_matches(credentials.credentials, expected):
        raise HTTPException(status.HTTP_403_FORBIDDEN, "wrong bearer token")


def has_token(request: Request, authorization: Annotated[
        str | None, Header(include_in_schema=False)] = None) -> bool:
    """Whether a read carries the service's bearer token, for what only operators may see (a
    read without it, or with a wrong one, is still answered)."""
    expected = get_settings(request).api_token
    scheme, _, token = (authorization or "").partition(" ")
    return (expected is not None and scheme.lower() == "bearer"
            and _token_matches(token, expected))


def _token_matches(given: str, expected: SecretStr) -> bool:
    return hmac.compare_digest(given.encode(), expected.get_secret_value().encode())


def resolve_version(session: Session, ref: str) -> ModelVersion:
    """The version a reference names (number, tag, `latest`, `released`), or 404."""
    try:
        return get_version(session, ref)
    except LookupError as exc:
        raise HTTPException(status.HTTP_404_NOT_FOUND, str(exc)) from None


SessionDep = Annotated[Session, Depends(get_session)]
SettingsDep = Annotated[Settings, Depends(get_settings)]
JobsDep = Annotated[JobQueue, Depends(get_jobs)]
PagingDep = Annotated[Paging, Query()]
VersionRef = Annotated[str, Path(pattern=VERSION_REF_PATTERN,
                                 description="version number, release tag, `latest` (newest) "
                                             "or `released` (newest released)")]
Id = Annotated[int, Path(ge=1, le=MAX_ID)]
Authorized = Depends(require_token)
TokenGiven = Annotated[bool, Depends(has_token)]
