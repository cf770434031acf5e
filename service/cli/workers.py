"""Distributed commands: a Celery worker, the watcher that submits new downlinks' ingest, and
the jobs: list, show, retry."""

from __future__ import annotations

import enum
import threading
import time
from datetime import datetime
from pathlib import Path
from typing import TypeVar

import typer

from service.cli.app import HELP_MARKUP, MAX_ROW_ID, app, echo_json, finite, setup_logging

E = TypeVar("E", bound=enum.StrEnum)

jobs_app = typer.Typer(help="Background jobs, as the API's /jobs shows them.", no_args_is_help=True,
                       rich_markup_mode=HELP_MARKUP)
app.add_typer(jobs_app, name="jobs")


@app.command()
def watch(
    directory: Path = typer.Argument(..., exists=True, file_okay=False,
                                     help="folder where downlink directories arrive"),
    quiet_seconds: float = typer.Option(60.0, parser=finite(ge=0.0),
                                        help="a directory without manifest.json is complete once unchanged this "
                                             "long, s"),
    poll_seconds: float = typer.Option(5.0, parser=finite(ge=0.01), help="look for new directories this often, s"),
    once: bool = typer.Option(False, "--once", help="look once and exit"),
    verbose: bool = typer.Option(False, "--verbose", "-v"),
) -> None:
    """Submit the ingest of each new downlink directory under DIRECTORY once it is complete
    (manifest.json present, or quiet); with PWM_BROKER_URL the workers run it, else it runs here."""
    from service.catalog import open_catalog
    from service.watch import watch as watch_directory
    from workers.app import get_worker_settings
    from workers.tasks import reconcile_pass, submit_ingest

    setup_logging(verbose)
    open_catalog()  # migrated before the first submission
    settings = get_worker_settings()
    if settings.broker_url and not once:
        # The watcher reconciles too, so that work the broker lost is handed over again even
        # while no worker can (all of them busy on long jobs, or none started yet).
        def reconcile_forever() -> None:
            while True:
                time.sleep(settings.reconcile_interval_s)
                reconcile_pass()

        threading.Thread(target=reconcile_forever, name="reconciler", daemon=True).start()
    watch_directory(directory, submit=submit_ingest, quiet_s=quiet_seconds, poll_s=poll_seconds,
                    once=once)


@app.command()
def worker(
    queues: str = typer.Option("ingest,refine,fuse", help="comma-separated queues to consume"),
    concurrency: int | None = typer.Option(None, min=1, help="worker processes (default: one per CPU)"),
    name: str | None = typer.Option(None, help="worker node name (default celery@HOSTNAME)"),
    loglevel: str = typer.Option("INFO", help="DEBUG | INFO | WARNING | ERROR"),
) -> None:
    """Run a Celery worker (prefork pool) on PWM_BROKER_URL, writing to PWM_DATABASE_URL."""
    from service.db import upgrade
    from workers.app import QUEUES, app as celery_app, get_worker_settings

    settings = get_worker_settings()
    if not settings.broker_url:
        raise typer.BadParameter("set PWM_BROKER_URL (e.g. redis://localhost:6379/0)",
                                 param_hint="PWM_BROKER_URL")
    wanted = [q.strip() for q in queues.split(",") if q.strip()]
    if not wanted or set(wanted) - set(QUEUES):
        raise typer.BadParameter(f"expected some of {', '.join(QUEUES)}", param_hint="--queues")
    upgrade(settings.database_url)
    # Coordination goes through the jobs table: no gossip, mingle or event heartbeats needed.
    argv = ["worker", "--pool=prefork", "-Q", ",".join(wanted), f"--loglevel={loglevel}",
            "--without-gossip", "--without-mingle", "--without-heartbeat"]
    if concurrency is not None:
        argv.append(f"--concurrency={concurrency}")
    if name is not None:
        argv += ["-n", name]
    celery_app.worker_main(argv)


@jobs_app.command("list")
def jobs_list(
    status: str | None = typer.Option(None, help="a status as shown: queued, running, lost (running with no "
                                      "heartbeat), done, failed"),
    kind: str | None = typer.Option(None, help="ingest, refine or fuse"),
    key: str | None = typer.Option(None, help="the job with this key"),
    limit: int = typer.Option(50, min=1, max=1000),
    offset: int = typer.Option(0, min=0, max=MAX_ROW_ID),
    as_json: bool = typer.Option(False, "--json", help="the page as the API's GET /jobs gives it (with the "
                                 "token)"),
) -> None:
    """Jobs, newest first: id, kind, status, attempts, progress, worker, last heartbeat, key, and the
    message or the failure's reason."""
    # Imported here, as the enums they need: every other command starts without them.
    from service.api.schemas import JobOut, Page
    from service.catalog import open_catalog
    from service.jobs import JobState, find_jobs
    from service.rows import JobKind
    from service.settings import get_settings

    state = None if status is None else _choice(JobState, status, "--status")
    job_kind = None if kind is None else _choice(JobKind, kind, "--kind")
    grace_s = get_settings().heartbeat_grace_s
    with open_catalog()() as session:
        total, rows = find_jobs(session, grace_s=grace_s, state=state, kind=job_kind, key=key, limit=limit,
                                offset=offset)
        jobs = [JobOut.shown(job, with_traceback=True, grace_s=grace_s) for job in rows]
    if as_json:
        echo_json(Page(items=jobs, total=total, limit=limit, offset=offset).model_dump(mode="json"))
        return
    typer.echo("id\tkind\tstatus\tattempts\tprogress\tworker\theartbeat\tkey\tmessage or error")
    for job in jobs:
        beat = "-" if job.heartbeat_at is None else f"{_age_s(job.heartbeat_at):.0f}s ago"
        note = job.error if job.status is JobState.FAILED else job.message
        if job.enqueue_error:
            note = f"not handed to the broker: {job.enqueue_error}"
        typer.echo(f"{job.id}\t{job.kind}\t{job.status}\t{job.attempts}\t{job.progress:.2f}\t"
                   f"{job.worker or '-'}\t{beat}\t{job.key}\t{note or ''}")
    typer.echo(f"{len(jobs)} of {total} jobs", err=True)


@jobs_app.command("show")
def jobs_show(job_id: int = typer.Argument(..., min=1, max=MAX_ROW_ID)) -> None:
    """One job as the API's GET /jobs/ID gives it (with the token: the traceback too)."""
    from service.api.schemas import JobOut
    from service.catalog import open_catalog
    from service.rows import Job
    from service.settings import get_settings

    with open_catalog()() as session:
        job = session.get(Job, job_id)
        if job is None:
            typer.echo(f"error: no job {job_id}", err=True)
            raise typer.Exit(1)
        echo_json(JobOut.shown(job, with_traceback=True, grace_s=get_settings().heartbeat_grace_s)
                  .model_dump(mode="json"))


@jobs_app.command("retry")
def jobs_retry(job_id: int = typer.Argument(..., min=1, max=MAX_ROW_ID)) -> None:
    """Run a failed or lost job again: queued and handed to the workers (PWM_BROKER_URL), or run here without a
    broker. Its attempts so far are kept."""
    from service.catalog import open_catalog
    from workers.tasks import retry

    setup_logging(False)
    try:
        key = retry(job_id, sessions=open_catalog())
    except (LookupError, ValueError) as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(1) from None
    typer.echo(key)


def _choice(enum: type[E], value: str, option: str) -> E:
    try:
        return enum(value)
    except ValueError:
        raise typer.BadParameter(f"expected one of {', '.join(enum)}", param_hint=option) from None


def _age_s(moment: datetime) -> float:
    from service.rows import utcnow

    return (utcnow() - moment).total_seconds()
