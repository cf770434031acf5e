"""`pwm downlinks`: each downlink's outcome, as the API's /downlinks gives it."""

from __future__ import annotations

import typer

from service.cli.app import MAX_ROW_ID, app, echo_json


@app.command()
def downlinks(
    status: str | None = typer.Option(None, help="received | ingesting | ingested | failed"),
    limit: int = typer.Option(50, min=1, max=MAX_ROW_ID, help="at most this many rows, newest first"),
    files: bool = typer.Option(False, "--files", help="also list each unused file and why"),
    json_out: bool = typer.Option(False, "--json", help="print JSON instead of a table"),
) -> None:
    """List downlinks with their outcome: products accepted, rejected and in conflict (outcome rejected when every
    product failed), lidar products accepted and rejected with their shots, kernels, unused files and repeated
    deliveries; below the table, how many maplets' current revisions were made with another refinement
    configuration than the present one, which no downlink re-refines unless PWM_REFINE_ON_CONFIG_CHANGE is set
    (`pwm refine-catalog --because-config-changed` does)."""
    from sqlalchemy import select

    from service.catalog import open_catalog
    from service.downlinks import configuration_note, downlink_ids, downlink_summaries
    from service.rows import Acceptance, DownlinkFile, DownlinkStatus
    from service.settings import get_settings

    try:
        wanted = None if status is None else DownlinkStatus(status)
    except ValueError:
        raise typer.BadParameter(f"expected one of {', '.join(DownlinkStatus)}", param_hint="--status") from None
    settings = get_settings()
    with open_catalog(settings)() as session:
        ids, _ = downlink_ids(session, status=wanted, limit=limit)
        rows = downlink_summaries(session, ids)
        note = configuration_note(session, settings.refinement())
        unused = {d.id: [(f.path, f.code, f.reason) for f in session.scalars(
            select(DownlinkFile).filter_by(downlink_id=d.id).order_by(DownlinkFile.path))]
            for d in rows} if files or json_out else {}
    if json_out:
        echo_json([{"id": d.id, "name": d.name, "path": d.path, "received_at": d.received_at.isoformat(),
                    "status": d.status.value, "outcome": d.outcome.value, "accepted": d.accepted,
                    "rejected": d.rejected, "conflict": d.conflict, "kernels": d.kernels,
                    "lidar_accepted": d.lidar.get(Acceptance.ACCEPTED, 0),
                    "lidar_rejected": d.lidar.get(Acceptance.REJECTED, 0), "lidar_shots": d.lidar_shots,
                    "lidar_valid_shots": d.lidar_valid_shots,
                    "unused_files": [dict(zip(("path", "code", "reason"), f, strict=True)) for f in unused[d.id]],
                    "repeat_count": d.repeat_count,
                    "last_seen_at": d.last_seen_at.isoformat() if d.last_seen_at else None,
                    "model_note": d.model_note, "pose_adjustment": d.pose_adjustment} for d in rows])
        return
    typer.echo(f"{'id':>4} {'downlink':<32} {'status':<10} {'outcome':<9} {'accepted':>8} {'rejected':>8} "
               f"{'conflict':>8} {'kernels':>7} {'unused':>6} {'repeats':>7}")
    for d in rows:
        typer.echo(f"{d.id:>4} {d.name[:32]:<32} {d.status.value:<10} {d.outcome.value:<9} {d.accepted:>8} "
                   f"{d.rejected:>8} {d.conflict:>8} {d.kernels:>7} {d.unused_files:>6} {d.repeat_count:>7}")
        if d.lidar:
            typer.echo(f"      lidar: {d.lidar.get(Acceptance.ACCEPTED, 0)} products accepted "
                       f"({d.lidar_shots} shots, {d.lidar_valid_shots} valid), "
                       f"{d.lidar.get(Acceptance.REJECTED, 0)} rejected")
        if d.model_note:
            typer.echo(f"      model: {d.model_note}")
        if d.pose_adjustment:
            a = d.pose_adjustment
            after = f" -> {a['los_posterior_px']:.2f}" if "los_posterior_px" in a else ""
            tied = (f"; {a['ties']} points tied to {a['lidar_spots']} lidar spots, {a['tie_rms_m']:.2f} m RMS off them"
                    if a.get("ties") else "")
            typer.echo(f"      poses: {a['knowledge']} ({a['source']}): {a['note']}; line of sight "
                       f"{a['los_prior_px']:.2f}{after} px (1 sigma){tied}")
        for path, code, reason in unused.get(d.id, []) if files else []:
            typer.echo(f"      unused {path}: {code}: {reason}")
    if note is not None:
        typer.echo(note.line())
