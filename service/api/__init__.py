"""The HTTP API (FastAPI): reads are open, changing calls need the bearer token."""

from service.api.app import create_app

__all__ = ["create_app"]
