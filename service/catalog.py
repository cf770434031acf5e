"""Opening the catalog: the one place that migrates the database before use."""

from __future__ import annotations

from sqlalchemy.orm import Session, sessionmaker

from service.db import make_engine, make_sessionmaker, upgrade
from service.settings import Settings, get_settings


def open_catalog(settings: Settings | None = None) -> sessionmaker[Session]:
    """Session factory for the configured catalog, migrated to the latest schema."""
    settings = settings or get_settings()
    settings.data_dir.mkdir(parents=True, exist_ok=True)
    upgrade(settings.database_url)
    return make_sessionmaker(make_engine(settings.database_url, pool_timeout_s=settings.database_pool_timeout_s))
