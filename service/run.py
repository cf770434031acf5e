"""`pwm run DIR`: a downlink from directory to published model version in one process, with no
servers: ingest (with the coverage of its images against the current model), refinement of the
maplets whose input changed, fusion into a new version.

The distributed setup (workers/) runs the same three steps as Celery tasks.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path

from sqlalchemy import select
from sqlalchemy.orm import Session, sessionmaker

from pwm.config import DEFAULTS, RefinementConfig
from pwm.parallel import map_processes
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
                    start: Path | None = None, config: RefinementConfig = DEFAULTS) -> Plan:
    """Ingest a downlink against the current model and list the maplets whose input changed:
    those its images weigh into, and those its coverage update re-weighed against the current
    model (the shape moved, and with it which images they keep) or a stopped run left stale.

    The current model is the latest version; a catalog without one first imports `start` (or
    DIRECTORY/start_model.obj when present) as a version of kind start. config: how maplets
    are tiled where the images look and none is catalogued (service.ingest.ingest_directory),
    and refined.
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
    report = ingest_directory(sessions, directory, shape=shape, config=config)
    with sessions() as session:
        downlink_id = session.scalars(select(Downlink.id).filter_by(name=report.downlink)).one()
        work = stale_maplets(session, config=config)
    log.info("%s: %d maplets to refine", report.downlink, len(work))
    return Plan(downlink_id=downlink_id, ingest=report, work=work, base_version=base_version)


def run_directory(sessions: sessionmaker[Session], directory: Path, *, data_dir: Path,
                  start: Path | None = None, config: RefinementConfig = DEFAULTS,
                  workers: int = 1) -> RunReport:
    """Ingest, refine (in `workers` processes, pwm.parallel.map_processes) and fuse one downlink;
    see `ingest_and_plan`. A version is published when some maplet's current revision changed."""
    clock = time.perf_counter()
    plan = ingest_and_plan(sessions, directory, data_dir=data_dir, start=start, config=config)
    report = RunReport(plan=plan)
    url = sessions.kw["bind"].url.render_as_string(hide_password=False)
    refine = partial(_refine_in_process, data_dir=data_dir, config=config)
    revisions = map_processes(refine, plan.work, workers=workers, initializer=_open_catalog, initargs=(url,))
    try:
        for k, (work, revision) in enumerate(zip(plan.work, revisions, strict=True), 1):
            report.revisions.append(revision)
            _log_progress(k, len(plan.work), work, clock)
    finally:
        _close_catalog()
    report.version = fuse_and_publish(sessions, data_dir=data_dir, downlink_ids=[plan.downlink_id],
                                      config=config)
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


_CATALOG: dict[str, sessionmaker[Session]] = {}


def _open_catalog(url: str) -> None:
    # Each refining process opens its own engine: connections do not cross processes.
    _CATALOG["sessions"] = make_sessionmaker(make_engine(url))


def _close_catalog() -> None:
    # Only where the refinement ran in this process: its engine goes with the run.
    sessions = _CATALOG.pop("sessions", None)
    if sessions is not None:
        sessions.kw["bind"].dispose()


def _refine_in_process(work: MapletWork, *, data_dir: Path, config: RefinementConfig) -> int:
    return refine_catalog_maplet(_CATALOG["sessions"], data_dir=data_dir, maplet_id=work.maplet_id,
                                 input_hash=work.input_hash, config=config)


def _log_progress(k: int, total: int, work: MapletWork, clock: float) -> None:
    log.info("maplet %d/%d %s refined from %d images (%.0f s elapsed)", k, total, work.name,
             work.images, time.perf_counter() - clock)
