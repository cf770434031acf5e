"""The job queue of `pwm serve` without a broker: work runs after the response, not inside it.

Without a broker, Celery runs a task where it is sent (workers.app: always eager), so
`POST /ingests` would ingest, refine and fuse a downlink before answering. BackgroundQueue
records the ingest job (queued) and answers with its key at once; the job, with the refinements
and the fusion it leads to, runs in one spawned process of its own, one ingest at a time in the
order asked (SPICE's kernel pool is per process and not thread-safe, so never in a thread of
the server). The process reads the same PWM_* settings from the environment. Refinements asked
for directly are run by the wrapped queue.
"""

from __future__ import annotations

import logging
import multiprocessing
from concurrent.futures import Future, ProcessPoolExecutor
from pathlib import Path

from sqlalchemy.orm import Session, sessionmaker

from service.db import session_scope
from service.jobs import JobQueue, submit_job
from service.rows import JobKind, JobStatus

log = logging.getLogger(__name__)


def _ingest(directory: str) -> str:
    """The ingest job of `directory` run to its end in this process (Celery eager)."""
    from workers.tasks import submit_ingest

    return submit_ingest(Path(directory))


def _report(future: Future[str]) -> None:
    if (exc := future.exception()) is not None:  # the job row holds the outcome already
        log.error("background ingest failed: %s", exc)


class BackgroundQueue:
    """A JobQueue (service.jobs) running ingests in a background process; see the module."""

    def __init__(self, inner: JobQueue) -> None:
        self.inner = inner
        self.pool = ProcessPoolExecutor(max_workers=1, mp_context=multiprocessing.get_context("spawn"))

    def submit_ingest(self, directory: Path, *, sessions: sessionmaker[Session]) -> str:
        from workers.tasks import ingest_key

        key = ingest_key(directory)
        with session_scope(sessions) as session:
            done = submit_job(session, kind=JobKind.INGEST, key=key).status is JobStatus.DONE
        if not done:
            self.pool.submit(_ingest, str(Path(directory).resolve())).add_done_callback(_report)
        return key

    def submit_refinement(self, session: Session, *, maplet_id: int) -> str:
        return self.inner.submit_refinement(session, maplet_id=maplet_id)

    def close(self) -> None:
        """Wait for the ingests asked for, then stop the background process."""
        self.pool.shutdown(wait=True)
