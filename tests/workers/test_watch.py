"""The watcher: when a delivered directory counts as complete, submitting each once, and
`pwm watch --once` without a broker, where the submitted work runs in the watcher's process."""

from __future__ import annotations

import os
import shutil
import subprocess
import time
from pathlib import Path

from harness import PWM, REPO
from sqlalchemy import select

from pwm.config import DEFAULTS
from service.db import make_engine, make_sessionmaker
from service.rows import Image, Job, JobKind, JobStatus, ModelVersion
from service.watch import MANIFEST_NAME, Watcher, completeness
from workers.tasks import ingest_key

QUIET_S = 60.0


def _deliver(directory: Path, *names: str) -> Path:
    directory.mkdir(parents=True, exist_ok=True)
    for name in names:
        (directory / name).write_text(name)
    return directory


def test_a_directory_is_complete_with_its_manifest_or_once_quiet(tmp_path: Path) -> None:
    empty = _deliver(tmp_path / "empty")
    partial = _deliver(tmp_path / "partial", "a.xml", "a.fits")
    later = time.time() + QUIET_S + 1
    assert completeness(empty, quiet_s=QUIET_S, now=later) is None
    assert completeness(partial, quiet_s=QUIET_S) is None
    assert completeness(partial, quiet_s=QUIET_S, now=later) == "quiet"
    # A copy that keeps its source's old modification times is still a fresh change.
    old = time.time() - 10 * QUIET_S
    os.utime(partial / "a.xml", (old, old))
    copied = tmp_path / "copied"
    shutil.copytree(partial, copied)
    assert (copied / "a.xml").stat().st_mtime == old
    assert completeness(copied, quiet_s=QUIET_S) is None
    _deliver(partial, MANIFEST_NAME)
    assert completeness(partial, quiet_s=QUIET_S) == "manifest"


def test_the_watcher_submits_each_complete_directory_once(tmp_path: Path) -> None:
    root = tmp_path / "incoming"
    _deliver(root / "dl-1", "a.xml", MANIFEST_NAME)
    _deliver(root / ".dl-2.partial", "b.xml", MANIFEST_NAME)
    _deliver(root / "dl-3", "c.xml")
    submitted: list[Path] = []
    refusals = iter([RuntimeError("broker down")])

    def submit(directory: Path) -> str:
        if directory.name == "dl-3" and (refusal := next(refusals, None)):
            raise refusal
        submitted.append(directory)
        return ingest_key(directory)

    watcher = Watcher(root, submit=submit, quiet_s=0.0)
    assert watcher.poll() == [root / "dl-1"]  # dl-3 refused: tried again next time
    (root / ".dl-2.partial").rename(root / "dl-2")
    assert watcher.poll() == [root / "dl-2", root / "dl-3"]
    assert watcher.poll() == []
    assert submitted == [root / "dl-1", root / "dl-2", root / "dl-3"]
    assert watcher.submitted[root / "dl-2"] == ingest_key(root / "dl-2")


def test_watch_once_without_a_broker_runs_the_downlink_in_process(tiny_sim: Path,
                                                                  tmp_path: Path) -> None:
    incoming = tmp_path / "incoming"
    shutil.copytree(tiny_sim / "downlink", incoming / "dl-001")
    data = tmp_path / "data"
    env = os.environ | {"PWM_DATA_DIR": str(data), "PWM_BROKER_URL": "",
                        "PWM_DATABASE_URL": "", "PWM_MAPLET_NODES": "24",
                        "PWM_TILE_RADIUS_KM": "0.0008", "PWM_REFINE_MAX_PASSES": "2"}
    for _ in range(2):  # a restarted watcher submits again, and nothing new is done
        run = subprocess.run([str(PWM), "watch", str(incoming), "--once"], cwd=REPO, env=env,
                             capture_output=True, text=True, timeout=300)
        assert run.returncode == 0, run.stderr
        assert "complete (manifest): ingest submitted" in run.stderr
    engine = make_engine(f"sqlite:///{data / 'catalog.sqlite'}")
    with make_sessionmaker(engine)() as session:
        versions = session.scalars(select(ModelVersion.version)).all()
        jobs = session.scalars(select(Job)).all()
    engine.dispose()
    kinds = [j.kind for j in jobs]
    # one version per pass (RefinementConfig.passes, 2): each maplet refined once in each
    assert DEFAULTS.passes == 2 and versions == [1, 2, 3]
    assert kinds.count(JobKind.INGEST) == 1 and kinds.count(JobKind.FUSE) == 2
    refined = [j.maplet_id for j in jobs if j.kind is JobKind.REFINE]
    assert refined and sorted(refined) == sorted(2 * list(set(refined)))
    assert all((j.status, j.attempts) == (JobStatus.DONE, 1) for j in jobs)


def test_a_directory_written_to_after_its_submission_is_submitted_again_once_quiet(
        tmp_path: Path) -> None:
    root = tmp_path / "incoming"
    late = _deliver(root / "dl-1", "a.xml", MANIFEST_NAME)
    submitted: list[Path] = []

    def submit(directory: Path) -> str:
        submitted.append(directory)
        return ingest_key(directory)

    watcher = Watcher(root, submit=submit, quiet_s=0.0)
    assert watcher.poll() == [late]
    assert watcher.poll() == []
    time.sleep(0.01)
    _deliver(late, "a.fits")  # the data file, after its label and the manifest
    assert watcher.poll() == [late]
    assert watcher.poll() == []
    waiting = Watcher(root, submit=submit, quiet_s=QUIET_S)
    assert waiting.poll() == [late]  # the manifest is there
    time.sleep(0.01)
    _deliver(late, "b.fits")
    assert waiting.poll() == []  # changed, but not quiet yet
    assert submitted == [late, late, late]


def test_a_downlink_whose_data_arrived_after_its_ingest_is_ingested_again(
        tiny_sim: Path, tmp_path: Path) -> None:
    """`pwm watch --once` without a broker, twice: the first time one image's data file is not
    there yet (rejected missing_file); the second finds the directory changed since its ingest
    started, queues the done ingest job again, and the image is accepted."""
    incoming = tmp_path / "incoming"
    downlink = incoming / "dl-001"
    shutil.copytree(tiny_sim / "downlink", downlink)
    data_file = sorted((downlink / "images").glob("*.fits"))[0]
    held = tmp_path / data_file.name
    data_file.rename(held)
    data = tmp_path / "data"
    env = os.environ | {"PWM_DATA_DIR": str(data), "PWM_BROKER_URL": "",
                        "PWM_DATABASE_URL": "", "PWM_MAPLET_NODES": "24",
                        "PWM_TILE_RADIUS_KM": "0.0008", "PWM_REFINE_MAX_PASSES": "2"}

    def image() -> tuple[str, str | None, int]:
        engine = make_engine(f"sqlite:///{data / 'catalog.sqlite'}")
        with make_sessionmaker(engine)() as session:
            row = session.scalars(select(Image).where(
                Image.label_path == str(data_file.with_suffix(".xml")))).one()
            job = session.scalars(select(Job).where(Job.kind == JobKind.INGEST)).one()
            found = (row.status.value, row.rejection_code, job.attempts)
        engine.dispose()
        return found

    for _ in range(2):
        run = subprocess.run([str(PWM), "watch", str(incoming), "--once"], cwd=REPO, env=env,
                             capture_output=True, text=True, timeout=300)
        assert run.returncode == 0, run.stderr
        if held.exists():
            assert image() == ("rejected", "missing_file", 1)
            held.rename(data_file)
    assert image() == ("accepted", None, 2)
