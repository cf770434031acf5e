"""Alembic environment for the catalog.

Programmatic runs (service.db.upgrade) hand over an open connection in
config.attributes["connection"]; the alembic command line builds one from alembic.ini's
sqlalchemy.url or, when that is unset, from PWM_DATABASE_URL (service.settings).
"""

from __future__ import annotations

from logging.config import fileConfig

from alembic import context
from sqlalchemy.engine import Connection

from service.db import make_engine, migration_transaction
from service.rows import Base
from service.settings import get_settings

config = context.config
target_metadata = Base.metadata


def run_migrations(connection: Connection) -> None:
    context.configure(
        connection=connection,
        target_metadata=target_metadata,
        # SQLite cannot ALTER constraints in place: batch mode rebuilds the table instead.
        render_as_batch=connection.dialect.name == "sqlite",
    )
    with context.begin_transaction():
        context.run_migrations()


def database_url() -> str:
    return config.get_main_option("sqlalchemy.url") or get_settings().database_url


if context.is_offline_mode():
    context.configure(url=database_url(), target_metadata=target_metadata, literal_binds=True)
    with context.begin_transaction():
        context.run_migrations()
elif (shared := config.attributes.get("connection")) is not None:
    run_migrations(shared)
else:
    if config.config_file_name is not None:
        fileConfig(config.config_file_name, disable_existing_loggers=False)
    engine = make_engine(database_url())
    try:
        with migration_transaction(engine) as connection:
            run_migrations(connection)
    finally:
        engine.dispose()
