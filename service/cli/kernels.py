"""`pwm kernels`: the catalogued SPICE kernels, and retiring one."""

from __future__ import annotations

from typing import TYPE_CHECKING

import typer

from service.cli.app import HELP_MARKUP, app, echo_json

if TYPE_CHECKING:
    from service.kernels import KernelListing

kernels_app = typer.Typer(help="The catalogued SPICE kernels: what each is and whether it is "
                               "used; retire one.", rich_markup_mode=HELP_MARKUP)
app.add_typer(kernels_app, name="kernels")


@kernels_app.callback(invoke_without_command=True)
def kernels(
    ctx: typer.Context,
    json_out: bool = typer.Option(False, "--json", help="print JSON instead of a table"),
) -> None:
    """List the kernels: id, kind, file, status (accepted, rejected, retired), why, the span its
    coverage windows reach (SPK, CK) and the downlinks that delivered it."""
    if ctx.invoked_subcommand is not None:
        return
    from service.catalog import open_catalog
    from service.kernels import kernel_listing

    with open_catalog()() as session:
        rows = kernel_listing(session)
    spans = _spans(rows)
    if json_out:
        echo_json([{"id": r.id, "kind": r.kind.value, "name": r.name, "path": r.path,
                    "status": r.status, "code": r.code, "reason": r.reason,
                    "coverage": None if r.coverage is None else dict(zip(
                        ("start_et", "stop_et", "start_utc", "stop_utc"),
                        (*r.coverage, *spans[r.id]), strict=True)),
                    "downlinks": r.downlinks} for r in rows])
        return
    typer.echo(f"{'id':>4} {'kind':<4} {'file':<32} {'status':<8} {'coverage (UTC)':<41} downlinks")
    for r in rows:
        span = " to ".join(s[:19] for s in spans[r.id]) if r.id in spans else "-"
        typer.echo(f"{r.id:>4} {r.kind.value:<4} {r.name[:32]:<32} {r.status:<8} {span:<41} "
                   f"{', '.join(r.downlinks)}")
        if r.reason:
            typer.echo(f"      {r.code + ': ' if r.code else ''}{r.reason}")


def _spans(rows: list[KernelListing]) -> dict[int, tuple[str, str]]:
    """Each kernel's coverage ends as ISO UTC (the LSK bundled with pwm converts them)."""
    from pwm.io.spice_kernels import bundled_kernels, kernel_pool
    from service.kernels import et_to_datetime

    with kernel_pool([bundled_kernels()["naif0012.tls"]]):
        return {r.id: (et_to_datetime(r.coverage[0]).isoformat(),
                       et_to_datetime(r.coverage[1]).isoformat())
                for r in rows if r.coverage is not None}


@kernels_app.command("retire")
def retire(
    kernel_id: int = typer.Argument(..., help="the kernel's id (pwm kernels)"),
    reason: str = typer.Option("retired by an operator", help="why, recorded with it"),
) -> None:
    """Retire a kernel: it is no longer loaded for any ingest, and a later delivery of the same
    file does not bring it back. The images whose geometry it may have served lose it, with a
    reason naming the retirement; each one's downlink's next ingest computes it again from the
    kernels left, against the current model (`pwm run DIR`, which also adjusts their poses again
    and refines the maplets whose images changed)."""
    from service.catalog import open_catalog
    from service.db import session_scope
    from service.kernels import retire_kernel

    try:
        with session_scope(open_catalog()) as session:
            done = retire_kernel(session, kernel_id, reason=reason)
    except LookupError as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(1) from None
    typer.echo(f"kernel {done.kernel_id} ({done.name}) retired; {done.images} images lost their "
               "geometry")
    for name, path in done.downlinks:
        typer.echo(f"  judged again at the next ingest of downlink {name}: pwm run {path}")
