"""The `pwm` Typer app and what its command modules share."""

from __future__ import annotations

import dataclasses
import json
import logging
from collections.abc import Iterable
from pathlib import Path
from typing import TYPE_CHECKING, Any

import typer

from pwm.config import DEFAULTS, RefinementConfig

if TYPE_CHECKING:
    from pwm.camera import PoseCorrection
    from pwm.io.downlink import DownlinkViews
    from service.ingest import Failure

app = typer.Typer(help="Shape modeling of an asteroid with pixel-weighted maplets.", no_args_is_help=True,
                  add_completion=False, pretty_exceptions_enable=False)

# Overrides of the commands that read a downlink directory through its SPICE kernels: by
# default the labels and the kernels say what each image is (pwm.io.downlink).
INSTRUMENT = typer.Option(None, help="only this camera's images (NAIF name or id), taken for those "
                          "whose label names no known instrument; default: each image's own")
TARGET = typer.Option(None, help="target body (SPICE name or id) in place of the labels'")
BODY_FRAME = typer.Option(None, help="body-fixed frame in place of the target's")


def setup_logging(verbose: bool) -> None:
    """Log to stderr: INFO, or DEBUG with --verbose."""
    logging.basicConfig(level=logging.DEBUG if verbose else logging.INFO,
                        format="%(asctime)s %(levelname)s %(message)s", datefmt="%H:%M:%S")


def echo_json(value: object) -> None:
    """Print `value` as indented JSON."""
    typer.echo(json.dumps(value, indent=2))


def refinement_config(base: RefinementConfig = DEFAULTS, **changes: Any) -> RefinementConfig:
    """`base` with the options given (None: keep base's), or a usage error naming what is wrong."""
    try:
        return dataclasses.replace(base, **{k: v for k, v in changes.items() if v is not None})
    except ValueError as exc:
        raise typer.BadParameter(str(exc)) from None


def downlink_views(downlink: Path, *, instrument: str | None, target: str | None, body_frame: str | None,
                   corrections: dict[str, PoseCorrection] | None = None) -> DownlinkViews:
    """The downlink's views (pwm.io.downlink.read_downlink), each skipped product reported on
    stderr; a clear message and exit status 1 when nothing usable is left."""
    from pwm.io.downlink import read_downlink
    from pwm.io.spice_kernels import KernelError

    try:
        read = read_downlink(downlink, instrument=instrument, target=target, body_frame=body_frame,
                             corrections=corrections)
    except (ValueError, KernelError) as exc:  # NoUsableImages is a ValueError
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(1) from None
    for skipped in read.skipped:
        typer.echo(f"skipped {skipped.path}: {skipped.code}: {skipped.reason}", err=True)
    return read


def echo_rejected(failures: Iterable[Failure]) -> None:
    """Each file an ingest rejected, with its code and reason, on stderr."""
    for failure in failures:
        typer.echo(f"rejected {failure.path}: {failure.code}: {failure.reason}", err=True)


def downlink_report(read: DownlinkViews) -> dict:
    """What a downlink read gave, for a command's JSON report: target, frame, cameras and the
    products skipped (file, code, reason)."""
    return {"target": read.target, "target_id": read.target_id, "body_frame": read.body_frame,
            "instruments": {str(k): v for k, v in read.instruments.items()},
            "skipped": [dataclasses.asdict(s) for s in read.skipped]}
