"""The catalog's foundation on real SQLite and PostgreSQL: migrations, schema, constraints,
lineage, settings; and the Redis server fixture later work relies on."""

from __future__ import annotations

import os
import subprocess
import sys
from datetime import UTC, datetime, timedelta, timezone
from pathlib import Path

import pytest
import redis
from alembic.autogenerate import compare_metadata
from alembic.migration import MigrationContext
from alembic.script import ScriptDirectory
from sqlalchemy import inspect, select, text
from sqlalchemy.exc import IntegrityError, StatementError
from sqlalchemy.orm import Session, sessionmaker

from service.db import MIGRATIONS_DIR, make_engine, make_sessionmaker, session_scope, upgrade
from service.rows import (
    Base,
    Downlink,
    Image,
    ImageStatus,
    Job,
    JobKind,
    Maplet,
    MapletRevision,
    ModelKind,
    ModelVersion,
)
from service.settings import CATALOG_FILENAME, Settings, get_settings

REPO = Path(__file__).resolve().parents[2]


def _image(lidvid: str) -> Image:
    lid, vid = lidvid.split("::")
    return Image(
        lidvid=lidvid,
        lid=lid,
        vid=vid,
        label_path=f"{lid}.xml",
        data_path=f"{lid}.img",
        sha256="0" * 64,
        size_bytes=1024,
        status=ImageStatus.ACCEPTED,
    )


def _maplet(name: str) -> Maplet:
    identity = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]
    return Maplet(
        name=name, center_lat_deg=10.0, center_lon_deg=20.0, origin_x_km=0.2, origin_y_km=0.05,
        origin_z_km=0.03, rotation=identity, size_km=0.03, gsd_m=0.05, nodes_per_side=601,
    )


def _revision(maplet: Maplet, number: int, input_hash: str) -> MapletRevision:
    return MapletRevision(
        maplet=maplet, revision=number, input_hash=input_hash, mode="photoclinometry",
        artifact_path=f"maplets/{maplet.name}/{number}.npz", sha256="f" * 64,
    )


def _schema_differences(url: str) -> list:
    engine = make_engine(url)
    try:
        with engine.connect() as connection:
            return compare_metadata(MigrationContext.configure(connection), Base.metadata)
    finally:
        engine.dispose()


def test_migrations_build_the_schema_of_the_models(db_url: str) -> None:
    upgrade(db_url)
    upgrade(db_url)  # a second run finds nothing to do
    engine = make_engine(db_url)
    with engine.connect() as connection:
        current = MigrationContext.configure(connection).get_current_revision()
        tables = set(inspect(connection).get_table_names())
    engine.dispose()
    config_head = ScriptDirectory(str(MIGRATIONS_DIR)).get_current_head()
    assert current == config_head
    assert tables == set(Base.metadata.tables) | {"alembic_version"}
    assert _schema_differences(db_url) == []


def test_processes_migrating_an_empty_database_at_once_all_succeed(db_url: str) -> None:
    # As workers starting together do: the migration lock lets one migrate, the rest wait and
    # find nothing to do.
    code = f"from service.db import upgrade; upgrade({db_url!r})"
    processes = [subprocess.Popen([sys.executable, "-c", code], cwd=REPO, stderr=subprocess.PIPE,
                                  text=True) for _ in range(3)]
    errors = [p.communicate(timeout=120)[1] for p in processes]
    assert [p.returncode for p in processes] == [0, 0, 0], errors
    assert _schema_differences(db_url) == []


def test_alembic_command_line_downgrades_and_the_service_upgrades_again(
    db_url: str, tmp_path: Path
) -> None:
    upgrade(db_url)
    # The command line finds alembic.ini's migrations from any working directory and takes the
    # database from PWM_DATABASE_URL.
    env = {**os.environ, "PWM_DATABASE_URL": db_url}
    result = subprocess.run(
        [sys.executable, "-m", "alembic", "-c", str(REPO / "alembic.ini"), "downgrade", "base"],
        cwd=tmp_path, env=env, capture_output=True, text=True,
    )
    assert result.returncode == 0, result.stderr
    engine = make_engine(db_url)
    with engine.connect() as connection:
        assert set(inspect(connection).get_table_names()) <= {"alembic_version"}
    engine.dispose()
    upgrade(db_url)
    assert _schema_differences(db_url) == []


def test_lidvid_is_unique(catalog: sessionmaker[Session]) -> None:
    with session_scope(catalog) as session:
        session.add(_image("urn:nasa:pds:orex.ocams:data_calibrated:20190321t190500s_pol::1.0"))
    with pytest.raises(IntegrityError), session_scope(catalog) as session:
        session.add(_image("urn:nasa:pds:orex.ocams:data_calibrated:20190321t190500s_pol::1.0"))
    with session_scope(catalog) as session:
        session.add(_image("urn:nasa:pds:orex.ocams:data_calibrated:20190321t190500s_pol::2.0"))
    with session_scope(catalog) as session:
        assert len(session.scalars(select(Image)).all()) == 2


def test_input_hash_and_revision_number_are_unique_per_maplet(
    catalog: sessionmaker[Session],
) -> None:
    with session_scope(catalog) as session:
        first, second = _maplet("m0001"), _maplet("m0002")
        session.add_all([_revision(first, 1, "a" * 64), _revision(second, 1, "a" * 64)])
    with pytest.raises(IntegrityError), session_scope(catalog) as session:
        maplet = session.scalars(select(Maplet).filter_by(name="m0001")).one()
        session.add(_revision(maplet, 2, "a" * 64))
    with pytest.raises(IntegrityError), session_scope(catalog) as session:
        maplet = session.scalars(select(Maplet).filter_by(name="m0001")).one()
        session.add(_revision(maplet, 1, "b" * 64))
    with session_scope(catalog) as session:
        maplet = session.scalars(select(Maplet).filter_by(name="m0001")).one()
        session.add(_revision(maplet, 2, "b" * 64))
    with session_scope(catalog) as session:
        counts = {m.name: len(m.revisions) for m in session.scalars(select(Maplet))}
    assert counts == {"m0001": 2, "m0002": 1}


def test_model_version_lineage_round_trips(catalog: sessionmaker[Session]) -> None:
    with session_scope(catalog) as session:
        downlinks = [Downlink(name=f"dl{i}", path=f"/downlinks/dl{i}") for i in (1, 2)]
        maplet = _maplet("m0001")
        old, new = _revision(maplet, 1, "a" * 64), _revision(maplet, 2, "b" * 64)
        maplet.current_revision = new
        start = ModelVersion(
            version=1, kind=ModelKind.START, downlinks=downlinks[:1], maplet_revisions=[old]
        )
        refined = ModelVersion(
            version=2, kind=ModelKind.REFINED, parent=start, downlinks=downlinks,
            maplet_revisions=[new], artifacts={"mesh": {"path": "v2.obj", "sha256": "c" * 64}},
            released=True, release_tag="bennu-v2",
        )
        session.add_all([start, refined])
    with session_scope(catalog) as session:
        refined = session.scalars(select(ModelVersion).filter_by(version=2)).one()
        assert refined.parent is not None and refined.parent.version == 1
        assert [child.version for child in refined.parent.children] == [2]
        assert sorted(d.name for d in refined.downlinks) == ["dl1", "dl2"]
        assert [(r.maplet.name, r.revision) for r in refined.maplet_revisions] == [("m0001", 2)]
        assert [r.revision for r in refined.parent.maplet_revisions] == [1]
        assert refined.artifacts["mesh"]["path"] == "v2.obj"
        maplet = session.scalars(select(Maplet)).one()
        assert maplet.current_revision is not None and maplet.current_revision.revision == 2
    with pytest.raises(IntegrityError), session_scope(catalog) as session:
        session.add(ModelVersion(version=3, kind=ModelKind.IMPORTED, release_tag="bennu-v2"))


def test_model_version_content_is_immutable_but_can_be_released(sqlite_url: str) -> None:
    upgrade(sqlite_url)
    sessions = make_sessionmaker(make_engine(sqlite_url))
    with session_scope(sessions) as session:
        session.add(ModelVersion(version=1, kind=ModelKind.START, statistics={"faces": 10}))
    with pytest.raises(ValueError, match="immutable"), session_scope(sessions) as session:
        session.scalars(select(ModelVersion)).one().statistics = {"faces": 11}
    with pytest.raises(ValueError, match="immutable"), session_scope(sessions) as session:
        version = session.scalars(select(ModelVersion)).one()
        version.downlinks.append(Downlink(name="late", path="/downlinks/late"))
    with session_scope(sessions) as session:
        version = session.scalars(select(ModelVersion)).one()
        version.released, version.release_tag = True, "bennu-v1"
        session.add(ModelVersion(version=2, kind=ModelKind.REFINED, parent=version))
    with session_scope(sessions) as session:
        version = session.scalars(select(ModelVersion).filter_by(version=1)).one()
        assert (version.statistics, version.release_tag, len(version.children)) == (
            {"faces": 10}, "bennu-v1", 1,
        )
        assert session.scalars(select(Downlink)).all() == []


def test_database_enforces_foreign_keys_and_enumerations(catalog: sessionmaker[Session]) -> None:
    with pytest.raises(IntegrityError), session_scope(catalog) as session:
        session.execute(
            text("INSERT INTO maplet_revisions (maplet_id, revision, input_hash, mode,"
                 " created_at, statistics, artifact_path, sha256)"
                 " VALUES (999, 1, 'h', 'm', :now, '{}', 'p', 's')"),
            {"now": datetime.now(UTC)},
        )
    with pytest.raises(IntegrityError), session_scope(catalog) as session:
        session.execute(
            text("INSERT INTO jobs (kind, key, status, attempts, progress, created_at)"
                 " VALUES ('refine', 'k', 'paused', 0, 0, :now)"),
            {"now": datetime.now(UTC)},
        )
    with session_scope(catalog) as session:
        assert session.scalars(select(Job)).all() == []


def test_timestamps_are_stored_and_returned_in_utc(catalog: sessionmaker[Session]) -> None:
    created = datetime(2019, 3, 21, 21, 5, tzinfo=timezone(timedelta(hours=2)))
    with session_scope(catalog) as session:
        session.add(Job(kind=JobKind.REFINE, key="refine:m0001:1", created_at=created))
    with session_scope(catalog) as session:
        job = session.scalars(select(Job)).one()
        assert job.created_at == created and job.created_at.utcoffset() == timedelta(0)
        assert job.created_at.hour == 19
        assert (job.status, job.attempts, job.progress) == ("queued", 0, 0.0)
    with pytest.raises(StatementError, match="naive"), session_scope(catalog) as session:
        session.add(Job(kind=JobKind.FUSE, key="fuse:1", created_at=datetime(2019, 3, 21)))


def test_sqlite_connections_are_in_wal_mode_with_foreign_keys(sqlite_url: str) -> None:
    engine = make_engine(sqlite_url)
    with engine.connect() as first, engine.connect() as second:
        for connection in (first, second):
            assert connection.exec_driver_sql("PRAGMA journal_mode").scalar() == "wal"
            assert connection.exec_driver_sql("PRAGMA foreign_keys").scalar() == 1
            assert connection.exec_driver_sql("PRAGMA busy_timeout").scalar() == 30_000
    engine.dispose()


def test_plain_postgresql_urls_use_psycopg3(postgres_url: str) -> None:
    plain = postgres_url.replace("postgresql+psycopg://", "postgresql://")
    engine = make_engine(plain)
    with engine.connect() as connection:
        assert connection.dialect.driver == "psycopg"
        assert connection.execute(text("SELECT 1")).scalar() == 1
    engine.dispose()


def test_session_scope_commits_or_rolls_back(sqlite_url: str) -> None:
    upgrade(sqlite_url)
    sessions = make_sessionmaker(make_engine(sqlite_url))
    with session_scope(sessions) as session:
        session.add(Downlink(name="dl1", path="/downlinks/dl1"))
    with pytest.raises(RuntimeError), session_scope(sessions) as session:
        session.add(Downlink(name="dl2", path="/downlinks/dl2"))
        session.flush()
        raise RuntimeError("ingest failed")
    with session_scope(sessions) as session:
        assert [d.name for d in session.scalars(select(Downlink))] == ["dl1"]


def test_settings_default_to_a_catalog_in_the_data_dir(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    monkeypatch.delenv("PWM_DATABASE_URL", raising=False)
    monkeypatch.setenv("PWM_DATA_DIR", str(tmp_path / "data"))
    monkeypatch.setenv("PWM_API_TOKEN", "s3cret")
    settings = Settings()
    assert settings.data_dir == tmp_path / "data"
    assert settings.database_url == f"sqlite:///{tmp_path / 'data' / CATALOG_FILENAME}"
    assert settings.broker_url is None
    assert settings.api_token is not None and settings.api_token.get_secret_value() == "s3cret"
    assert "s3cret" not in repr(settings)
    upgrade(settings.database_url)  # creates the data directory
    assert (tmp_path / "data" / CATALOG_FILENAME).is_file()

    monkeypatch.setenv("PWM_DATABASE_URL", "postgresql://catalog@db/pwm")
    monkeypatch.setenv("PWM_BROKER_URL", "redis://broker:6379/0")
    get_settings.cache_clear()
    try:
        settings = get_settings()
        assert get_settings() is settings
        assert (settings.database_url, settings.broker_url) == (
            "postgresql://catalog@db/pwm", "redis://broker:6379/0",
        )
    finally:
        get_settings.cache_clear()


def test_redis_server_answers(redis_url: str) -> None:
    client = redis.Redis.from_url(redis_url)
    try:
        assert client.ping() is True
        client.set("pwm:test", "ready")
        assert client.get("pwm:test") == b"ready"
    finally:
        client.close()
