"""The `pwm` Typer app and what its command modules share."""

from __future__ import annotations

import dataclasses
import json
import logging
from typing import Any

import typer

from pwm.config import DEFAULTS, RefinementConfig

app = typer.Typer(help="Shape modeling of an asteroid with pixel-weighted maplets.", no_args_is_help=True,
                  add_completion=False, pretty_exceptions_enable=False)

# Options of the commands that read a downlink directory through its SPICE kernels.
INSTRUMENT = typer.Option(-64361, help="NAIF id of the camera (default: OSIRIS-REx MapCam)")
TARGET = typer.Option("BENNU", help="SPICE name of the target body")
BODY_FRAME = typer.Option("IAU_BENNU", help="body-fixed frame of the target")


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
