"""Databases for the service tests: an empty SQLite file per test, and `db_url`, which runs a
test on SQLite and on PostgreSQL (the server fixtures are in tests/conftest.py)."""

from __future__ import annotations

import os
from collections.abc import Iterator
from pathlib import Path

import pytest
from sqlalchemy.orm import Session, sessionmaker
from typer.testing import CliRunner

from service.settings import get_settings


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



@pytest.fixture
def pwm(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[CliRunner]:
    """A runner of `pwm` on a new SQLite catalog in tmp_path/data, no other PWM_* setting in the
    environment, the settings read afresh."""
    for variable in [v for v in os.environ if v.startswith("PWM_")]:
        monkeypatch.delenv(variable)
    monkeypatch.setenv("PWM_DATA_DIR", str(tmp_path / "data"))
    get_settings.cache_clear()
    yield CliRunner()
    get_settings.cache_clear()
