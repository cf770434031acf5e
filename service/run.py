"""`pwm run DIR`: a downlink from directory to published model version in one process, with no
servers: ingest (with the coverage of its images against the current model), refinement of the
maplets whose input changed, fusion into a new version.

The distributed setup (workers/) runs the same three steps as Celery tasks.
"""

from __future__ import annotations

import logging
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field
from multiprocessing import get_context
from pathlib import Path

from sqlalchemy import select
from sqlalchemy.orm import Session, sessionmaker

from service.db import make_engine, make_sessionmaker, session_scope
from service.ingest import IngestReport, ingest_directory
from service.models import Downlink, ModelKind
from service.publish import fuse_and_publish
from service.refinement import MapletWork, refine_catalog_maplet, stale_maplets
from service.versions import import_model, latest_version, publication_lock, version_mesh

log = logging.getLogger(__name__)

START_MODEL_NAME = "start_model.obj"
"""The start model a simulated downlink carries (pwm simulate)."""


@dataclass
class Plan:
    """What a downlink asks for: its id, its ingest, the maplets to refine, and the version
    (number) that the refinement starts from."""

    downlink_id: int
    ingest: IngestReport
    work: list[MapletWork]
    base_version: int


@dataclass
class RunReport:
    """What `run_directory` did: the plan, the revisions refined (ids), the version published
    (None when nothing changed) and the time taken (s)."""

    plan: Plan
    revisions: list[int] = field(default_factory=list)
    version: int | None = None
    seconds: float = 0.0

    def summary(self) -> str:
        outcome = (f"published version {self.version}" if self.version is not None
                   else "no new version (nothing changed)")
        return (f"{self.plan.ingest.summary()}\n{len(self.plan.work)} maplets refined from "
                f"version {self.plan.base_version}; {outcome}; {self.seconds:.1f} s")


def ingest_and_plan(sessions: sessionmaker[Session], directory: Path, *, data_dir: Path,
                    start: Path | None = None, mode: str = "pwm", maplet_nodes: int = 100,
                    tile_radius_km: float | None = None) -> Plan:
    """Ingest a downlink against the current model and list the maplets whose input changed:
    those its images weigh into, and those its coverage update re-weighed against the current
    model (the shape moved, and with it which images they keep) or a stopped run left stale.

    The current model is the latest version; a catalog without one first imports `start` (or
    DIRECTORY/start_model.obj when present) as a version of kind start. maplet_nodes,
    tile_radius_km: of the maplets tiled where the images look and none is catalogued
    (service.ingest.ingest_directory).
    """
    directory = Path(directory)
    with session_scope(sessions) as session:
        # Locked, so that two first runs do not both import a start model.
        publication_lock(session)
        base = latest_version(session)
        if base is None:
            base = import_model(session, data_dir=data_dir, kind=ModelKind.START,
                                path=_start_model(directory, start))
            log.info("imported %s as version %d (start)", base.statistics["source"], base.version)
        elif start is not None:
            log.info("the catalog's latest version %d is the current model; %s is not used",
                     base.version, start)
        shape, base_version = version_mesh(data_dir, base), base.version
    report = ingest_directory(sessions, directory, shape=shape, maplet_nodes=maplet_nodes,
                              tile_radius_km=tile_radius_km)
    with sessions() as session:
        downlink_id = session.scalars(select(Downlink.id).filter_by(name=report.downlink)).one()
        work = stale_maplets(session, mode=mode)
    log.info("%s: %d maplets to refine", report.downlink, len(work))
    return Plan(downlink_id=downlink_id, ingest=report, work=work, base_version=base_version)


def run_directory(sessions: sessionmaker[Session], directory: Path, *, data_dir: Path,
                  start: Path | None = None, mode: str = "pwm", workers: int = 1,
                  maplet_nodes: int = 100, tile_radius_km: float | None = None) -> RunReport:
    """Ingest, refine (in `workers` processes) and fuse one downlink; see `ingest_and_plan`.
    A version is published when some maplet's current revision changed."""
    clock = time.perf_counter()
    plan = ingest_and_plan(sessions, directory, data_dir=data_dir, start=start, mode=mode,
                           maplet_nodes=maplet_nodes, tile_radius_km=tile_radius_km)
    report = RunReport(plan=plan)
    if workers <= 1 or len(plan.work) <= 1:
        for k, work in enumerate(plan.work, 1):
            report.revisions.append(refine_catalog_maplet(
                sessions, data_dir=data_dir, maplet_id=work.maplet_id,
                input_hash=work.input_hash, mode=mode))
            _log_progress(k, len(plan.work), work, clock)
    else:
        url = sessions.kw["bind"].url.render_as_string(hide_password=False)
        # spawn: each process opens its own engine and Embree scenes, nothing inherited.
        with ProcessPoolExecutor(workers, mp_context=get_context("spawn")) as pool:
            jobs = [pool.submit(_refine_in_process, url, data_dir, work, mode)
                    for work in plan.work]
            for k, (work, job) in enumerate(zip(plan.work, jobs, strict=True), 1):
                report.revisions.append(job.result())
                _log_progress(k, len(plan.work), work, clock)
    report.version = fuse_and_publish(sessions, data_dir=data_dir,
                                      downlink_ids=[plan.downlink_id])
    report.seconds = time.perf_counter() - clock
    log.info("run %s: %d maplets refined, version %s (%.1f s)", directory, len(plan.work),
             report.version, report.seconds)
    return report


def _start_model(directory: Path, start: Path | None) -> Path:
    if start is not None:
        return start
    if (directory / START_MODEL_NAME).is_file():
        return directory / START_MODEL_NAME
    raise FileNotFoundError(f"the catalog has no model version and {directory} holds no "
                            f"{START_MODEL_NAME}: give a start model (pwm run --start MODEL, "
                            "or pwm import MODEL)")


def _refine_in_process(url: str, data_dir: Path, work: MapletWork, mode: str) -> int:
    engine = make_engine(url)
    try:
        return refine_catalog_maplet(make_sessionmaker(engine), data_dir=data_dir,
                                     maplet_id=work.maplet_id, input_hash=work.input_hash,
                                     mode=mode)
    finally:
        engine.dispose()


def _log_progress(k: int, total: int, work: MapletWork, clock: float) -> None:
    log.info("maplet %d/%d %s refined from %d images (%.0f s elapsed)", k, total, work.name,
             work.images, time.perf_counter() - clock)
