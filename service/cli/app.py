"""The `pwm` Typer app and what its command modules share."""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import re
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

import typer
from typer.core import TyperGroup

from pwm.config import DEFAULTS, RefinementConfig

if TYPE_CHECKING:
    from pwm.camera import PoseCorrection
    from pwm.io.downlink import DownlinkViews
    from service.ingest import Failure

# The largest exit status a command gives for its failed files (`exit_status`): below the
# shells' 126 and up, which mean "not run" and "killed by a signal".
MAX_EXIT_STATUS = 100
# The largest id, row count or offset a command passes to the catalog (ids are 32-bit integers).
MAX_ROW_ID = 2**31 - 1


class _Commands(TyperGroup):
    """pwm's commands, with one answer to PWM_* settings that make no valid settings
    (service.settings.BadEnvironment), whichever command read them: a line per bad variable on
    stderr, exit status 2."""

    def invoke(self, ctx: Any) -> Any:
        try:
            return super().invoke(ctx)
        except Exception as exc:
            from service.settings import BadEnvironment  # imported already when it is one

            if not isinstance(exc, BadEnvironment):
                raise
            for problem in exc.problems:
                typer.echo(f"error: {problem}", err=True)
            raise typer.Exit(2) from None


# Help is Markdown: a docstring's paragraphs are rewrapped to the terminal, where typer's "rich"
# mode keeps each docstring line break (sentences cut mid-line in `pwm --help`); every sub-app
# takes the same (HELP_MARKUP).
HELP_MARKUP: Literal["markdown"] = "markdown"
app = typer.Typer(help="Shape modeling of an asteroid with pixel-weighted maplets.", no_args_is_help=True,
                  add_completion=False, pretty_exceptions_enable=False, cls=_Commands,
                  rich_markup_mode=HELP_MARKUP)

# Overrides of the commands that read a downlink directory through its SPICE kernels: by
# default the labels and the kernels say what each image is (pwm.io.downlink).
INSTRUMENT = typer.Option(None, help="only this camera's images (NAIF name or id), taken for those "
                          "whose label names no known instrument; default: each image's own")
TARGET = typer.Option(None, help="target body (SPICE name or id) in place of the labels'")
BODY_FRAME = typer.Option(None, help="body-fixed frame in place of the target's")


def finite(*, ge: float | None = None, gt: float | None = None,
           le: float | None = None) -> Callable[[str], float]:
    """The `parser` of a number option: a finite number within the bounds given, else a usage
    error saying what the option takes (typer's own float takes inf and nan, and its range check
    lets nan through)."""
    bounds = [f"{sign} {bound:g}" for sign, bound in ((">=", ge), (">", gt), ("<=", le)) if bound is not None]
    accepted = " ".join(["a finite number", " and ".join(bounds)]).strip()

    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            value = math.nan
        if not (math.isfinite(value) and (ge is None or value >= ge) and (gt is None or value > gt)
                and (le is None or value <= le)):
            raise typer.BadParameter(f"{text!r} is not {accepted}")
        return value

    return parse


# The parsers of a surface point's latitude and east longitude (deg), as the API takes them.
LATITUDE = finite(ge=-90.0, le=90.0)
LONGITUDE = finite(ge=-360.0, le=360.0)


def version_ref(text: str) -> str:
    """The `parser` of a version argument: a version number, a release tag, `latest` or
    `released` (service.api.schemas.VERSION_REF_PATTERN), else a usage error."""
    from service.api.schemas import VERSION_REF_PATTERN

    if not re.fullmatch(VERSION_REF_PATTERN, text):
        raise typer.BadParameter(f"{text!r} is not a version number, release tag, latest or released")
    return text


def exit_status(failed: int) -> int:
    """A command's exit status for its failed files: their number, at most MAX_EXIT_STATUS."""
    return min(failed, MAX_EXIT_STATUS)


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
