"""Engines, sessions and schema migrations for the catalog (SQLite or PostgreSQL)."""

from __future__ import annotations

import fcntl
import logging
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from alembic import command
from alembic.config import Config
from alembic.runtime.migration import MigrationContext
from sqlalchemy import URL, Connection, Engine, create_engine, event, make_url, text
from sqlalchemy.dialects import postgresql, sqlite
from sqlalchemy.orm import Session, sessionmaker

log = logging.getLogger(__name__)

# The repository's top-level migrations/ folder; the package is installed editable next to it.
MIGRATIONS_DIR = Path(__file__).resolve().parent.parent / "migrations"

SQLITE_BUSY_TIMEOUT_MS = 30_000
# The PostgreSQL advisory lock key that serializes migrations (any fixed 64-bit number: "pwm").
MIGRATION_LOCK_KEY = 0x70776D


_INSERTS: dict[str, Callable[..., postgresql.Insert | sqlite.Insert]] = {
    "postgresql": postgresql.insert, "sqlite": sqlite.insert}


def insert_ignoring_conflict(session: Session, table: type, *, unique: Sequence[Any],
                             **values: Any) -> postgresql.Insert | sqlite.Insert:
    """INSERT of `values` into `table` that does nothing where a row with the same `unique`
    columns exists (ON CONFLICT DO NOTHING), rather than select-then-insert: concurrent first
    inserts never fail on the unique key, the loser reads the winner's row, and on SQLite the
    write lock is taken before the row is read. NotImplementedError on another database."""
    dialect = session.get_bind().dialect.name
    insert = _INSERTS.get(dialect)
    if insert is None:
        raise NotImplementedError(f"the catalog needs PostgreSQL or SQLite, not {dialect}")
    return insert(table).values(**values).on_conflict_do_nothing(index_elements=list(unique))


def normalize_url(url: str | URL) -> URL:
    """The URL with PostgreSQL pinned to the psycopg 3 driver (plain postgresql:// accepted)."""
    parsed = make_url(url)
    if parsed.drivername in ("postgresql", "postgres"):
        return parsed.set(drivername="postgresql+psycopg")
    return parsed


def _set_sqlite_pragmas(dbapi_connection: Any, _connection_record: Any) -> None:
    # WAL lets readers (API) and a writer (ingest, workers) share the file; SQLite leaves
    # foreign keys off unless asked, on every connection.
    cursor = dbapi_connection.cursor()
    try:
        cursor.execute("PRAGMA journal_mode=WAL")
        cursor.execute("PRAGMA foreign_keys=ON")
        cursor.execute(f"PRAGMA busy_timeout={SQLITE_BUSY_TIMEOUT_MS}")
    finally:
        cursor.close()


def make_engine(url: str | URL, *, pool_timeout_s: float | None = None) -> Engine:
    """An engine for a SQLite file (WAL, foreign keys on, 30 s busy timeout) or PostgreSQL
    (pool_timeout_s: how long a checkout waits for a free connection; None: SQLAlchemy's)."""
    parsed = normalize_url(url)
    if parsed.get_backend_name() != "sqlite":
        if pool_timeout_s is None:
            return create_engine(parsed, pool_pre_ping=True)
        return create_engine(parsed, pool_pre_ping=True, pool_timeout=pool_timeout_s)
    if parsed.database and parsed.database != ":memory:" and not parsed.query.get("uri"):
        Path(parsed.database).parent.mkdir(parents=True, exist_ok=True)
    engine = create_engine(parsed)
    event.listen(engine, "connect", _set_sqlite_pragmas)
    return engine


def make_sessionmaker(engine: Engine) -> sessionmaker[Session]:
    """Session factory; objects stay readable after commit (no expiry)."""
    return sessionmaker(bind=engine, expire_on_commit=False)


@contextmanager
def session_scope(sessions: sessionmaker[Session]) -> Iterator[Session]:
    """A session committed when the block ends, rolled back if it raises."""
    with sessions() as session, session.begin():
        yield session


def _alembic_config() -> Config:
    """Alembic configuration pointing at the repository's migrations folder."""
    if not (MIGRATIONS_DIR / "env.py").is_file():
        raise FileNotFoundError(f"Alembic migrations not found in {MIGRATIONS_DIR}")
    config = Config()
    config.set_main_option("script_location", str(MIGRATIONS_DIR))
    return config


def upgrade(url: str | URL, revision: str = "head") -> None:
    """Migrate the database at `url` to `revision` (default: the latest schema).

    Any number of processes may call it at once (workers starting together on an empty
    database): the upgrade runs under a lock, a PostgreSQL advisory lock held by the migrating
    transaction or an exclusive lock on a file beside a SQLite database, so one migrates and the
    others, once it has committed, find nothing left to do."""
    engine = make_engine(url)
    try:
        with migration_transaction(engine) as connection, _quiet_alembic():
            before = MigrationContext.configure(connection).get_current_revision()
            config = _alembic_config()
            # env.py migrates this connection, so the SQLite pragmas above apply there too.
            config.attributes["connection"] = connection
            command.upgrade(config, revision)
            after = MigrationContext.configure(connection).get_current_revision()
    finally:
        engine.dispose()
    if after != before:
        log.info("catalog %s revision %s", "created at" if before is None else f"migrated from revision {before} to",
                 after)


@contextmanager
def _quiet_alembic() -> Iterator[None]:
    """Alembic's logger at WARNING while the block runs, unless DEBUG is asked for: its INFO
    lines (a line per migration, 14 and more on a first run) say nothing an operator acts on;
    `upgrade` says in one line what changed."""
    alembic_log = logging.getLogger("alembic")
    level = alembic_log.level
    if alembic_log.getEffectiveLevel() > logging.DEBUG:
        alembic_log.setLevel(logging.WARNING)
    try:
        yield
    finally:
        alembic_log.setLevel(level)


@contextmanager
def migration_transaction(engine: Engine) -> Iterator[Connection]:
    """A transaction on `engine` holding the migration lock (upgrade; the alembic command line
    through migrations/env.py). On SQLite the transaction runs with foreign keys off, and every
    reference is checked before it commits (ForeignKeyViolation, and nothing committed, if one
    dangles)."""
    with _migration_file_lock(engine.url), engine.connect() as connection:
        if connection.dialect.name != "sqlite":
            with connection.begin():
                if connection.dialect.name == "postgresql":
                    # Released when the transaction ends, that is after the migration committed.
                    connection.execute(text("SELECT pg_advisory_xact_lock(:key)"),
                                       {"key": MIGRATION_LOCK_KEY})
                yield connection
            return
        with _sqlite_transaction_without_foreign_keys(connection):
            yield connection


@contextmanager
def _sqlite_transaction_without_foreign_keys(connection: Connection) -> Iterator[None]:
    """One SQLite transaction, DDL included, with foreign keys off: SQLite changes a table's
    constraints by rebuilding it (Alembic's batch mode), and with foreign keys on, dropping the
    old table would delete the rows that reference it (ON DELETE CASCADE) or be refused
    (RESTRICT). The pragma is a no-op inside a transaction, so it is set before BEGIN; the
    driver's own transaction handling (an implicit BEGIN before DML only, none before DDL) is
    set aside so that the whole migration commits or rolls back as one."""
    driver = connection.connection.driver_connection
    assert driver is not None
    isolation_level = driver.isolation_level
    driver.isolation_level = None
    try:
        connection.exec_driver_sql("PRAGMA foreign_keys=OFF")
        connection.commit()  # ends SQLAlchemy's autobegun transaction; the driver began none
        with connection.begin():
            connection.exec_driver_sql("BEGIN")
            yield
            dangling = connection.exec_driver_sql("PRAGMA foreign_key_check").all()
            if dangling:
                raise ForeignKeyViolation(
                    "the migration left rows referencing missing ones (table, rowid, referenced "
                    f"table): {[tuple(row[:3]) for row in dangling[:10]]}")
    finally:
        connection.exec_driver_sql("PRAGMA foreign_keys=ON")
        connection.commit()
        driver.isolation_level = isolation_level


class ForeignKeyViolation(RuntimeError):
    """A migration left rows whose references point nowhere; it was rolled back."""


@contextmanager
def _migration_file_lock(url: URL) -> Iterator[None]:
    """An exclusive lock on `<database>.migrate.lock` for a SQLite file, else nothing."""
    if url.get_backend_name() != "sqlite" or not url.database or url.database == ":memory:":
        yield
        return
    with open(f"{url.database}.migrate.lock", "a") as handle:
        fcntl.flock(handle, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(handle, fcntl.LOCK_UN)
