"""Migration 0016 (a version kind `lidar`) on real SQLite and PostgreSQL: the versions stored
before it, their parents and lineage rows come through unchanged, and a lidar version can then
be stored; the enumeration still refuses what it does not know. And service.db's SQLite
migration transaction: a table rebuilt keeps the rows referencing it, a migration leaving a
reference dangling is rolled back whole (its DDL too), foreign keys are on again after."""

from __future__ import annotations

import pytest
from sqlalchemy import text
from sqlalchemy.exc import IntegrityError

from service.db import (
    ForeignKeyViolation,
    make_engine,
    make_sessionmaker,
    migration_transaction,
    session_scope,
    upgrade,
)
from service.rows import Downlink, Maplet, MapletRevision, ModelKind, ModelVersion

_READ = {
    "versions": "SELECT id, version, kind, parent_id, released, release_tag FROM model_versions "
                "ORDER BY id",
    "revisions": "SELECT * FROM model_version_maplet_revisions ORDER BY 1, 2",
    "downlinks": "SELECT * FROM model_version_downlinks ORDER BY 1, 2",
}


def _read(url: str) -> dict[str, list[tuple]]:
    engine = make_engine(url)
    try:
        with engine.connect() as connection:
            return {name: [tuple(row) for row in connection.execute(text(sql))]
                    for name, sql in _READ.items()}
    finally:
        engine.dispose()


def test_versions_and_lineage_survive_the_lidar_kind_migration(db_url: str) -> None:
    upgrade(db_url, "0015")
    # Two versions (the second a child of the first, released) with their lineage; the rows'
    # tables are at revision 0015 as the models declare them, model_versions.kind aside.
    engine = make_engine(db_url)
    try:
        with session_scope(make_sessionmaker(engine)) as session:
            maplet = Maplet(name="m0003", center_lat_deg=1.0, center_lon_deg=2.0, origin_x_km=0.2,
                            origin_y_km=0.0, origin_z_km=0.0, rotation=[1.0, 0, 0, 0, 1, 0, 0, 0, 1],
                            size_km=0.03, gsd_m=0.05, nodes_per_side=11)
            revision = MapletRevision(maplet=maplet, revision=1, input_hash="a",
                                      mode="photoclinometry", artifact_path="m.npz", sha256="f")
            downlink = Downlink(name="dl7", path="/downlinks/dl7")
            start = ModelVersion(version=1, kind=ModelKind.START, downlinks=[downlink],
                                 maplet_revisions=[revision])
            session.add_all([start, ModelVersion(
                version=2, kind=ModelKind.REFINED, parent=start, downlinks=[downlink],
                maplet_revisions=[revision], statistics={"faces": 4}, released=True,
                release_tag="v2")])
    finally:
        engine.dispose()
    before = _read(db_url)
    assert len(before["versions"]) == 2 and len(before["revisions"]) == 2

    upgrade(db_url)
    assert _read(db_url) == before

    engine = make_engine(db_url)
    try:
        with engine.begin() as connection:
            connection.execute(text(
                "INSERT INTO model_versions (version, kind, parent_id, created_at, statistics, "
                "artifacts, released) VALUES (3, 'lidar', :parent, '2026-12-06 10:00:00+00:00', "
                "'{}', '{}', false)"), {"parent": before["versions"][1][0]})
        with pytest.raises(IntegrityError), engine.begin() as connection:
            connection.execute(text(
                "INSERT INTO model_versions (version, kind, created_at, statistics, artifacts, "
                "released) VALUES (4, 'radar', '2026-12-06 10:00:00+00:00', '{}', '{}', false)"))
        # The rebuilt table's references are enforced again (SQLite: foreign keys back on).
        with pytest.raises(IntegrityError), engine.begin() as connection:
            connection.execute(text("INSERT INTO model_version_downlinks VALUES (99, :downlink)"),
                               {"downlink": before["downlinks"][0][1]})
        with pytest.raises(IntegrityError), engine.begin() as connection:
            connection.execute(text("DELETE FROM downlinks"))
    finally:
        engine.dispose()


def test_a_sqlite_migration_leaving_a_dangling_reference_is_rolled_back_whole(sqlite_url: str) -> None:
    engine = make_engine(sqlite_url)
    try:
        with engine.begin() as connection:
            connection.execute(text("CREATE TABLE parent (id INTEGER PRIMARY KEY)"))
            connection.execute(text("CREATE TABLE child (id INTEGER PRIMARY KEY, "
                                    "parent_id INTEGER REFERENCES parent (id) ON DELETE CASCADE)"))
            connection.execute(text("INSERT INTO parent VALUES (1)"))
            connection.execute(text("INSERT INTO child VALUES (1, 1)"))
        # inside, foreign keys are off: a rebuild of parent keeps its child rows...
        with migration_transaction(engine) as connection:
            connection.execute(text("CREATE TABLE parent_new (id INTEGER PRIMARY KEY, note TEXT)"))
            connection.execute(text("INSERT INTO parent_new (id) SELECT id FROM parent"))
            connection.execute(text("DROP TABLE parent"))
            connection.execute(text("ALTER TABLE parent_new RENAME TO parent"))
        with engine.connect() as connection:
            assert connection.execute(text("SELECT parent_id FROM child")).scalars().all() == [1]
            assert "note" in [row[1] for row in connection.execute(text("PRAGMA table_info(parent)"))]
        # ...but a migration that leaves a reference dangling is refused, its DDL undone too
        with pytest.raises(ForeignKeyViolation, match="child"), migration_transaction(engine) as connection:
            connection.execute(text("CREATE TABLE other (id INTEGER PRIMARY KEY)"))
            connection.execute(text("DELETE FROM parent"))
        with engine.connect() as connection:
            assert connection.execute(text("SELECT count(*) FROM parent")).scalar_one() == 1
            assert connection.execute(text("SELECT count(*) FROM sqlite_master WHERE name = 'other'")
                                      ).scalar_one() == 0
            assert connection.execute(text("PRAGMA foreign_keys")).scalar_one() == 1
    finally:
        engine.dispose()
