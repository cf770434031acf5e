"""Operations end to end with real servers: `pwm watch` and `pwm worker` processes (prefork) on a
Redis broker and a PostgreSQL catalog take simulated downlinks dropped into a folder to published
model versions, refining only the maplets whose input changed; a pool process killed during a
refinement loses nothing and duplicates nothing; with two refinement passes, each pass of a
downlink is fused into a version of its own, the second refined against the first's; a small
campaign's survey and two sites, in order, nest each site's level under the survey's and change
the model only about each new site."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from datetime import timedelta
from pathlib import Path

import numpy as np
import pytest
from celery import Celery
from harness import (
    HEARTBEAT_GRACE_S,
    PWM,
    RECONCILE_INTERVAL_S,
    REPO,
    TIME_LIMIT_S,
    Worker,
    end_to_end_settings,
    pwm_worker_command,
    result_of,
    wait_for,
)
from sqlalchemy import func, select
from sqlalchemy.orm import Session, selectinload, sessionmaker

from pwm.config import DEFAULTS
from pwm.evaluate.closure import closure
from pwm.frames import latlon_to_unit
from pwm.mesh import face_keys
from pwm.simulate.windows import window_downlink
from service.artifacts import artifact_path
from service.db import session_scope
from service.rows import (
    Coverage,
    Downlink,
    Image,
    Job,
    JobKind,
    JobStatus,
    Maplet,
    MapletRevision,
    ModelKind,
    ModelVersion,
)
from service.run import run_directory
from service.versions import version_mesh
from workers.app import WorkerSettings
from workers.tasks import fuse_key, ingest_downlink, ingest_key

# The revisit: 64 px windows (3 m at 5 cm) of the tiny images, beside one corner of the tiling.
CORNER_WINDOW_PX, CORNER_FIRST_PX = 64, (180, 180)
DOWNLINK_TIMEOUT_S = 150.0


@pytest.fixture
def settings(request: pytest.FixtureRequest, broker_url: str, postgres_url: str,
             tmp_path: Path) -> WorkerSettings:
    """The end-to-end settings; parametrized indirectly, a dict of settings to override."""
    overrides = request.param if hasattr(request, "param") else {}
    return end_to_end_settings(broker_url=broker_url, database_url=postgres_url,
                               data_dir=tmp_path / "data", **overrides)


@pytest.fixture
def incoming(tmp_path: Path) -> Path:
    path = tmp_path / "incoming"
    path.mkdir()
    return path


@pytest.fixture
def watcher(incoming: Path, worker_env: dict[str, str], catalog: sessionmaker[Session],
            tmp_path: Path) -> Iterator[Worker]:
    """`pwm watch INCOMING` in a process of its own (polling every 0.2 s); killed at teardown."""
    log = tmp_path / "watch.log"
    with open(log, "wb") as out:
        process = subprocess.Popen(
            [str(PWM), "watch", str(incoming), "--quiet-seconds", "5", "--poll-seconds", "0.2"],
            cwd=REPO, env=worker_env, stdout=out, stderr=subprocess.STDOUT,
            start_new_session=True)
    watch = Worker(process, log)
    yield watch
    watch.kill()


def _drop(source: Path, incoming: Path, name: str) -> Path:
    """Deliver a downlink as a transfer would: copied beside, then renamed into the folder."""
    staging = incoming / f".{name}.partial"
    shutil.copytree(source, staging)
    return staging.rename(incoming / name)


@pytest.fixture(scope="module")
def corner_downlink(tiny_sim: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A revisit of one corner of the tiny site: a window of each tiny exposure as a new product."""
    out = tmp_path_factory.mktemp("corner") / "downlink"
    window_downlink(tiny_sim / "downlink", out, size_px=CORNER_WINDOW_PX,
                    first_px=CORNER_FIRST_PX, count=6, tag="corner")
    return out


def _versions(sessions: sessionmaker[Session]) -> list[ModelVersion]:
    with sessions() as session:
        return list(session.scalars(select(ModelVersion).order_by(ModelVersion.version).options(
            selectinload(ModelVersion.maplet_revisions), selectinload(ModelVersion.downlinks),
            selectinload(ModelVersion.parent))))


def _jobs(sessions: sessionmaker[Session], kind: JobKind, *where) -> list[Job]:
    with sessions() as session:
        return list(session.scalars(select(Job).where(Job.kind == kind, *where)
                                    .order_by(Job.id)))


def _count(sessions: sessionmaker[Session], what: type) -> int:
    with sessions() as session:
        return session.scalar(select(func.count()).select_from(what))


def _submit_refinement(env: dict[str, str], maplet_id: int) -> subprocess.CompletedProcess:
    """workers.tasks.submit_refinement in a process on the test broker and catalog (the key on
    stdout)."""
    code = ("from service.catalog import open_catalog; from service.db import session_scope; "
            "from workers.tasks import submit_refinement\n"
            "with session_scope(open_catalog()) as session:\n"
            f"    print(submit_refinement(session, maplet_id={maplet_id}))")
    return subprocess.run([sys.executable, "-c", code], cwd=REPO, env=env, capture_output=True,
                          text=True, timeout=60)


def _image_sets(sessions: sessionmaker[Session]) -> dict[int, frozenset[int]]:
    """The images each maplet's coverage weighs above zero, for the maplets with DEFAULTS.min_images or
    more (those that can be refined)."""
    sets: dict[int, set[int]] = {}
    with sessions() as session:
        for maplet_id, image_id in session.execute(
                select(Coverage.maplet_id, Coverage.image_id).where(Coverage.weight > 0)):
            sets.setdefault(maplet_id, set()).add(image_id)
    return {m: frozenset(images) for m, images in sets.items() if len(images) >= DEFAULTS.min_images}


def _downlink_id(sessions: sessionmaker[Session], name: str) -> int:
    with sessions() as session:
        return session.scalars(select(Downlink.id).filter_by(name=name)).one()


def _wait_for_version(sessions: sessionmaker[Session], number: int, processes: list[Worker]
                      ) -> None:
    """Until version `number` is published and no fusion job is left unfinished: a fusion
    goes on after its publication to make the console's 3D document of the new version."""
    wait_for(lambda: len(_versions(sessions)) >= number
             and all(j.status is JobStatus.DONE for j in _jobs(sessions, JobKind.FUSE)),
             f"model version {number}, its fusion done", processes, timeout=DOWNLINK_TIMEOUT_S)


def _files(data_dir: Path, version: ModelVersion) -> dict[str, str]:
    """Each artifact's recorded checksum, once its file is verified against it."""
    for record in version.artifacts.values():
        artifact_path(data_dir, record, verify=True)
    return {role: record["sha256"] for role, record in version.artifacts.items()}


def test_downlinks_dropped_into_the_watched_folder_become_versions(
        tiny_sim: Path, corner_downlink: Path, incoming: Path, catalog: sessionmaker[Session],
        settings: WorkerSettings, client: Celery, watcher: Worker, worker_env: dict[str, str],
        start_worker: Callable[..., Worker]) -> None:
    worker = start_worker(lambda name: pwm_worker_command(name, 2))
    processes = [worker, watcher]

    # A downlink dropped into the folder: a refined version, with no further command.
    first = _drop(tiny_sim / "downlink", incoming, "dl-001")
    _wait_for_version(catalog, 2, processes)
    start, refined = _versions(catalog)
    first_id = _downlink_id(catalog, "dl-001")
    refines = _jobs(catalog, JobKind.REFINE)
    maplets = _image_sets(catalog)
    assert (start.kind, refined.kind, refined.parent.version) == (
        ModelKind.START, ModelKind.REFINED, start.version)
    assert [d.name for d in refined.downlinks] == ["dl-001"]
    assert {j.maplet_id for j in refines} == maplets.keys()
    assert len(refines) == len(refined.maplet_revisions) == len(maplets) > 1
    assert all((j.status, j.attempts, j.downlink_id) == (JobStatus.DONE, 1, first_id)
               for j in refines)
    [fuse] = _jobs(catalog, JobKind.FUSE)
    assert (fuse.key, fuse.status, fuse.attempts) == (fuse_key(first_id), JobStatus.DONE, 1)
    assert fuse.message == f"published version {refined.version}"
    published = {v.version: _files(settings.data_dir, v) for v in (start, refined)}

    # The same downlink delivered twice: again by its path, and as a copy under another name.
    again = client.send_task(ingest_downlink.name, args=[str(first)],
                             kwargs={"key": ingest_key(first)})
    assert not result_of(again, processes)["ran"]
    copy = _drop(tiny_sim / "downlink", incoming, "dl-001-again")
    wait_for(lambda: [j.status for j in _jobs(catalog, JobKind.INGEST,
                                              Job.key == ingest_key(copy))] == [JobStatus.DONE],
             "the ingest of the copy", processes)
    assert len(_jobs(catalog, JobKind.REFINE)) == len(refines)
    assert len(_jobs(catalog, JobKind.FUSE)) == 1
    assert _count(catalog, MapletRevision) == len(refines)
    assert _count(catalog, Image) == len(list((first / "images").glob("*.xml")))
    assert [v.version for v in _versions(catalog)] == [start.version, refined.version]

    # A revisit of one corner: only the maplets whose image set changed are refined.
    _drop(corner_downlink, incoming, "dl-002")
    _wait_for_version(catalog, 3, processes)
    corner_id = _downlink_id(catalog, "dl-002")
    now = _image_sets(catalog)
    changed = {m for m in now if now[m] != maplets.get(m)}
    corner = _jobs(catalog, JobKind.REFINE, Job.downlink_id == corner_id)
    # The maplets whose image set changed, and those alone: the ones the corner's images weigh
    # into, any that its coverage update re-weighed against the refined shape (which moves
    # what their older images show of them), and any it tiled where its images newly see enough;
    # not all of those tiled before.
    assert 0 < len(corner) == len(changed) and len(changed & maplets.keys()) < len(maplets)
    assert {j.maplet_id for j in corner} == changed
    assert all((j.status, j.attempts) == (JobStatus.DONE, 1) for j in corner)
    versions = _versions(catalog)
    assert [v.version for v in versions] == [start.version, refined.version, refined.version + 1]
    revisit = versions[-1]
    assert (revisit.kind, revisit.parent.version) == (ModelKind.REFINED, refined.version)
    assert sorted(d.name for d in revisit.downlinks) == ["dl-001", "dl-002"]
    before = {r.maplet_id: r.id for r in refined.maplet_revisions}
    after = {r.maplet_id: r.id for r in revisit.maplet_revisions}
    # every maplet of before, and those the corner's place added
    assert after.keys() >= before.keys()
    assert {m for m in after if after[m] != before.get(m)} == changed
    assert revisit.statistics["maplets_changed"] == len(changed)
    assert _count(catalog, MapletRevision) == len(refines) + len(changed)
    # The earlier versions are as they were published, and still readable.
    assert {v.version: _files(settings.data_dir, v) for v in versions[:2]} == published
    assert len(version_mesh(settings.data_dir, versions[0]).faces) == start.statistics["faces"]
    assert [j.attempts for j in _jobs(catalog, JobKind.FUSE)] == [1, 1]
    assert "ingest submitted" in watcher.output() and watcher.process.poll() is None

    # A refinement asked for (as the API does) after a pose correction changed a maplet's input:
    # that maplet alone is refined, and fused into a version of its own.
    maplet = min(changed)
    with session_scope(catalog) as session:
        image = session.scalars(select(Image).join(Coverage).where(
            Coverage.maplet_id == maplet, Coverage.weight > 0).order_by(Image.id)).first()
        image.pose_dx_km = 1e-4
    run = _submit_refinement(worker_env, maplet)
    assert run.returncode == 0, run.stderr
    key = run.stdout.split()[-1]
    _wait_for_version(catalog, 4, processes)
    requested = _versions(catalog)[-1]
    assert (requested.parent.version, requested.statistics["maplets_changed"]) == (
        revisit.version, 1)
    assert {r.maplet_id: r.id for r in requested.maplet_revisions} != after
    assert {m for m, r in after.items()
            if r not in {x.id for x in requested.maplet_revisions}} == {maplet}
    assert [d.name for d in requested.downlinks] == sorted(d.name for d in revisit.downlinks)
    [job] = _jobs(catalog, JobKind.REFINE, Job.key == key)
    assert (job.maplet_id, job.downlink_id, job.status) == (maplet, None, JobStatus.DONE)
    assert key.startswith(f"refine:requested:{maplet}:")
    again = _submit_refinement(worker_env, maplet)
    assert again.returncode != 0 and "nothing new to refine" in again.stderr


@pytest.mark.parametrize("settings", [{"refine_passes": 2, "refine_max_passes": 2}], indirect=True)
def test_each_pass_of_a_downlink_is_fused_into_a_version_of_its_own(
        tiny_sim: Path, catalog: sessionmaker[Session], settings: WorkerSettings, client: Celery,
        start_worker: Callable[..., Worker], open_catalog_at: Callable[[str], sessionmaker[Session]],
        tmp_path: Path) -> None:
    worker = start_worker(lambda name: pwm_worker_command(name, 2))
    downlink = tiny_sim / "downlink"
    key = ingest_key(downlink)
    client.send_task(ingest_downlink.name, args=[str(downlink)], kwargs={"key": key})
    _wait_for_version(catalog, 3, [worker])
    start, first, second = _versions(catalog)
    [ingest] = _jobs(catalog, JobKind.INGEST)
    downlink_id = ingest.downlink_id
    refines = _jobs(catalog, JobKind.REFINE)
    maplets = _image_sets(catalog)
    # each maplet refined once in each pass, each fusion once, nothing tried twice
    assert settings.refine_passes == 2 and len(maplets) > 1
    assert sorted(j.maplet_id for j in refines) == sorted(2 * list(maplets))
    assert all((j.status, j.attempts, j.downlink_id) == (JobStatus.DONE, 1, downlink_id)
               for j in refines)
    fuses = _jobs(catalog, JobKind.FUSE)
    assert [f.key for f in fuses] == [fuse_key(downlink_id), fuse_key(downlink_id, 2)]
    assert all((f.status, f.attempts) == (JobStatus.DONE, 1) for f in fuses)
    assert fuses[0].message == (f"published version {first.version}; {len(maplets)} maplets due "
                                f"for another pass")
    assert fuses[1].message == f"published version {second.version}"
    # the second pass starts from the version that fused the first
    assert (first.parent.version, second.parent.version) == (start.version, first.version)
    assert [d.id for d in first.downlinks] == [d.id for d in second.downlinks] == [downlink_id]
    first_pass = {r.maplet_id: r for r in first.maplet_revisions}
    assert first_pass.keys() == {r.maplet_id for r in second.maplet_revisions} == maplets.keys()
    for revision in second.maplet_revisions:
        assert (revision.statistics["pass"], revision.statistics["model_version"]) == (2, first.version)
        earlier = first_pass[revision.maplet_id].statistics
        assert (earlier["pass"], earlier["model_version"]) == (1, start.version)
    assert _count(catalog, MapletRevision) == 2 * len(maplets)
    # delivered again: nothing is refined or fused again, by the task or by the reconciler
    assert not result_of(client.send_task(ingest_downlink.name, args=[str(downlink)],
                                          kwargs={"key": key}), [worker])["ran"]
    time.sleep(3 * RECONCILE_INTERVAL_S)
    assert len(_versions(catalog)) == 3 and len(_jobs(catalog, JobKind.FUSE)) == 2
    assert len(_jobs(catalog, JobKind.REFINE)) == len(refines)
    # the conductor's one order, driven in one process: the same versions, to the byte
    in_process = open_catalog_at(f"sqlite:///{tmp_path / 'in_process.sqlite'}")
    run = run_directory(in_process, downlink, data_dir=tmp_path / "data", config=settings.refinement())
    assert run.versions == [first.version, second.version]
    assert [_files(tmp_path / "data", v)["ply"] for v in _versions(in_process)] == [
        _files(settings.data_dir, v)["ply"] for v in (start, first, second)]


def test_a_downlink_that_states_its_pose_knowledge_is_adjusted_by_the_workers(
        tiny_nav_sim: Path, catalog: sessionmaker[Session], client: Celery,
        start_worker: Callable[..., Worker]) -> None:
    worker = start_worker(lambda name: pwm_worker_command(name, 2))
    downlink = tiny_nav_sim / "downlink"
    client.send_task(ingest_downlink.name, args=[str(downlink)], kwargs={"key": ingest_key(downlink)})
    # the first fusion, then (the poses still tens of pixels off) the maplets' registrations fed
    # back into the adjustment by the fusion job, and the maplets refined again and fused
    _wait_for_version(catalog, 3, [worker])
    with catalog() as session:
        report = session.scalars(select(Downlink.pose_adjustment)).one()
        assert (report["knowledge"], report["note"]) == ("nav:3,1,50,20", "adjusted")
        assert report["source"].startswith("stated in") and report["los_posterior_px"] < 0.5 * report["los_prior_px"]
        assert report["feedback"]["note"] == "adjusted" and report["feedback"]["landmarks"] > 3
        images = session.scalars(select(Image)).all()
        assert images and all(i.pose_corrected_at is not None and i.pose_sigma["knowledge"] for i in images)
        # the maplets were weighed and refined with the corrected poses, against the first fusion
        # and again against the second: their input names them
        made_on = [r.statistics["model_version"] for r in session.scalars(select(MapletRevision))]
        assert made_on.count(2) >= report["feedback"]["landmarks"]


# A survey's maplets: 16 nodes, within 60 m of each place's centre (issue 15: the whole flow)
@pytest.mark.parametrize("settings", [{"maplet_nodes": 16, "tile_radius_km": 0.06}], indirect=True)
def test_a_first_survey_with_no_model_becomes_a_closed_global_model(
        global_tiny_sim: Path, catalog: sessionmaker[Session], settings: WorkerSettings, client: Celery,
        start_worker: Callable[..., Worker]) -> None:
    worker = start_worker(lambda name: pwm_worker_command(name, 2))
    downlink = global_tiny_sim / "downlink"
    client.send_task(ingest_downlink.name, args=[str(downlink)], kwargs={"key": ingest_key(downlink)})
    _wait_for_version(catalog, 3, [worker])
    photogrammetric, start, refined = _versions(catalog)[:3]
    # version 1 made from the images, with no model before, version 2 from the lidar, whose spots
    # sample the body more finely than the images' stereo points: version 3 refined from it
    assert (photogrammetric.kind, photogrammetric.parent) == (ModelKind.PHOTOGRAMMETRIC, None)
    assert (start.kind, start.parent.version) == (ModelKind.LIDAR, photogrammetric.version)
    assert (refined.kind, refined.parent.version) == (ModelKind.REFINED, start.version)
    with catalog() as session:
        assert session.scalars(select(Downlink.model_note)).one().startswith(
            "version 1 (photogrammetric) made from the images, with no model before; version 2 (lidar) made from "
            "the lidar is the start: the lidar's measurements sample the body more finely")
        assert session.scalar(select(func.count()).select_from(Image).where(
            Image.pose_corrected_at.is_(None))) == 0
    # the survey's places round the body were tiled and refined, and fused into one closed surface
    # (while the feedback under the knowledge the start assumed may weigh the images again and
    # tile more places for the next round)
    maplets = _image_sets(catalog)
    fused = {r.maplet_id for r in refined.maplet_revisions}
    assert len(fused) > 1 and fused <= maplets.keys()
    assert refined.statistics["surface"] == "closed"
    # checked against the survey's lidar, catalogued by the ingest task
    assert refined.statistics["lidar"]["shots"] > 1000 and refined.statistics["lidar"]["rms_km"] < 0.012
    checks = closure(version_mesh(Path(settings.data_dir), refined))
    assert checks.closed, checks


# Maplets of 24 nodes within 1.2 m of each place's centre: each site's as many maplets as the
# harness's 40 within 2 m, at a third of the nodes (a site's level is its spacing's, pwm.tiling.level_of)
@pytest.mark.parametrize("settings", [{"maplet_nodes": 24, "tile_radius_km": 0.0012}], indirect=True)
def test_a_campaign_nests_each_site_under_the_survey_and_changes_only_about_it(
        campaign_tiny_sim: Path, catalog: sessionmaker[Session], settings: WorkerSettings, client: Celery,
        start_worker: Callable[..., Worker]) -> None:
    """Issue 16 through the workers: campaign-tiny's survey (with its start model), site A and
    site B, each delivered once the last is published."""
    worker = start_worker(lambda name: pwm_worker_command(name, 2))
    downlinks = sorted((campaign_tiny_sim / "downlinks").iterdir())
    for number, downlink in zip((2, 3, 4), downlinks, strict=True):
        client.send_task(ingest_downlink.name, args=[str(downlink)], kwargs={"key": ingest_key(downlink)})
        _wait_for_version(catalog, number, [worker])
    start, survey, site_a, site_b = _versions(catalog)
    assert [v.kind for v in (start, survey, site_a, site_b)] == [ModelKind.START] + 3 * [ModelKind.REFINED]
    with catalog() as session:
        level = {m: k for m, k in session.execute(select(Maplet.id, Maplet.level))}
    refined = [{j.maplet_id for j in _jobs(catalog, JobKind.REFINE, Job.downlink_id == _downlink_id(catalog, d.name))}
               for d in downlinks]
    assert all(refined)
    # each site tiled at its own level, 16x and more finer than the survey's; site B's downlink
    # refines none of site A's maplets (a site's images may refine a survey maplet they suit)
    coarse = min(level[m] for m in refined[0])
    assert all(any(level[m] <= coarse - 4 for m in r) for r in refined[1:])
    assert not refined[2] & refined[1]
    # site B's version: the survey level's surface not made again, site A's region carried over,
    # site B's laid; the model changed only about site B, and is one closed surface
    assert site_b.statistics["composition"] == {"regions_laid": 1, "regions_carried": 1,
                                                "closed_levels_made": False}
    data = Path(settings.data_dir)
    meshes = [version_mesh(data, v) for v in (site_a, site_b)]
    scenario = json.loads((campaign_tiny_sim / "truth" / downlinks[2].name / "manifest.json").read_text())["scenario"]
    changed = meshes[1].vertices[meshes[1].faces[~np.isin(face_keys(meshes[1]), face_keys(meshes[0]))]]
    direction = changed.mean(axis=1) / np.linalg.norm(changed.mean(axis=1), axis=1, keepdims=True)
    off = np.degrees(np.arccos(direction @ latlon_to_unit(scenario["site_lat_deg"], scenario["site_lon_deg"])))
    assert len(changed) and off.max() < 12.0  # the site is 2.3 deg across, its region's margin 8 deg
    checks = closure(meshes[1])
    assert checks.closed, checks


def test_a_refinement_lost_with_its_pool_process_is_redelivered_and_done_once(
        tiny_sim: Path, catalog: sessionmaker[Session], client: Celery,
        start_worker: Callable[..., Worker]) -> None:
    worker = start_worker(lambda name: pwm_worker_command(name, 1))
    downlink = tiny_sim / "downlink"
    client.send_task(ingest_downlink.name, args=[str(downlink)],
                     kwargs={"key": ingest_key(downlink)})

    def refining() -> list[Job]:
        return _jobs(catalog, JobKind.REFINE, Job.status == JobStatus.RUNNING,
                     Job.progress >= 0.2)

    wait_for(lambda: bool(refining()), "a refinement under way", [worker])
    [lost] = refining()
    [pool_process] = worker.children()
    os.kill(pool_process, signal.SIGKILL)
    # Killed in the middle of its first attempt.
    assert [(j.status, j.attempts) for j in _jobs(catalog, JobKind.REFINE, Job.key == lost.key)
            ] == [(JobStatus.RUNNING, 1)]

    _wait_for_version(catalog, 2, [worker])
    refines = _jobs(catalog, JobKind.REFINE)
    retaken = next(j for j in refines if j.key == lost.key)
    assert (retaken.status, retaken.attempts, retaken.progress) == (JobStatus.DONE, 2, 1.0)
    # Taken over once the lost attempt's heartbeat was the grace old, not after the hard limit.
    assert (timedelta(seconds=HEARTBEAT_GRACE_S) <= retaken.started_at - lost.started_at
            < timedelta(seconds=TIME_LIMIT_S))
    assert all((j.status, j.attempts) == (JobStatus.DONE, 1) for j in refines if j is not retaken)
    with catalog() as session:
        revisions = session.execute(select(MapletRevision.maplet_id, MapletRevision.revision)
                                    ).all()
        lidvids = session.scalars(select(Image.lidvid)).all()
    assert sorted(m for m, _ in revisions) == sorted(j.maplet_id for j in refines)
    assert {j.maplet_id for j in refines} == _image_sets(catalog).keys()
    assert {r for _, r in revisions} == {1}
    assert len(lidvids) == len(set(lidvids)) == len(list((downlink / "images").glob("*.xml")))
    versions = _versions(catalog)
    assert [v.version for v in versions] == [1, 2]
    assert len(versions[-1].maplet_revisions) == len(refines) > 1
    assert [(j.status, j.attempts) for j in _jobs(catalog, JobKind.FUSE)] == [(JobStatus.DONE, 1)]
    assert [(j.status, j.attempts) for j in _jobs(catalog, JobKind.INGEST)] == [
        (JobStatus.DONE, 1)]
    assert worker.process.poll() is None and pool_process not in worker.children()
    print(f"\nrefinement taken over {(retaken.started_at - lost.started_at).total_seconds():.1f} s"
          f" after the lost attempt began (heartbeat grace {HEARTBEAT_GRACE_S:g} s)")
