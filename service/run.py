"""`pwm run DIR`: a downlink from directory to published model versions in one process, with no
servers, its stages in the conductor's order (service.conductor): ingest, pose adjustment and
weighing up to the plan (service.conductor.ingest_and_plan), refinement of the maplets whose
input changed (in processes, pwm.parallel.map_processes), fusion into a new version, the
feedback after the first fusion (service.conductor.feed_back); then the maplets the conductor's
pass rule says are due (service.conductor.due_after_fusion) are refined against that version and
fused into the next, until none is due (`refine_and_fuse`). `pwm refine-catalog
--because-config-changed` (`refine_other_configurations`) refines and fuses the same way the
maplets whose current revision was made with another configuration.

The distributed setup (workers.tasks) runs the same stages as Celery tasks, one per task; each
stage run here is recorded as an attempt at the job a worker would have run
(service.jobs.record_attempt: the ingest, a refinement per maplet, a fusion per pass), so that
`pwm jobs list` and the API's /jobs show what a run did and how it ended.
"""

from __future__ import annotations

import logging
import os
import socket
import time
import traceback
from dataclasses import dataclass, field
from datetime import datetime
from functools import partial
from pathlib import Path

from sqlalchemy.orm import Session, sessionmaker

from pwm.config import DEFAULTS, RefinementConfig
from pwm.parallel import Progress, map_processes
from service.conductor import Plan, adjust_lidar, due_after_fusion, feed_back, fusion_due, ingest_and_plan
from service.console.documents import make_mesh_document
from service.db import make_engine, make_sessionmaker, session_scope
from service.downlinks import other_configurations
from service.jobs import ingest_key, record_attempt, refine_key
from service.lidar import LidarAdjustment
from service.publish import fuse_and_publish
from service.refinement import MapletWork, refine_catalog_maplet, stale_maplets
from service.rows import JobKind, utcnow

log = logging.getLogger(__name__)


@dataclass
class Refinements:
    """What `refine_and_fuse` did: the revisions refined (ids, of every pass) and the versions
    published (one per pass that changed a maplet)."""

    revisions: list[int] = field(default_factory=list)
    versions: list[int] = field(default_factory=list)


@dataclass
class RunReport:
    """What `run_directory` did: the plan, the revisions refined (ids, of every pass), the
    versions published (one per pass that changed a maplet), the last of them (None when
    nothing changed), the lidar's strip adjustment (None where none ran) and the time taken (s)."""

    plan: Plan
    revisions: list[int] = field(default_factory=list)
    versions: list[int] = field(default_factory=list)
    lidar: LidarAdjustment | None = None
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
        lidar = "" if self.lidar is None else f"\n{self.lidar.summary()}"
        return (f"{self.plan.ingest.summary()}\n{len(self.revisions)} maplet refinements from "
                f"version {self.plan.base_version}; {outcome}{lidar}; {self.seconds:.1f} s")


def run_directory(sessions: sessionmaker[Session], directory: Path, *, data_dir: Path,
                  start: Path | None = None, config: RefinementConfig = DEFAULTS,
                  workers: int = 1, refine_on_config_change: bool = False,
                  progress: Progress | None = None) -> RunReport:
    """Ingest, refine (in `workers` processes) and fuse one downlink, pass after pass
    (`refine_and_fuse`, telling `progress` how far each pass's refinement has come); see
    service.conductor.ingest_and_plan (refine_on_config_change as there)."""
    clock = time.perf_counter()
    started = utcnow()
    try:
        plan = ingest_and_plan(sessions, directory, data_dir=data_dir, start=start, config=config,
                               refine_on_config_change=refine_on_config_change)
    except Exception:
        _record(sessions, kind=JobKind.INGEST, key=ingest_key(directory), started_at=started,
                error=traceback.format_exc())
        raise
    then = (f"{len(plan.work)} maplets to refine from version {plan.base_version}"
            if plan.base_version is not None else "no model to refine yet (the downlink's model note says why)")
    _record(sessions, kind=JobKind.INGEST, key=ingest_key(directory), started_at=started,
            message=f"{plan.ingest.summary()}; {then}", downlink_id=plan.downlink_id)
    report = RunReport(plan=plan)
    if plan.base_version is not None:  # else no model, and none could be made yet: nothing to refine
        done = refine_and_fuse(sessions, plan.work, data_dir=data_dir, config=config, workers=workers,
                               downlink_id=plan.downlink_id,
                               refine_on_config_change=refine_on_config_change, progress=progress)
        report.revisions, report.versions = done.revisions, done.versions
        report.lidar = adjust_lidar(sessions, data_dir=data_dir, downlink_id=plan.downlink_id,
                                    published=report.version, current=plan.base_version)
    report.seconds = time.perf_counter() - clock
    log.debug("run %s: %s", directory, report.summary())  # the command line prints it
    return report


def refine_other_configurations(sessions: sessionmaker[Session], *, data_dir: Path,
                                config: RefinementConfig = DEFAULTS, workers: int = 1,
                                progress: Progress | None = None) -> Refinements:
    """Refine under `config` the maplets whose current revision was made with another
    configuration (service.downlinks.other_configurations) and fuse them, pass after pass
    (`refine_and_fuse`, with no downlink: no feedback; progress as there)."""
    with sessions() as session:
        work = stale_maplets(session, config=config, refine_on_config_change=True,
                             maplet_ids=list(other_configurations(session, config)))
    if not work:
        return Refinements()
    return refine_and_fuse(sessions, work, data_dir=data_dir, config=config, workers=workers, progress=progress)


def refine_and_fuse(sessions: sessionmaker[Session], work: list[MapletWork], *, data_dir: Path,
                    config: RefinementConfig, workers: int = 1, downlink_id: int | None = None,
                    refine_on_config_change: bool = False, progress: Progress | None = None) -> Refinements:
    """Refine `work` (in `workers` processes, pwm.parallel.map_processes) and fuse it into a
    version, with the downlink in its lineage and, after its first fusion, the downlink's
    feedback (service.conductor.feed_back; none without a downlink). A version is published when
    some maplet's current revision changed; then the maplets due after it
    (service.conductor.due_after_fusion, refine_on_config_change as there) are refined against it
    and fused again, until none is due (at most config.most_passes rounds, one more where the feedback
    corrected the poses). The console's 3D document is made for the last version. `progress` is
    told how far each round's refinement has come (stage "refine round R")."""
    clock = time.perf_counter()
    done = Refinements()
    url = sessions.kw["bind"].url.render_as_string(hide_password=False)
    refine = partial(_refine_in_process, data_dir=data_dir, config=config)
    rounds = config.most_passes
    round_number = 0
    while round_number < rounds:
        round_number += 1
        refined = _refine_round(sessions, work, refine=refine, url=url, workers=workers, downlink_id=downlink_id,
                                progress=progress, stage=f"refine round {round_number}", clock=clock)
        done.revisions += refined
        started = utcnow()
        try:
            # the console's 3D document of the last version only, made below: a pass's version that
            # the next pass supersedes within minutes need not cost a minute more
            version = fuse_and_publish(sessions, data_dir=data_dir,
                                       downlink_ids=[] if downlink_id is None else [downlink_id], config=config)
            fed = version is not None and downlink_id is not None and feed_back(
                sessions, data_dir=data_dir, downlink_id=downlink_id, version=version, config=config)
        except Exception:
            _record_fusion(sessions, downlink_id=downlink_id, work=work, started_at=started,
                           error=traceback.format_exc())
            raise
        if version is not None:
            done.versions.append(version)
        fused = work
        with sessions() as session:
            work = due_after_fusion(session, config=config, fed=fed,
                                    refine_on_config_change=refine_on_config_change)
        outcome = "no maplet changed: no new version" if version is None else f"published version {version}"
        _record_fusion(sessions, downlink_id=downlink_id, work=fused, started_at=started,
                       message=outcome + (f"; {len(work)} maplets due for another pass" if work else ""))
        if fed:
            rounds += 1
        if not work:
            break
        log.info("round %d: %d maplets due for %s", round_number + 1, len(work),
                 "refinement with the poses corrected" if fed else "another pass")
    if done.versions:
        make_mesh_document(sessions, data_dir=data_dir, version=done.versions[-1])
    log.info("%d maplet refinements, versions %s (%.1f s)", len(done.revisions), done.versions,
             time.perf_counter() - clock)
    return done


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


def _refine_round(sessions: sessionmaker[Session], work: list[MapletWork], *, refine: partial[int], url: str,
                  workers: int, downlink_id: int | None, progress: Progress | None, stage: str,
                  clock: float) -> list[int]:
    """One round's refinements (in `workers` processes), each recorded as its refine job once its
    result is in; the revisions, in work's order. Results come in work's order: the first item
    without one when the map raises is the one that failed, recorded so."""
    revisions: list[int] = []
    started = utcnow()
    if progress is not None:
        progress(stage, 0, len(work))
    try:
        for item, revision in zip(work, map_processes(refine, work, workers=workers, initializer=_open_catalog,
                                                      initargs=(url,)), strict=True):
            revisions.append(revision)
            # in processes side by side an item's start is not known here: the last result's arrival
            _record(sessions, kind=JobKind.REFINE, key=refine_key(downlink_id, item.maplet_id, item.input_hash),
                    started_at=started, message=f"maplet {item.maplet_id}: revision {revision}",
                    downlink_id=downlink_id, maplet_id=item.maplet_id)
            started = utcnow()
            log.debug("maplet %d/%d %s refined (pass %d) from %d images (%.0f s elapsed)", len(revisions),
                      len(work), item.name, item.pass_number, item.images, time.perf_counter() - clock)
            if progress is not None:
                progress(stage, len(revisions), len(work))
    except Exception:
        if len(revisions) < len(work):
            failed = work[len(revisions)]
            _record(sessions, kind=JobKind.REFINE, key=refine_key(downlink_id, failed.maplet_id, failed.input_hash),
                    started_at=started, error=traceback.format_exc(), downlink_id=downlink_id,
                    maplet_id=failed.maplet_id)
        raise
    finally:
        _close_catalog()
    return revisions


def _record_fusion(sessions: sessionmaker[Session], *, downlink_id: int | None, work: list[MapletWork],
                   started_at: datetime, message: str | None = None, error: str | None = None) -> None:
    """Record a round's fusion as the fuse job the workers' fan-in would have made after its
    refine jobs (service.conductor.fusion_due); none where no refinement came before it."""
    if not work:
        return
    last = work[-1]
    with session_scope(sessions) as session:
        key = fusion_due(session, downlink_id=downlink_id,
                         after=refine_key(downlink_id, last.maplet_id, last.input_hash))
    if key is None:  # a refine job of the downlink failed in an earlier run and was not run again
        log.debug("fusion not recorded as a job: the downlink's refine jobs are not all done")
        return
    _record(sessions, kind=JobKind.FUSE, key=key, started_at=started_at, message=message, error=error,
            downlink_id=downlink_id)


def _record(sessions: sessionmaker[Session], *, kind: JobKind, key: str, started_at: datetime,
            message: str | None = None, error: str | None = None, downlink_id: int | None = None,
            maplet_id: int | None = None) -> None:
    """A stage run here, recorded as an attempt at its job (service.jobs.record_attempt)."""
    with session_scope(sessions) as session:
        recorded = record_attempt(session, kind=kind, key=key, worker=f"pwm run {socket.gethostname()}:{os.getpid()}",
                                  started_at=started_at, message=message, error=error, downlink_id=downlink_id,
                                  maplet_id=maplet_id)
    if recorded is None:
        log.info("job %s is running elsewhere: this run's attempt is not recorded", key)
