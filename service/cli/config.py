"""`pwm config show`: the refinement configuration the environment makes, and its digest."""

from __future__ import annotations

import dataclasses
from typing import Any

import typer

from pwm.config import RefinementConfig
from service.cli.app import HELP_MARKUP, app, echo_json, refinement_config

config_app = typer.Typer(help="The effective configuration.", no_args_is_help=True, rich_markup_mode=HELP_MARKUP)
app.add_typer(config_app, name="config")


def described(config: RefinementConfig) -> dict[str, Any]:
    """`config` as JSON values (the pose knowledge as PWM_POSE_KNOWLEDGE writes it), its digest and
    the settings the digest names (pwm.config.RefinementConfig.digested)."""
    from pwm.knowledge import format_knowledge_errors

    settings = dataclasses.asdict(config)
    settings["knowledge"] = None if config.knowledge is None else format_knowledge_errors(config.knowledge)
    return {"refinement": settings, "digest": config.digest(), "in_digest": sorted(config.digested())}


@config_app.command("show")
def show() -> None:
    """Print the refinement configuration that `pwm run`, ingest and the workers use, as the PWM_* environment makes
    it from pwm.config's defaults, with its digest (part of each refinement's input hash, recorded on each revision: a
    change of a setting it names re-refines when asked, PWM_REFINE_ON_CONFIG_CHANGE or `pwm refine-catalog
    --because-config-changed`), as JSON."""
    from service.settings import get_settings

    echo_json(described(refinement_config(get_settings().refinement())))
