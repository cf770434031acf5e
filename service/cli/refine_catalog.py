"""`pwm refine-catalog --because-config-changed`: refine, in this process, the maplets whose
current revision was made with another refinement configuration, and fuse a new version."""

from __future__ import annotations

import typer

from service.cli.app import app, setup_logging


@app.command("refine-catalog")
def refine_catalog(
    because_config_changed: bool = typer.Option(
        False, "--because-config-changed",
        help="refine them; without it, only say how many there are"),
    workers: int = typer.Option(1, min=1, help="processes refining maplets in parallel"),
    verbose: bool = typer.Option(False, "--verbose", "-v"),
) -> None:
    """Refine the maplets whose current revision was made with another refinement configuration (a changed setting
    that `pwm config show`'s digest names) under the present one, and publish a version per pass, as `pwm run` does.

    A changed configuration alone refines nothing at the next downlink unless PWM_REFINE_ON_CONFIG_CHANGE is set; this
    command is the operator's way to ask for it. Revisions made before their configuration was recorded are not
    counted: the next downlink refines them where their configuration changed.
    """
    from service.catalog import open_catalog
    from service.cli.progress import progress_bar
    from service.downlinks import configuration_note
    from service.run import refine_other_configurations
    from service.settings import get_settings

    setup_logging(verbose)
    settings = get_settings()
    config = settings.refinement()
    sessions = open_catalog(settings)
    with sessions() as session:
        note = configuration_note(session, config)
    if not because_config_changed or note is None:
        typer.echo(note.line() if note is not None else
                   f"every maplet's current revision was made with the present configuration ({config.digest()[:12]}) "
                   "or before configurations were recorded: nothing to refine")
        return
    with progress_bar() as progress:
        done = refine_other_configurations(sessions, data_dir=settings.data_dir, config=config, workers=workers,
                                           progress=progress)
    outcome = (f"published version{'s' * (len(done.versions) > 1)} {', '.join(map(str, done.versions))}"
               if done.versions else "no new version (nothing changed)")
    typer.echo(f"{len(done.revisions)} maplet refinements under configuration {config.digest()[:12]}...; {outcome}")
