"""The `pwm` command line: one Typer app, its commands grouped by module."""

from service.cli import (  # noqa: F401  (each module registers its commands)
    api,
    catalog,
    config,
    downlinks,
    exports,
    kernels,
    refine_catalog,
    science,
    spg,
    versions,
    workers,
)
from service.cli.app import app

__all__ = ["app"]

if __name__ == "__main__":
    app()
