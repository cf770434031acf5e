"""The conductor: the order of one downlink's stages, and the rules for what follows each.

1. catalogue: kernels and products, each image's geometry (service.ingest.ingest_directory);
2. adjust the poses on the current model (service.spg.adjust_downlink, the points tied to the
   catalog's strip-adjusted lidar spots), or with no model make one from the images
   (service.spg.start_from_images) and one from the lidar (service.lidar.start_from_lidar),
   started from whichever is the better founded: from the lidar's, the images' poses adjusted
   again on it, tied to its spots;
3. weigh the images against the model (`weigh`, service.coverage.update_coverage): once per
   downlink and pass, after its poses are final;
4. plan: the maplets whose input changed (service.refinement.stale_maplets);
5. refine each (service.refinement.refine_catalog_maplet);
6. fuse and publish a version (service.publish.fuse_and_publish);
7. feed back (`feed_back`): after the downlink's first fusion, the maplets' registrations
   into its poses (service.spg.feed_back_registrations), and the images corrected weighed again;
8. the next pass: the maplets due after the fusion (`due_after_fusion`), from step 5;
9. the lidar (`adjust_lidar`): once a downlink's passes are published, every catalogued track
   strip-adjusted to the last version (the model changed); a downlink that brought lidar and
   published nothing, its own tracks to the current version (service.lidar.adjust_tracks).

Two drivers run the stages: service.run.run_directory in one process, and the Celery tasks of
workers.tasks (one for steps 1 to 4, one per maplet's refinement, one per fusion with its
feedback). Both take from here the stages' order and what comes next: `ingest_and_plan` (steps
1 to 4), `feed_back`, `due_after_fusion` (the pass rule), `adjust_lidar` and, for the tasks,
`fusion_due` (the fan-in).
"""

from __future__ import annotations

import logging
from collections.abc import Collection
from dataclasses import dataclass
from pathlib import Path

from sqlalchemy import select
from sqlalchemy.orm import Session, sessionmaker

from pwm.config import DEFAULTS, RefinementConfig
from pwm.mesh import Mesh
from service.coverage import CoverageReport, unweighed_images, update_coverage
from service.db import session_scope
from service.ingest import IngestReport, ingest_directory
from service.jobs import fusions_due
from service.lidar import LidarAdjustment, adjust_tracks, products_of, start_from_lidar
from service.refinement import MapletWork, stale_maplets
from service.rows import Downlink, ModelKind
from service.spg import adjust_downlink, feed_back_registrations, start_from_images
from service.versions import get_version, import_model, latest_version, publication_lock, version_mesh

log = logging.getLogger(__name__)

START_MODEL_NAME = "start_model.obj"
"""The start model a simulated downlink carries when asked for (pwm simulate --with-start-model)."""


@dataclass
class Plan:
    """What a downlink asks for: its id, its ingest, the weighing of its images, the maplets to
    refine, and the version (number) that the refinement starts from (None: the catalog has no
    model, and none could be made from the images yet; the downlink's model_note says why, and
    its images wait unweighed, coverage None)."""

    downlink_id: int
    ingest: IngestReport
    coverage: CoverageReport | None
    work: list[MapletWork]
    base_version: int | None


def ingest_and_plan(sessions: sessionmaker[Session], directory: Path, *, data_dir: Path,
                    start: Path | None = None, config: RefinementConfig = DEFAULTS,
                    refine_on_config_change: bool = False) -> Plan:
    """Catalogue a downlink, adjust its poses, weigh its images and list the maplets whose input
    changed: those its images weigh into (their image sets changed), and those a stopped run
    left stale.

    The current model is the latest version; a catalog without one first imports `start` (or
    DIRECTORY/start_model.obj when present) as a version of kind start, and with neither makes
    one from the catalogued images after the ingest (service.spg.start_from_images) and one from
    its lidar spots (service.lidar.start_from_lidar), published after the images' where it is
    the better founded (service.lidar.finer_start) and then started from; when neither can yet,
    nothing is weighed nor refined (Plan.base_version None). config: the pose
    knowledge where the kernels state none, how maplets are tiled where the images look and none
    is catalogued, and how they are refined. refine_on_config_change: also the maplets whose
    current revision was made with another configuration (service.refinement.stale_maplets).
    """
    directory = Path(directory)
    shape, base_version = _current_model(sessions, directory, data_dir=data_dir, start=start)
    report = ingest_directory(sessions, directory, shape=shape, data_dir=data_dir)
    with sessions() as session:
        downlink_id = session.scalars(select(Downlink.id).filter_by(name=report.downlink)).one()
    if shape is not None:
        adjust_downlink(sessions, shape=shape, downlink_id=downlink_id, data_dir=data_dir,
                        configured=config.knowledge)
    else:
        from_images = start_from_images(sessions, data_dir=data_dir, downlink_id=downlink_id,
                                        configured=config.knowledge)
        base_version = start_from_lidar(sessions, data_dir=data_dir, downlink_id=downlink_id, over=from_images)
        if base_version is None:
            base_version = from_images
        if base_version is None:
            return Plan(downlink_id=downlink_id, ingest=report, coverage=None, work=[], base_version=None)
        with sessions() as session:
            shape = version_mesh(data_dir, get_version(session, base_version))
        if base_version != from_images:  # the lidar's start: the images placed on it, tied to its spots
            adjust_downlink(sessions, shape=shape, downlink_id=downlink_id, data_dir=data_dir,
                            configured=config.knowledge)
    coverage = weigh(sessions, shape, config=config)
    with sessions() as session:
        work = stale_maplets(session, config=config, refine_on_config_change=refine_on_config_change)
    log.info("%s: %d maplets to refine", report.downlink, len(work))
    return Plan(downlink_id=downlink_id, ingest=report, coverage=coverage, work=work, base_version=base_version)


def weigh(sessions: sessionmaker[Session], shape: Mesh, *,
          config: RefinementConfig = DEFAULTS) -> CoverageReport:
    """Weigh the images not weighed yet against `shape` (service.coverage.update_coverage): a
    new downlink's, those ingested while the catalog had no model, and those whose pose was
    corrected since. config: how maplets are tiled where none lies yet, and weighed."""
    with session_scope(sessions) as session:
        unweighed = unweighed_images(session)
        # nothing new: no tracer built, no maplet looked at
        return update_coverage(session, shape, image_ids=unweighed, config=config) if unweighed else CoverageReport()


def feed_back(sessions: sessionmaker[Session], *, data_dir: Path, downlink_id: int, version: int,
              config: RefinementConfig) -> bool:
    """After a downlink's refinements were first fused into `version`: its maplets'
    registrations fed back into the adjustment of its poses on that version
    (service.spg.feed_back_registrations), and the images it corrected weighed again on it.
    Whether it corrected any."""
    corrected = feed_back_registrations(sessions, data_dir=data_dir, version=version, downlink_id=downlink_id,
                                        configured=config.knowledge)
    with sessions() as session:
        # also those a stopped attempt corrected and left unweighed
        shape = version_mesh(data_dir, get_version(session, version)) if unweighed_images(session) else None
    if shape is not None:
        weigh(sessions, shape, config=config)
    return bool(corrected)


def due_after_fusion(session: Session, *, config: RefinementConfig, fed: bool,
                     maplet_ids: Collection[int] | None = None,
                     refine_on_config_change: bool = False) -> list[MapletWork]:
    """The pass rule: of the maplets (of maplet_ids, or all) due for refinement
    (service.refinement.stale_maplets, refine_on_config_change as there), those due after a
    fusion. Only later passes: a new input now is another downlink's to refine; but once the
    feedback corrected the downlink's poses (fed), its maplets start again, at any pass."""
    due = stale_maplets(session, config=config, maplet_ids=maplet_ids,
                        refine_on_config_change=refine_on_config_change)
    return [w for w in due if w.pass_number > 1 or fed]


def adjust_lidar(sessions: sessionmaker[Session], *, data_dir: Path, downlink_id: int,
                 published: int | None, current: int | None) -> LidarAdjustment | None:
    """The lidar stage after a downlink's last pass: where it published a version (`published`),
    every catalogued track strip-adjusted to it; else, where it brought lidar products and the
    catalog has a model (`current`), its own tracks to that. None where nothing was adjusted."""
    if published is not None:
        return adjust_tracks(sessions, data_dir=data_dir, version=published)
    with sessions() as session:
        brought = products_of(session, downlink_id)
    if not brought or current is None:
        return None
    return adjust_tracks(sessions, data_dir=data_dir, version=current, product_ids=brought)


def fusion_due(session: Session, *, downlink_id: int | None, after: str) -> str | None:
    """The fan-in: the key of the fusion that follows the refine job `after`, or None when it is
    not due. A downlink's is due once none of its refine jobs is unfinished (failed ones count
    as unfinished) and none was made since them (service.jobs.fusions_due); a requested
    refinement's (downlink None) at once."""
    if downlink_id is None:
        return f"fuse:{after}"
    return fusions_due(session, downlink_id=downlink_id).get(downlink_id)


def _current_model(sessions: sessionmaker[Session], directory: Path, *, data_dir: Path,
                   start: Path | None) -> tuple[Mesh | None, int | None]:
    """The current model's mesh and version number (None, None: the catalog has none), the
    start model imported first where the catalog has none and one is given."""
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
        if base is None:
            return None, None
        return version_mesh(data_dir, base), base.version
