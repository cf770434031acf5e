"""Distributed commands: a Celery worker, and the watcher that submits new downlinks' ingest."""

from __future__ import annotations

from pathlib import Path

import typer

from service.cli.app import app, setup_logging


@app.command()
def watch(
    directory: Path = typer.Argument(..., exists=True, file_okay=False,
                                     help="folder where downlink directories arrive"),
    quiet_seconds: float = typer.Option(60.0, min=0.0,
                                        help="a directory without manifest.json is complete once unchanged this "
                                             "long, s"),
    poll_seconds: float = typer.Option(5.0, min=0.01, help="look for new directories this often, s"),
    once: bool = typer.Option(False, "--once", help="look once and exit"),
    verbose: bool = typer.Option(False, "--verbose", "-v"),
) -> None:
    """Submit the ingest of each new downlink directory under DIRECTORY once it is complete
    (manifest.json present, or quiet); with PWM_BROKER_URL the workers run it, else it runs here."""
    from service.catalog import open_catalog
    from service.watch import watch as watch_directory
    from workers.tasks import submit_ingest

    setup_logging(verbose)
    open_catalog()  # migrated before the first submission
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
