"""Laser altimetry through the Celery workers on real PostgreSQL and Redis (issue 46): global-tiny's
images alone, then its lidar alone, then a revisit of its images, each handed to the ingest task.
The images make versions 1 and 2 (no lidar yet: none checked against it); the lidar downlink's
tracks are catalogued and strip-adjusted by the ingest task to version 2, no version made; the
revisit's version is checked against the lidar and the tracks adjusted to it."""

from __future__ import annotations

import shutil
from collections.abc import Callable
from pathlib import Path

import pytest
from celery import Celery
from harness import Worker, end_to_end_settings, pwm_worker_command, wait_for
from sqlalchemy import select
from sqlalchemy.orm import Session, sessionmaker

from pwm.simulate.windows import window_downlink
from service.rows import Job, JobKind, JobStatus, LidarTrack, ModelKind, ModelVersion
from workers.app import WorkerSettings
from workers.tasks import ingest_downlink, ingest_key

TIMEOUT_S = 150.0
# The revisit: windows of the middle of a few of the survey's 320 px images.
REVISIT_PX, REVISIT_FIRST_PX, REVISIT_IMAGES = 128, (96, 96), 4


@pytest.fixture
def settings(broker_url: str, postgres_url: str, tmp_path: Path) -> WorkerSettings:
    # the survey's places: 16-node maplets within 60 m of each centre (as the survey test); the
    # images' poses known to a centimetre and a microradian (they are exact): no feedback round,
    # which the knowledge a start from nothing assumes would bring (tests/service/test_start_from_images.py)
    return end_to_end_settings(broker_url=broker_url, database_url=postgres_url, data_dir=tmp_path / "data",
                               maplet_nodes=16, tile_radius_km=0.06, pose_knowledge="0.01,1e-6")


def _part(source: Path, out: Path, *parts: str) -> Path:
    for part in parts:
        shutil.copytree(source / part, out / part)
    return out


def _versions(sessions: sessionmaker[Session]) -> list[ModelVersion]:
    with sessions() as session:
        return list(session.scalars(select(ModelVersion).order_by(ModelVersion.version)))


def _tracks(sessions: sessionmaker[Session]) -> list[LidarTrack]:
    with sessions() as session:
        return list(session.scalars(select(LidarTrack).order_by(LidarTrack.id)))


def _ingested(sessions: sessionmaker[Session], downlink: Path) -> bool:
    with sessions() as session:
        job = session.scalars(select(Job).where(Job.kind == JobKind.INGEST, Job.key == ingest_key(downlink))).first()
        return job is not None and job.status is JobStatus.DONE


def _settled(sessions: sessionmaker[Session]) -> bool:
    with sessions() as session:
        return all(j.status is JobStatus.DONE for j in session.scalars(select(Job)))


def test_images_then_lidar_then_images_through_the_workers(
        global_tiny_sim: Path, tmp_path: Path, catalog: sessionmaker[Session], settings: WorkerSettings,
        client: Celery, start_worker: Callable[..., Worker]) -> None:
    worker = start_worker(lambda name: pwm_worker_command(name, 2))
    source = global_tiny_sim / "downlink"

    def ingest(downlink: Path, done: Callable[[], bool]) -> None:
        client.send_task(ingest_downlink.name, args=[str(downlink)], kwargs={"key": ingest_key(downlink)})
        # a downlink's jobs follow one another: its ingest, then its refinements, then their fusion
        wait_for(lambda: _ingested(catalog, downlink) and done() and _settled(catalog), f"{downlink.name} done",
                 [worker], timeout=TIMEOUT_S)

    ingest(_part(source, tmp_path / "images", "images", "kernels"), lambda: len(_versions(catalog)) >= 2)
    first = _versions(catalog)
    assert [v.kind for v in first] == [ModelKind.PHOTOGRAMMETRIC, ModelKind.REFINED]
    assert all("lidar" not in v.statistics for v in first)  # no lidar yet

    ingest(_part(source, tmp_path / "lidar", "lidar", "kernels"),
           lambda: all(t.adjusted_at is not None for t in _tracks(catalog)))
    assert len(_versions(catalog)) == len(first)  # nothing to refine, no version
    tracks = _tracks(catalog)
    assert len(tracks) > 1 and {t.residual_version for t in tracks} == {first[-1].version}

    # a revisit of the middle of some of the survey's images: its maplets refined, a version fused
    again = tmp_path / "again"
    window_downlink(source, again, size_px=REVISIT_PX, first_px=REVISIT_FIRST_PX, count=REVISIT_IMAGES, tag="again")
    ingest(again, lambda: len(_versions(catalog)) > len(first)
           and {t.residual_version for t in _tracks(catalog)} == {len(_versions(catalog))})
    latest = _versions(catalog)[-1]
    assert (latest.kind, latest.parent_id) == (ModelKind.REFINED, first[-1].id)
    figures = latest.statistics["lidar"]
    # the survey's 4 m GSD model: within 3 GSD of the spots, which cross one another
    assert figures["measured"] > 1000 and figures["rms_km"] < 0.012 and figures["crossovers"] > 0
