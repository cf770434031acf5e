"""Benchmark operations: downlink-to-version latency and refinement throughput of `pwm worker`
processes on a Redis broker and a PostgreSQL catalog. Prints two tables.

    .venv/bin/python bench/operations.py [--workers 1 2] [--nodes 40] [--radius-km 0.004]
                                         [--revisit-images 10] [--scratch DIR]

For each worker count N: a fresh catalog and one `pwm worker --concurrency N`. The tiny
scenario's downlink (simulated with seed 3, or --downlink) is ingested against its start model,
the region within --radius-km of where its images look is tiled into maplets of --nodes nodes,
and every maplet is refined and fused: throughput is the maplets refined per minute between the
first refinement's start and the last one's end (jobs table). Then a revisit of
--revisit-images windows of those exposures aimed at one corner (pwm.simulate.windows) is
submitted: latency is from its submission to the new version's publication, with the ingest,
refinement and fusion stages beside it. Aim: 2 processes refine >= 1.7 times as fast as one on
2 free cores.

The servers are the tests' throwaway PostgreSQL cluster and Redis server (tests/conftest.py), so
the bench needs what the tests need (Debian's postgresql and redis-server).
"""

from __future__ import annotations

import argparse
import contextlib
import os
import subprocess
import sys
import tempfile
import time
import uuid
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from types import SimpleNamespace

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from celery import Celery  # noqa: E402
from sqlalchemy import select  # noqa: E402
from sqlalchemy.orm import Session, sessionmaker  # noqa: E402

from bench.catalog import postgres  # noqa: E402
from pwm.simulate.campaign import simulate  # noqa: E402
from pwm.simulate.scenarios import get_scenario  # noqa: E402
from pwm.simulate.windows import window_downlink  # noqa: E402
from service.db import make_engine, make_sessionmaker, upgrade  # noqa: E402
from service.rows import Job, JobKind, ModelVersion  # noqa: E402
from tests import conftest as test_servers  # noqa: E402
from workers.app import WorkerSettings, make_app  # noqa: E402
from workers.tasks import ingest_downlink, ingest_key  # noqa: E402

PWM = Path(sys.executable).parent / "pwm"
READY_TIMEOUT_S = 120.0
DOWNLINK_TIMEOUT_S = 1800.0
# The revisit: windows of 48 px (2.4 m at 5 cm) over one corner of the tiled region.
REVISIT_WINDOW_PX, REVISIT_FIRST_PX = 48, (200, 200)


@dataclass
class Stage:
    """A downlink's path to a version (s): ingest, refinement (of `maplets`, with the time its
    jobs ran summed in busy_s), fusion, and from submission to publication."""

    maplets: int
    ingest_s: float
    refine_s: float
    busy_s: float
    fuse_s: float
    latency_s: float

    @property
    def maplets_per_min(self) -> float:
        return 60.0 * self.maplets / self.refine_s if self.refine_s > 0 else float("nan")


@contextlib.contextmanager
def redis_server(workdir: Path) -> Iterator[str]:
    # __wrapped__: the fixture's own generator function; it only asks its factory for a folder.
    factory = SimpleNamespace(mktemp=lambda name: workdir)
    with contextlib.contextmanager(test_servers.redis_url.__wrapped__)(factory) as url:
        yield url


@contextlib.contextmanager
def worker(settings: WorkerSettings, concurrency: int, log: Path) -> Iterator[None]:
    """A `pwm worker --concurrency N` process on the settings' broker and catalog."""
    env = os.environ | {f"PWM_{k.upper()}": str(v) for k, v in settings.model_dump().items()
                        if v is not None}
    with open(log, "wb") as out:
        process = subprocess.Popen([str(PWM), "worker", f"--concurrency={concurrency}",
                                    "--name", f"bench-{uuid.uuid4().hex[:6]}@%h"],
                                   cwd=REPO, env=env, stdout=out, stderr=subprocess.STDOUT,
                                   start_new_session=True)
    try:
        _wait(lambda: " ready." in log.read_text(errors="replace"), "the worker", log,
              READY_TIMEOUT_S, process)
        yield
    finally:
        process.terminate()
        try:
            process.wait(timeout=30)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()


def _wait(condition: Callable[[], bool], what: str, log: Path, timeout: float,
          process: subprocess.Popen) -> None:
    deadline = time.monotonic() + timeout
    while not condition():
        if process.poll() is not None or time.monotonic() > deadline:
            raise RuntimeError(f"{what} not seen:\n{log.read_text(errors='replace')[-4000:]}")
        time.sleep(0.1)


def run_downlink(sessions: sessionmaker[Session], client: Celery, directory: Path, version: int,
                 log: Path) -> Stage:
    """Submit the ingest of `directory` and wait for model version `version`; its stages."""
    submitted = datetime.now(UTC)
    client.send_task(ingest_downlink.name, args=[str(directory)],
                     kwargs={"key": ingest_key(directory)})

    def published() -> ModelVersion | None:
        with sessions() as session:
            return session.scalar(select(ModelVersion).filter_by(version=version))

    deadline = time.monotonic() + DOWNLINK_TIMEOUT_S
    while (found := published()) is None:
        if time.monotonic() > deadline:
            raise RuntimeError(f"no version {version}:\n{log.read_text(errors='replace')[-4000:]}")
        time.sleep(0.1)
    with sessions() as session:
        jobs = session.scalars(select(Job).where(Job.created_at >= submitted)).all()
    ingest = [j for j in jobs if j.kind is JobKind.INGEST]
    refines = [j for j in jobs if j.kind is JobKind.REFINE]
    fuse = [j for j in jobs if j.kind is JobKind.FUSE]

    def span(group: list[Job]) -> float:
        return (max(j.finished_at for j in group) - min(j.started_at for j in group)
                ).total_seconds()

    busy = sum((j.finished_at - j.started_at).total_seconds() for j in refines)
    return Stage(maplets=len(refines), ingest_s=span(ingest), refine_s=span(refines),
                 busy_s=busy, fuse_s=span(fuse), latency_s=(found.created_at - submitted).total_seconds())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--nodes", type=int, default=40, help="maplet nodes per side")
    parser.add_argument("--radius-km", type=float, default=0.004, help="tiled region radius")
    parser.add_argument("--revisit-images", type=int, default=10)
    parser.add_argument("--downlink", type=Path, help="a tiny downlink (default: simulate one)")
    parser.add_argument("--scratch", type=Path, help="keep the work here (default: temporary)")
    args = parser.parse_args()

    with contextlib.ExitStack() as stack:
        scratch = args.scratch or Path(stack.enter_context(tempfile.TemporaryDirectory()))
        scratch.mkdir(parents=True, exist_ok=True)
        downlink = args.downlink
        if downlink is None:
            simulate(scratch / "tiny", scenario=get_scenario("tiny"), seed=3, with_start_model=True)
            downlink = scratch / "tiny" / "downlink"
        revisit = scratch / "revisit"
        if not revisit.exists():
            window_downlink(downlink, revisit, size_px=REVISIT_WINDOW_PX,
                            first_px=REVISIT_FIRST_PX, count=args.revisit_images, tag="revisit")
        (scratch / "redis").mkdir(exist_ok=True)
        server = stack.enter_context(postgres())
        broker = stack.enter_context(redis_server(scratch / "redis"))
        results = []
        for k, n in enumerate(args.workers):
            database = f"pwm_ops_{k}_{uuid.uuid4().hex[:6]}"
            with server.admin() as admin:
                admin.execute(f'CREATE DATABASE "{database}"')
            settings = WorkerSettings(
                broker_url=broker.rsplit("/", 1)[0] + f"/{k + 1}",
                database_url=server.url(database), data_dir=scratch / f"data-{k}",
                maplet_nodes=args.nodes, tile_radius_km=args.radius_km)
            upgrade(settings.database_url)
            engine = make_engine(settings.database_url)
            client = make_app(settings)
            log = scratch / f"worker-{n}.log"
            with worker(settings, n, log):
                sessions = make_sessionmaker(engine)
                base = run_downlink(sessions, client, downlink.resolve(), 2, log)
                again = run_downlink(sessions, client, revisit.resolve(), 3, log)
            client.close()
            engine.dispose()
            results.append((n, base, again))
            print(f"{n} worker processes: {base.maplets} maplets in {base.refine_s:.1f} s; "
                  f"revisit {again.latency_s:.1f} s", flush=True)

    one = next((b.maplets_per_min for n, b, _ in results if n == 1), None)
    print(f"\nRefinement throughput: the tiny downlink, maplets of {args.nodes} nodes within "
          f"{args.radius_km * 1e3:g} m ({os.cpu_count()} cores, load average "
          f"{os.getloadavg()[0]:.1f})")
    # busy/wall: how many refinements ran at once on average; below the process count when the
    # queue starves them, while CPU contention slows each one instead.
    print(f"{'processes':>9}{'maplets':>9}{'refine s':>10}{'maplets/min':>13}{'ratio':>7}"
          f"{'busy/wall':>11}{'ingest s':>10}{'fuse s':>8}{'to version s':>14}")
    for n, base, _ in results:
        ratio = base.maplets_per_min / one if one else float("nan")
        print(f"{n:>9}{base.maplets:>9}{base.refine_s:>10.1f}{base.maplets_per_min:>13.1f}"
              f"{ratio:>7.2f}{base.busy_s / base.refine_s:>11.2f}{base.ingest_s:>10.1f}"
              f"{base.fuse_s:>8.1f}{base.latency_s:>14.1f}")
    print(f"\nDownlink to new version: a revisit of {args.revisit_images} images "
          f"({REVISIT_WINDOW_PX} px windows) of one corner")
    print(f"{'processes':>9}{'maplets':>9}{'ingest s':>10}{'refine s':>10}{'fuse s':>8}"
          f"{'latency s':>11}")
    for n, _, again in results:
        print(f"{n:>9}{again.maplets:>9}{again.ingest_s:>10.1f}{again.refine_s:>10.1f}"
              f"{again.fuse_s:>8.1f}{again.latency_s:>11.1f}")


if __name__ == "__main__":
    main()
