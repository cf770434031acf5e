"""Databases for the service tests: an empty SQLite file per test, and `db_url`, which runs a
test on SQLite and on PostgreSQL (the server fixtures are in tests/conftest.py)."""

from __future__ import annotations

from pathlib import Path

import pytest
from sqlalchemy.orm import Session, sessionmaker

from pwm.frames import unit_to_latlon
from pwm.maplets import MapletGrid
from service.models import Maplet


@pytest.fixture
def sqlite_url(tmp_path: Path) -> str:
    """A SQLite database file of its own for one test (not created yet)."""
    return f"sqlite:///{tmp_path / 'catalog.sqlite'}"


@pytest.fixture(params=["sqlite", "postgres"])
def db_url(request: pytest.FixtureRequest) -> str:
    """Each test that takes it runs once on SQLite and once on PostgreSQL."""
    return request.getfixturevalue(f"{request.param}_url")


@pytest.fixture
def catalog(db_url: str, open_catalog_at) -> sessionmaker[Session]:
    """Sessions on a freshly migrated catalog (SQLite and PostgreSQL)."""
    return open_catalog_at(db_url)


def catalogue_maplets(session: Session, maplets: list[MapletGrid]) -> None:
    """Maplet rows for the grids, as an earlier downlink's tiling would have left them."""
    for m in maplets:
        lat, lon = unit_to_latlon(m.frame.origin)
        session.add(Maplet(name=m.name, center_lat_deg=float(lat), center_lon_deg=float(lon),
                           origin_x_km=float(m.frame.origin[0]), origin_y_km=float(m.frame.origin[1]),
                           origin_z_km=float(m.frame.origin[2]), rotation=m.frame.rotation.tolist(),
                           size_km=(m.n - 1) * m.spacing_km, gsd_m=m.spacing_km * 1e3, nodes_per_side=m.n))
