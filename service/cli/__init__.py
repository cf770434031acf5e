"""The `pwm` command line: one Typer app, its commands grouped by module."""

from service.cli import api, catalog, config, downlinks, kernels, models, science, spg, workers  # noqa: F401  (each module registers its commands)
from service.cli.app import app

__all__ = ["app"]

if __name__ == "__main__":
    app()
