"""Fixtures shared across test folders: one simulated `tiny` downlink per session, and real
database and broker servers: a throwaway PostgreSQL cluster and a Redis server, started once per
session on free local ports.

The servers come from Debian's `postgresql` and `redis-server` packages (scripts/test.sh
installs them); when they are missing the fixtures fail, they never skip.
"""

from __future__ import annotations

import os
import pwd
import shutil
import socket
import subprocess
import tempfile
import time
import uuid
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import psycopg
import pytest
import trimesh
from sqlalchemy.orm import Session, sessionmaker

from pwm.knowledge import NavigationErrors
from pwm.maplets import MapletGrid
from pwm.mesh import Mesh
from pwm.raytrace import RayTracer
from pwm.simulate.campaign import simulate
from pwm.simulate.scenarios import get_scenario
from pwm.tiling import sample_surface, tile
from service.db import make_engine, make_sessionmaker, upgrade

SHARED_DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
START_TIMEOUT_S = 30.0


def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def _postgres_bindir() -> Path:
    candidates = []
    if pg_config := shutil.which("pg_config"):
        result = subprocess.run([pg_config, "--bindir"], capture_output=True, text=True)
        if result.returncode == 0:
            candidates.append(Path(result.stdout.strip()))
    versions = [p for p in Path("/usr/lib/postgresql").glob("*/bin") if p.parent.name.isdigit()]
    candidates += sorted(versions, key=lambda p: int(p.parent.name), reverse=True)
    for bindir in candidates:
        if (bindir / "initdb").is_file() and (bindir / "pg_ctl").is_file():
            return bindir
    pytest.fail(
        "PostgreSQL server binaries (initdb, pg_ctl) not found via pg_config or in "
        "/usr/lib/postgresql/*/bin: install Debian's `postgresql` package (scripts/test.sh does)",
        pytrace=False,
    )


def _run(command: list[str], what: str, log: Path | None = None) -> None:
    result = subprocess.run(command, capture_output=True, text=True)
    if result.returncode != 0:
        server_log = log.read_text() if log is not None and log.exists() else ""
        pytest.fail(
            f"{what} failed ({result.returncode}):\n{result.stdout}\n{result.stderr}\n{server_log}"
        )


@dataclass(frozen=True)
class PostgresServer:
    host: str
    port: int
    user: str

    def url(self, database: str) -> str:
        return f"postgresql+psycopg://{self.user}@{self.host}:{self.port}/{database}"

    def admin(self) -> psycopg.Connection:
        return psycopg.connect(
            host=self.host, port=self.port, user=self.user, dbname="postgres", autocommit=True
        )


@pytest.fixture(scope="session")
def postgres_server() -> Iterator[PostgresServer]:
    """A PostgreSQL cluster in a temporary directory, on 127.0.0.1 and its own socket dir."""
    bindir = _postgres_bindir()
    # PostgreSQL refuses to run as root: run it as the `postgres` user the package creates.
    as_user: list[str] = []
    owner = None
    if os.geteuid() == 0:
        try:
            owner = pwd.getpwnam("postgres")
        except KeyError:
            pytest.fail("running as root, but there is no `postgres` user to run PostgreSQL as")
        as_user = ["runuser", "-u", "postgres", "--"]
    # Not under pytest's tmp_path: its root is private to the current user.
    base = Path(tempfile.mkdtemp(prefix="pwm-pg-"))
    data, sockets, log = base / "data", base / "sockets", base / "server.log"
    sockets.mkdir()
    if owner is not None:
        for path in (base, sockets):
            os.chown(path, owner.pw_uid, owner.pw_gid)
    port = _free_port()
    server = PostgresServer(host="127.0.0.1", port=port, user="postgres")
    options = (
        f"-p {port} -k {sockets} -c listen_addresses=127.0.0.1"
        " -c fsync=off -c synchronous_commit=off -c full_page_writes=off"
    )
    try:
        _run(
            [*as_user, str(bindir / "initdb"), "-D", str(data), "-U", server.user,
             "--auth=trust", "--encoding=UTF8", "--no-locale", "--no-sync"],
            "initdb",
        )
        _run(
            [*as_user, str(bindir / "pg_ctl"), "-D", str(data), "-l", str(log), "-o", options,
             "-w", "-t", str(int(START_TIMEOUT_S)), "start"],
            "pg_ctl start",
            log,
        )
        yield server
    finally:
        if (data / "postmaster.pid").exists():
            subprocess.run(
                [*as_user, str(bindir / "pg_ctl"), "-D", str(data), "-m", "immediate", "-w",
                 "stop"],
                capture_output=True,
            )
        shutil.rmtree(base, ignore_errors=True)


@pytest.fixture
def postgres_url(postgres_server: PostgresServer) -> Iterator[str]:
    """An empty PostgreSQL database of its own for one test, dropped afterwards."""
    name = f"pwm_test_{uuid.uuid4().hex[:12]}"
    with postgres_server.admin() as admin:
        admin.execute(f'CREATE DATABASE "{name}"')
    yield postgres_server.url(name)
    with postgres_server.admin() as admin:
        admin.execute(f'DROP DATABASE "{name}" WITH (FORCE)')


class RedisServer:
    """A redis-server without persistence on a local port, which a test may stop and start
    again (on the same port, empty: as a restarted broker without persistence comes back)."""

    def __init__(self, workdir: Path) -> None:
        executable = shutil.which("redis-server")
        if executable is None:
            pytest.fail(
                "redis-server not found: install Debian's `redis-server` package "
                "(scripts/test.sh does)",
                pytrace=False,
            )
        self.executable, self.workdir, self.port = executable, workdir, _free_port()
        self.log = workdir / "server.log"
        self.process: subprocess.Popen | None = None

    def url(self, database: int = 0) -> str:
        return f"redis://127.0.0.1:{self.port}/{database}"

    def start(self) -> None:
        self.process = subprocess.Popen(
            [self.executable, "--port", str(self.port), "--bind", "127.0.0.1", "--dir",
             str(self.workdir), "--logfile", str(self.log), "--save", "", "--appendonly", "no",
             "--daemonize", "no"],
            stdout=subprocess.DEVNULL, stderr=subprocess.STDOUT,
        )
        deadline = time.monotonic() + START_TIMEOUT_S
        while True:
            if self.process.poll() is not None:
                server_log = self.log.read_text() if self.log.exists() else ""
                pytest.fail(f"redis-server exited ({self.process.returncode}):\n{server_log}")
            try:
                socket.create_connection(("127.0.0.1", self.port), timeout=0.5).close()
                return
            except OSError:
                if time.monotonic() > deadline:
                    pytest.fail(f"redis-server did not accept connections on port {self.port}")
                time.sleep(0.05)

    def stop(self, *, kill: bool = False) -> None:
        """Stop the server (SIGKILL with `kill`, as a crash would), losing what it held."""
        if self.process is None:
            return
        if kill:
            self.process.kill()
        else:
            self.process.terminate()
        try:
            self.process.wait(timeout=10)
        except subprocess.TimeoutExpired:
            self.process.kill()
            self.process.wait()
        self.process = None


@pytest.fixture(scope="session")
def redis_url(tmp_path_factory: pytest.TempPathFactory) -> Iterator[str]:
    """A Redis server without persistence on a free local port, for the session."""
    server = RedisServer(tmp_path_factory.mktemp("redis"))
    try:
        server.start()
        yield server.url()
    finally:
        server.stop()


@pytest.fixture
def redis_server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[RedisServer]:
    """A Redis server of one test's own, started; the test may stop and restart it."""
    server = RedisServer(tmp_path_factory.mktemp("redis-own"))
    try:
        server.start()
        yield server
    finally:
        server.stop()


# The elongated body of `long_body`: its lattice step (km) and the blocks (lattice steps a side)
# that it spans five of along its length.
LONG_VOXEL, LONG_BLOCK = 0.006, 12


@pytest.fixture(scope="session")
def long_body() -> tuple[Mesh, list[MapletGrid]]:
    """An elongated body (0.3 x 0.06 x 0.06 km) tiled with 11 x 11-node maplets of LONG_VOXEL
    on it (albedo 0.1), and a base 3 m larger: a maplet at one end reaches few of the blocks
    of LONG_BLOCK lattice steps that its fusion spans (pwm.blocks)."""
    axes = np.array([0.15, 0.03, 0.03])
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=1.0)
    truth = Mesh(np.asarray(sphere.vertices) * axes, np.asarray(sphere.faces))
    tracer = RayTracer(truth)
    maplets = []
    for maplet in tile(truth, spacing_km=LONG_VOXEL, nodes=11, overlap=0.25):
        maplet.heights, _ = sample_surface(tracer, maplet)
        maplet.albedo = np.full_like(maplet.heights, 0.1)
        maplets.append(maplet)
    coarse = trimesh.creation.icosphere(subdivisions=3, radius=1.0)
    return Mesh(np.asarray(coarse.vertices) * (axes + 0.003), np.asarray(coarse.faces)), maplets


@pytest.fixture(scope="session")
def tiny_sim(tmp_path_factory) -> Path:
    """OUT directory of `pwm simulate OUT --scenario tiny --seed 3 --with-start-model` (downlink/
    and truth/)."""
    out = tmp_path_factory.mktemp("tiny") / "sim"
    simulate(out, scenario=get_scenario("tiny"), seed=3, with_start_model=True)
    return out


@pytest.fixture(scope="session")
def tiny_nav_sim(tmp_path_factory) -> Path:
    """`pwm simulate OUT --scenario tiny --seed 3 --knowledge-error nav:3,1,50,20 --with-start-model`:
    kernels with navigation-like pose errors, which state that knowledge."""
    out = tmp_path_factory.mktemp("tiny-nav") / "sim"
    simulate(out, scenario=get_scenario("tiny"), seed=3, with_start_model=True,
             knowledge=NavigationErrors(along_m=3.0, cross_m=1.0, misalign_urad=50.0, drift_urad=20.0))
    return out


@pytest.fixture(scope="session")
def global_tiny_sim(tmp_path_factory) -> Path:
    """OUT directory of `pwm simulate OUT --scenario global-tiny --seed 2`: a whole-body survey
    that comes with no shape model."""
    out = tmp_path_factory.mktemp("global-tiny") / "sim"
    simulate(out, scenario=get_scenario("global-tiny"), seed=2)
    return out


@pytest.fixture(scope="session")
def castalia_tiny_sim(tmp_path_factory) -> Path:
    """OUT directory of `pwm simulate OUT --scenario castalia-tiny --seed 1`: a contact binary's
    whole-body survey, with no shape model, whose labels name the body by number."""
    out = tmp_path_factory.mktemp("castalia-tiny") / "sim"
    simulate(out, scenario=get_scenario("castalia-tiny"), seed=1)
    return out


@pytest.fixture(scope="session")
def campaign_tiny_sim(tmp_path_factory) -> Path:
    """OUT directory of `pwm simulate OUT --scenario campaign-tiny --seed 4 --with-start-model`:
    a survey with its start model, then two site downlinks, in time order under downlinks/."""
    from typer.testing import CliRunner

    from service.cli import app

    out = tmp_path_factory.mktemp("campaign-tiny") / "sim"
    result = CliRunner().invoke(app, ["simulate", str(out), "--scenario", "campaign-tiny", "--seed", "4",
                                      "--with-start-model"])
    assert result.exit_code == 0, result.output
    return out


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """The project's shared real data (PROVENANCE.md there says where each file comes from)."""
    assert SHARED_DATA.is_dir(), f"shared data missing at {SHARED_DATA}"
    return SHARED_DATA


@pytest.fixture(scope="session")
def ryugu_sim(tmp_path_factory) -> Path:
    """OUT directory of `pwm simulate OUT --scenario ryugu-tiny --seed 3`: a second mission
    (Hayabusa2's ONC-T at Ryugu), simulated through the command line."""
    from typer.testing import CliRunner

    from service.cli import app

    out = tmp_path_factory.mktemp("ryugu") / "sim"
    result = CliRunner().invoke(app, ["simulate", str(out), "--scenario", "ryugu-tiny", "--seed", "3",
                                      "--with-start-model"])
    assert result.exit_code == 0, result.output
    return out


@pytest.fixture
def open_catalog_at() -> Iterator[Callable[[str], sessionmaker[Session]]]:
    """Sessions on the database at a URL, migrated to head; the engines are disposed afterwards."""
    engines = []

    def open_at(url: str) -> sessionmaker[Session]:
        upgrade(url)
        engines.append(make_engine(url))
        return make_sessionmaker(engines[-1])

    yield open_at
    for engine in engines:
        engine.dispose()


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Mark the tests that need a server or the browser, by the fixtures they use, so that
    `-m "not postgres and not redis and not browser"` runs the rest on its own."""
    for item in items:
        names = set(getattr(item, "fixturenames", ()))
        callspec = getattr(item, "callspec", None)
        params = callspec.params if callspec is not None else {}
        if "postgres_server" in names or params.get("db_url") == "postgres":
            item.add_marker(pytest.mark.postgres)
        if "redis_url" in names or "redis_server" in names:
            item.add_marker(pytest.mark.redis)
        if "browser" in names:
            item.add_marker(pytest.mark.browser)
