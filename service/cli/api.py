"""Serve the HTTP API and the console."""

from __future__ import annotations

import typer

from service.cli.app import app


@app.command()
def serve(
    host: str = typer.Option("127.0.0.1", help="address to listen on"),
    port: int = typer.Option(8000, min=1, max=65535, help="port to listen on"),
) -> None:
    """Serve the HTTP API (OpenAPI at /openapi.json) over the configured catalog. Without a broker
    (PWM_BROKER_URL), a requested ingest runs after the response, in a process of its own."""
    import uvicorn

    from service.api import create_app
    from service.cli.background import BackgroundQueue
    from service.settings import get_settings
    from workers.tasks import CeleryQueue

    queue = CeleryQueue() if get_settings().broker_url else BackgroundQueue(CeleryQueue())
    try:
        uvicorn.run(create_app(job_queue=queue), host=host, port=port)
    finally:
        if isinstance(queue, BackgroundQueue):
            queue.close()
