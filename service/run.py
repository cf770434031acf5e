"""`pwm run DIR`: a downlink from directory to published model versions in one process, with no
servers: ingest (with the coverage of its images against the current model; a catalog with no
model and none given first makes one from the images, service.spg.start_from_images),
refinement of the maplets whose input changed, fusion into a new version; then each further
pass (RefinementConfig.passes) refines those maplets again against that version and fuses the
next. After the first fusion, poses that are still not known within a pixel are adjusted again
with the maplets' registrations (`feed_back`), and the maplets refined again with them.

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
from service.coverage import unweighed_images, update_coverage
from service.db import make_engine, make_sessionmaker, session_scope
from service.ingest import IngestReport, ingest_directory
from service.models import Downlink, ModelKind
from service.publish import fuse_and_publish, make_document
from service.refinement import MapletWork, refine_catalog_maplet, stale_maplets
from service.spg import adjust_downlink, feed_back_registrations, start_from_images
from service.versions import get_version, import_model, latest_version, publication_lock, version_mesh

log = logging.getLogger(__name__)

START_MODEL_NAME = "start_model.obj"
"""The start model a simulated downlink carries when asked for (pwm simulate --with-start-model)."""


@dataclass
class Plan:
    """What a downlink asks for: its id, its ingest, the maplets to refine, and the version
    (number) that the refinement starts from (None: the catalog has no model, and none could be
    made from the images yet; the downlink's model_note says why)."""

    downlink_id: int
    ingest: IngestReport
    work: list[MapletWork]
    base_version: int | None


@dataclass
class RunReport:
    """What `run_directory` did: the plan, the revisions refined (ids, of every pass), the
    versions published (one per pass that changed a maplet), the last of them (None when
    nothing changed) and the time taken (s)."""

    plan: Plan
    revisions: list[int] = field(default_factory=list)
    versions: list[int] = field(default_factory=list)
    seconds: float = 0.0

    @property
    def version(self) -> int | None:
        return self.versions[-1] if self.versions else None

    def summary(self) -> str:
        if self.plan.base_version is None:
            return (f"{self.plan.ingest.summary()}\nno model to refine: the catalog has none and "
                    f"the images could not make one yet; {self.seconds:.1f} s")
        outcome = (f"published version{'s' * (len(self.versions) > 1)} "
                   f"{', '.join(map(str, self.versions))}" if self.versions
                   else "no new version (nothing changed)")
        return (f"{self.plan.ingest.summary()}\n{len(self.revisions)} maplet refinements from "
                f"version {self.plan.base_version}; {outcome}; {self.seconds:.1f} s")


def ingest_and_plan(sessions: sessionmaker[Session], directory: Path, *, data_dir: Path,
                    start: Path | None = None, config: RefinementConfig = DEFAULTS) -> Plan:
    """Ingest a downlink against the current model and list the maplets whose input changed:
    those its images weigh into (their image sets changed), and those a stopped run left stale.

    Where the downlink's pose knowledge is stated (its kernels, or config.knowledge), its poses
    are adjusted on the current model first (service.spg.adjust_downlink) and its images weighed
    with the corrected poses. The current model is the latest version; a catalog without one
    first imports `start` (or
    DIRECTORY/start_model.obj when present) as a version of kind start, and with neither makes
    one from the catalogued images after the ingest (service.spg.start_from_images), which then
    weighs them against it; when it cannot yet, nothing is refined (Plan.base_version None).
    config: how maplets are tiled where the images look and none is catalogued
    (service.ingest.ingest_directory), and refined.
    """
    directory = Path(directory)
    given = start if start is not None else (
        directory / START_MODEL_NAME if (directory / START_MODEL_NAME).is_file() else None)
    with session_scope(sessions) as session:
        # Locked, so that two first runs do not both import a start model.
        publication_lock(session)
        base = latest_version(session)
        if base is None and given is not None:
            base = import_model(session, data_dir=data_dir, kind=ModelKind.START, path=given)
            log.info("imported %s as version %d (start)", base.statistics["source"], base.version)
        elif base is not None and start is not None:
            log.info("the catalog's latest version %d is the current model; %s is not used",
                     base.version, start)
        shape = None if base is None else version_mesh(data_dir, base)
        base_version = None if base is None else base.version
    report = ingest_directory(sessions, directory, shape=shape, config=config)
    with sessions() as session:
        downlink_id = session.scalars(select(Downlink.id).filter_by(name=report.downlink)).one()
    if shape is not None and adjust_downlink(sessions, shape=shape, downlink_id=downlink_id,
                                             configured=config.knowledge):
        with session_scope(sessions) as session:  # weighed again with their corrected poses
            report.coverage = update_coverage(session, shape, image_ids=unweighed_images(session), config=config)
    if shape is None:
        base_version = start_from_images(sessions, data_dir=data_dir, downlink_id=downlink_id,
                                         configured=config.knowledge)
        if base_version is None:
            return Plan(downlink_id=downlink_id, ingest=report, work=[], base_version=None)
        with session_scope(sessions) as session:
            shape = version_mesh(data_dir, get_version(session, base_version))
            report.coverage = update_coverage(session, shape, image_ids=unweighed_images(session),
                                              config=config)
    with sessions() as session:
        work = stale_maplets(session, config=config)
    log.info("%s: %d maplets to refine", report.downlink, len(work))
    return Plan(downlink_id=downlink_id, ingest=report, work=work, base_version=base_version)


def run_directory(sessions: sessionmaker[Session], directory: Path, *, data_dir: Path,
                  start: Path | None = None, config: RefinementConfig = DEFAULTS,
                  workers: int = 1) -> RunReport:
    """Ingest, refine (in `workers` processes, pwm.parallel.map_processes) and fuse one downlink;
    see `ingest_and_plan`. A version is published when some maplet's current revision changed;
    then the maplets due for a later pass (service.refinement.stale_maplets) are refined against
    it and fused again, until none is due (at most config.passes rounds)."""
    clock = time.perf_counter()
    plan = ingest_and_plan(sessions, directory, data_dir=data_dir, start=start, config=config)
    report = RunReport(plan=plan)
    if plan.base_version is None:  # no model, and none could be made yet: nothing to refine
        report.seconds = time.perf_counter() - clock
        log.info("run %s: %s", directory, report.summary())
        return report
    url = sessions.kw["bind"].url.render_as_string(hide_password=False)
    refine = partial(_refine_in_process, data_dir=data_dir, config=config)
    work = plan.work
    rounds = config.passes
    round_number = 0
    while round_number < rounds:
        round_number += 1
        revisions = map_processes(refine, work, workers=workers, initializer=_open_catalog,
                                  initargs=(url,))
        try:
            for k, (item, revision) in enumerate(zip(work, revisions, strict=True), 1):
                report.revisions.append(revision)
                _log_progress(k, len(work), item, clock)
        finally:
            _close_catalog()
        # the console's 3D document of the run's last version only, made below: a pass's
        # version that the next pass supersedes within minutes need not cost a minute more
        version = fuse_and_publish(sessions, data_dir=data_dir, downlink_ids=[plan.downlink_id], config=config,
                                   document=False)
        fed = version is not None and feed_back(sessions, data_dir=data_dir, downlink_id=plan.downlink_id,
                                                version=version, config=config)
        if version is not None:
            report.versions.append(version)
        with sessions() as session:
            # Only later passes: a new input now is another run's (its downlink's) to refine;
            # but poses corrected by the feedback are this run's, and its maplets start again.
            work = [w for w in stale_maplets(session, config=config) if w.pass_number > 1 or fed]
        if fed:
            rounds += 1
        if not work:
            break
        log.info("round %d: %d maplets due for %s", round_number + 1, len(work),
                 "refinement with the poses corrected" if fed else "another pass")
    if report.versions:
        make_document(sessions, data_dir=data_dir, version=report.versions[-1])
    report.seconds = time.perf_counter() - clock
    log.info("run %s: %d maplet refinements, versions %s (%.1f s)", directory,
             len(report.revisions), report.versions, report.seconds)
    return report


def feed_back(sessions: sessionmaker[Session], *, data_dir: Path, downlink_id: int, version: int,
              config: RefinementConfig) -> bool:
    """After a downlink's refinements were first fused into `version`: its maplets' registrations
    fed back into the adjustment of its poses on that version (service.spg.feed_back_registrations),
    and the images it corrected weighed again. Whether it corrected any."""
    corrected = feed_back_registrations(sessions, data_dir=data_dir, version=version, downlink_id=downlink_id,
                                        configured=config.knowledge)
    with session_scope(sessions) as session:
        # also those a stopped attempt corrected and left unweighed
        unweighed = unweighed_images(session)
        if unweighed:
            update_coverage(session, version_mesh(data_dir, get_version(session, version)), image_ids=unweighed,
                            config=config)
    return bool(corrected)


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
    log.info("maplet %d/%d %s refined (pass %d) from %d images (%.0f s elapsed)", k, total,
             work.name, work.pass_number, work.images, time.perf_counter() - clock)
